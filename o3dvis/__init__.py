"""o3dvis: neural visibility of point sets, as an Open3D plugin."""

from .data import visibility_from_mesh

__version__ = "0.1.0"
__all__ = ["visibility_from_mesh"]
