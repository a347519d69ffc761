"""Labelled data for training and evaluation: procedural shapes and scenes, prepared samples, datasets.

The shapes load on first use, so that training from prepared samples runs where Open3D (which
making shapes and labelling meshes need) is not installed.
"""

from importlib import import_module

from .prepare import label_mesh, prepare
from .sample import Sample, list_samples, load_sample, save_sample

__all__ = ["random_shape", "write_shapes", "label_mesh", "load_sample", "save_sample", "list_samples", "prepare",
           "Sample"]


def __getattr__(name: str):
    if name in ("random_shape", "write_shapes"):
        return getattr(import_module(".shapes", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
