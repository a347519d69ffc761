"""Labelled data: ray-cast ground truth, procedural shapes, prepared samples, datasets."""

from .groundtruth import sample_viewpoints, visibility_from_mesh
from .prepare import Sample, label_mesh, load_sample, prepare
from .shapes import random_shape, write_shapes

__all__ = ["visibility_from_mesh", "sample_viewpoints", "random_shape", "write_shapes",
           "label_mesh", "load_sample", "prepare", "Sample"]
