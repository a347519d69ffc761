"""Reading maps, checked: a file that is cut short, corrupted or misread gives a ``ValueError``
that names the file and the problem, never points made of garbage.

:func:`read_point_cloud` reads point clouds in the formats Open3D reads (PLY, PCD, XYZ, XYZN,
XYZRGB, PTS; :mod:`o3dvis.io.clouds`) and LAS, LAZ and E57 maps (:mod:`o3dvis.io.scanners`,
optional extras ``las`` and ``e57``).
"""

from .clouds import SUFFIXES, read_point_cloud

__all__ = ["read_point_cloud", "SUFFIXES"]
