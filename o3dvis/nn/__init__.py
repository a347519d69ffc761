"""The torch core of o3dvis: octree, sparse convolutions, U-Net, noise and view cues, predictor.

Nothing in this package imports Open3D.
"""

from .conv import OctreeConv, OctreeDownsample, OctreeUpsample
from .cues import view_cues
from .features import LeafFeatures
from .network import NetworkConfig, VisibilityNetwork
from .noise import noise_cues
from .octree import Octree, morton_decode, morton_encode, morton_order, normalize_points
from .predictor import ViewEmbedding, VisibilityPredictor
from .unet import OctreeUNet

__all__ = ["Octree", "morton_encode", "morton_decode", "morton_order", "normalize_points", "OctreeConv",
           "OctreeDownsample", "OctreeUpsample", "OctreeUNet",
           "ViewEmbedding", "VisibilityPredictor", "LeafFeatures", "view_cues", "noise_cues", "NetworkConfig",
           "VisibilityNetwork"]
