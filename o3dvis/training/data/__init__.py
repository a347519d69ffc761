"""Labelled data for training and evaluation: procedural shapes, prepared samples, datasets."""

from .prepare import Sample, label_mesh, load_sample, prepare
from .shapes import random_shape, write_shapes

__all__ = ["random_shape", "write_shapes", "label_mesh", "load_sample", "prepare", "Sample"]
