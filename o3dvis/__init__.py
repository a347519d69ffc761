"""o3dvis: neural visibility of point sets, as an Open3D plugin.

Main entry points::

    mesh, pt_map = o3dvis.hidden_point_removal_neural(pcd, camera_location)   # drop-in for HPR
    vis = o3dvis.NeuralVisibility.pretrained()       # shipped weights, sha256-checked
    field = vis.encode(pcd)                          # U-Net once per cloud
    mask = field.query(cameras)                      # (V, N) bool
    prob = field.probabilities(cameras)              # (V, N) torch, differentiable in the cameras
    visible = o3dvis.select_visible(pcd, camera)     # a PointCloud with colours and normals
    frame = o3dvis.visible_in_frame(pcd, params)     # a pinhole frame: visible indices, pixels, depths
    for frame in o3dvis.frames(pcd, trajectory):     # a trajectory of frames over one map
    o3dvis.set_num_threads(1)                        # fixed CPU threads (default: see o3dvis.threads)

Naming: a function that stands in for an Open3D method is named after it with ``_neural``
appended (``hidden_point_removal_neural``, ``estimate_normals_neural``,
``orient_normals_neural``) and takes the cloud, then Open3D's arguments in Open3D's order;
the others have no Open3D counterpart and a plain name. Every function that runs the network
takes the source of visibility as ``model=`` (default: the shipped network).
"""

import importlib
import importlib.util

from . import clib

__version__ = "0.1.0"

# each public name and the module that defines it, imported on first use: ``import o3dvis`` (and
# ``o3dvis --help``) loads no torch and no Open3D before they are needed
_EXPORTS = {
    "NeuralVisibility": "neural", "VisibilityField": "field",
    "hidden_point_removal_neural": "dropins", "select_visible": "dropins", "register": "dropins",
    "load_model": "models", "available_models": "models", "visibility_from_mesh": "groundtruth",
    "hidden_point_removal_mask": "baselines", "exponential_hpr_mask": "baselines",
    "set_num_threads": "threads", "get_num_threads": "threads",
    **dict.fromkeys(["estimate_normals_neural", "orient_normals_neural", "reconstruct_view_dependent",
                     "reconstruct_poisson", "shadow_map", "points_in_shadow", "render_with_shadows", "best_view",
                     "render_points", "depth_image", "visible_in_frame", "frames", "Frame", "FrameMap"], "apps"),
    "frames_on_ray": "cluster",
}
__all__ = list(_EXPORTS)
clib.warn_unbuilt()


def __getattr__(name: str):
    """A public name, or a subpackage, imported on first use."""
    if name in _EXPORTS:
        value = getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
    elif not name.startswith("__") and importlib.util.find_spec(f"{__name__}.{name}") is not None:
        value = importlib.import_module(f".{name}", __name__)
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_EXPORTS})
