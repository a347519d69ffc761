"""Applications of point visibility on Open3D geometry: oriented normals, reconstruction,
shadows, best views, headless renders and the camera frames of a map. Each takes the source of
visibility as ``model=``, as the Open3D drop-ins do (default: the pretrained neural network; see
:mod:`o3dvis.methods`).
"""

from ..cameras import fibonacci_sphere
from .pinhole import PinholeView, make_view
from ..methods import ground_truth_method, resolve_method
from .map_frames import Frame, FrameMap, frames, visible_in_frame
from .normals import estimate_normals_neural, orient_normals_neural
from .reconstruction import reconstruct_poisson, reconstruct_view_dependent
from .render import depth_image, render_points
from .shadows import points_in_shadow, render_with_shadows, shadow_map
from .views import best_view

__all__ = ["estimate_normals_neural", "orient_normals_neural", "reconstruct_view_dependent",
           "reconstruct_poisson", "shadow_map", "points_in_shadow", "render_with_shadows",
           "best_view", "render_points", "depth_image", "ground_truth_method", "resolve_method",
           "PinholeView", "make_view", "fibonacci_sphere", "visible_in_frame", "frames", "Frame", "FrameMap"]
