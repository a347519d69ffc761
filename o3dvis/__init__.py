"""o3dvis: neural visibility of point sets, as an Open3D plugin.

Main entry points::

    mesh, pt_map = o3dvis.hidden_point_removal_neural(pcd, camera_location)   # drop-in for HPR
    vis = o3dvis.NeuralVisibility.pretrained()       # shipped weights, sha256-checked
    field = vis.encode(pcd)                          # U-Net once per cloud
    mask = field.query(cameras)                      # (V, N) bool
    prob = field.probabilities(cameras)              # (V, N) torch, differentiable in the cameras
    visible = o3dvis.select_visible(pcd, camera)     # a PointCloud with colours and normals
"""

from .apps import (best_view, depth_image, estimate_normals_neural, orient_normals_neural,
                   points_in_shadow, reconstruct_poisson, reconstruct_view_dependent, render_points,
                   render_with_shadows, shadow_map)
from .baselines import exponential_hpr_mask, hidden_point_removal_mask
from .data import visibility_from_mesh
from .models import available_models, load_model
from .visibility import (NeuralVisibility, VisibilityField, hidden_point_removal_neural, register,
                         select_visible)

__version__ = "0.1.0"
__all__ = ["NeuralVisibility", "VisibilityField", "hidden_point_removal_neural", "select_visible",
           "register", "load_model", "available_models", "visibility_from_mesh",
           "hidden_point_removal_mask", "exponential_hpr_mask", "estimate_normals_neural",
           "orient_normals_neural", "reconstruct_view_dependent", "reconstruct_poisson", "shadow_map",
           "points_in_shadow", "render_with_shadows", "best_view", "render_points", "depth_image"]
