"""Reading maps and camera poses, checked: a file that is cut short, corrupted or misread gives a
``ValueError`` that names the file and the problem, never points or poses made of garbage.

- :func:`read_point_cloud`: point clouds in the formats Open3D reads (PLY, PCD, XYZ, XYZN,
  XYZRGB, PTS; :mod:`o3dvis.io.clouds`) and LAS, LAZ and E57 maps (:mod:`o3dvis.io.scanners`,
  optional extras ``las`` and ``e57``).
- :func:`read_poses`: cameras as an ``o3d.camera.PinholeCameraTrajectory`` with a name per frame
  (:class:`Poses`), from Open3D's trajectory JSON and LOG files and COLMAP models
  (:mod:`o3dvis.io.poses`, :mod:`o3dvis.io.colmap`).
"""

from .clouds import SUFFIXES, read_point_cloud
from .poses import Poses, read_poses

__all__ = ["read_point_cloud", "SUFFIXES", "read_poses", "Poses"]
