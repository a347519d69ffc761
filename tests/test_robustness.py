"""Bad input for every public function of o3dvis: a correct answer or a clear error, never a dead process.

The matrix crosses the functions of ``o3dvis.__all__`` with degenerate clouds and cameras. Each cell
either raises the expected ValueError/TypeError (its message must name the problem) or returns an
answer checked against an independent truth:

* ``all``: nothing can hide anything (1-3 points, one repeated point, a plane or a line seen from
  off it, a sphere seen from its centre by HPR), so every point is visible, and an application's
  answer equals its answer under a method that says so;
* ``same``: the cloud and camera moved by 1e6 give the unmoved answer (float64), or the answer of the
  float64 copy of the same float32 data; a list gives the answer of the array;
* ``pairs``: a cloud listed twice gives both copies of a point the same answer.

The command line's readers get their own matrix: crafted point cloud files (cut short, counts
overstated, not points, folders, headers Open3D's reader misreads) through every command that reads a
cloud, and bad checkpoints through ``calibrate`` and ``publish``: exit code != 0 and one line naming
the problem, nothing created. PCD files that crash Open3D's reader go through a command in a child.

Open3D and qhull calls (HPR baselines, triangulations, Poisson, ray casting) run in one child
process, so a segfault or an abort fails the cell it happened in instead of killing pytest. Cells
that tests/test_api.py or tests/test_baselines.py already cover are left out. The 10 M-point test
runs only with ``O3DVIS_LARGE=1`` (see benchmarks/large_cloud.py for time and memory).
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import torch
from scipy.spatial import cKDTree

import o3dvis
from o3dvis.apps import fibonacci_sphere

from conftest import lzf_literal

SPHERE = fibonacci_sphere(160)
CAMERA = np.array([0.4, -0.3, 3.0])
OFFSET = np.array([1e6, -1e6, 1e6])
GRID = np.stack(np.meshgrid(np.linspace(0, 1, 12), np.linspace(0, 2, 12)), axis=-1).reshape(-1, 2)
PLANE = np.c_[GRID, np.zeros(len(GRID))]
LINE = np.c_[np.linspace(0, 1, 30), np.zeros(30), np.zeros(30)]
SPHERE32 = (100 * SPHERE + OFFSET).astype(np.float32)
HAIR_OFF_PLANE = PLANE + np.c_[np.zeros((len(PLANE), 2)), 1e-9 * np.random.default_rng(0).normal(size=len(PLANE))]
FAR, NEAR_FAR = 1e9 * np.array([0.3, -0.4, 0.5]), 1e7 * np.array([0.3, -0.4, 0.5])
"""A camera 10^9 away from the unit sphere, and one 10^7 away in the same direction: both the
orthographic view in that direction. (From 10^4 away the direction to the cloud's centre, which is
not the origin, differs by about 10^-7, two float32 steps: a network with bfloat16 products tells
such directions apart, by up to 3e-4 in a probability.)"""


FAR_TRIANGLE = (np.array([[-9.0, -9.0, -9.0], [-8.0, -9.0, -9.0], [-9.0, -8.0, -9.0]]), np.array([[0, 1, 2]]))
"""A mesh behind every camera of the matrix: it hides nothing (in the frame of the unmoved clouds)."""


def all_visible(points, cameras) -> np.ndarray:
    """The visibility method of a cloud in which nothing hides anything."""
    return np.ones((len(cameras), len(points)), dtype=bool)


def _outside(points: np.ndarray) -> np.ndarray:
    """A camera above the bounding box, off every line and plane of the clouds below."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    return (lo + hi) / 2 + max(float(np.linalg.norm(hi - lo)), 1.0) * np.array([0.13, -0.11, 1.7])


# ------------------------------------------------------------------------------ the cases

@dataclass(frozen=True)
class Case:
    """One bad input: the cloud's data, the camera, and the expected error or truth.

    Attributes:
        points: the cloud as data (float64 arrays become legacy Open3D clouds, float32 arrays
            tensor clouds, anything else is passed as it is).
        camera: the camera (default: one outside the cloud).
        error: ``(type, regex)`` by family (``"*"``: any) when the input must be refused.
        truth: ``"all"``, ``"same"``, ``"pairs"`` or ``"valid"`` (a well-formed answer).
        base: for ``"same"``: the points and camera whose answer it must equal, and the origin
            subtracted from positions in the answer.
    """

    points: object
    camera: object = None
    error: dict = field(default_factory=dict)
    truth: str = "valid"
    base: tuple | None = None

    def cam(self):
        return _outside(np.asarray(self.points, dtype=np.float64)) if self.camera is None else self.camera


_NAN = (ValueError, "(?i)nan|finite")
_SHAPE = (ValueError, "shape")
_REAL = (TypeError, "real numbers")
_NOT_PCD = (TypeError, "PointCloud")
_ONE = (ValueError, "one")

CASES: dict[str, Case] = {
    "empty cloud": Case(np.zeros((0, 3)), CAMERA, {"*": (ValueError, "empty")}),
    "1 point": Case(np.array([[0.1, 0.2, 0.3]]), truth="all"),
    "2 points": Case(np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]), truth="all"),
    "3 points": Case(np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]), truth="all"),
    "one point 10 times": Case(np.repeat([[0.5, -0.5, 2.0]], 10, axis=0), truth="all"),
    "cloud listed twice": Case(np.r_[SPHERE, SPHERE], CAMERA, truth="pairs"),
    "planar": Case(PLANE, truth="all"),
    "a hair off planar (1e-9)": Case(HAIR_OFF_PLANE, truth="all"),
    "camera 1e9 away": Case(SPHERE, FAR, truth="same", base=(SPHERE, NEAR_FAR, np.zeros(3))),
    "collinear": Case(LINE, truth="all"),
    "offset 1e6 float64": Case(SPHERE + OFFSET, CAMERA + OFFSET, truth="same", base=(SPHERE, CAMERA, OFFSET)),
    "offset 1e6 float32": Case(SPHERE32, 100 * CAMERA + OFFSET, truth="same",
                               base=(SPHERE32.astype(np.float64) - OFFSET, 100 * CAMERA, OFFSET)),
    "NaN point": Case(np.r_[SPHERE, [[np.nan, 0.0, 0.0]]], CAMERA, {"*": _NAN}),
    "Inf point": Case(np.r_[SPHERE, [[0.0, -np.inf, 0.0]]], CAMERA, {"*": _NAN}),
    "NaN camera": Case(SPHERE, [0.0, np.nan, 3.0], {"*": _NAN}),
    "Inf camera": Case(SPHERE, [0.0, 0.0, np.inf], {"*": _NAN}),
    "camera at a point": Case(SPHERE, SPHERE[7], {"*": (ValueError, "on a point"),
                                                  "array": (ValueError, "coincides")}),
    # answered from inside (a well-formed answer); HPR sees all of a sphere from its centre
    "camera inside the cloud": Case(SPHERE, np.zeros(3)),
    "points of shape (N, 2)": Case(SPHERE[:, :2], CAMERA, {"*": _SHAPE, "pcd": _NOT_PCD}),
    "points of shape (1, N, 3)": Case(SPHERE[None], CAMERA, {"*": _SHAPE, "pcd": _NOT_PCD}),
    "complex points": Case(SPHERE.astype(complex), CAMERA, {"*": _REAL, "pcd": _NOT_PCD}),
    "bool points": Case(SPHERE > 0, CAMERA, {"*": _REAL, "pcd": _NOT_PCD}),
    "string points": Case(np.array([["1", "2", "3"]]), CAMERA, {"*": _REAL, "pcd": _NOT_PCD}),
    "points as a list": Case(SPHERE.tolist(), CAMERA, {"*": _NOT_PCD, "array": None}, truth="same",
                             base=(SPHERE, CAMERA, np.zeros(3))),
    "camera of 2 numbers": Case(SPHERE, [0.0, 3.0], {"*": _SHAPE}),
    "camera as a string": Case(SPHERE, "0,0,3", {"*": _REAL}),
    "two cameras": Case(SPHERE, [CAMERA, -CAMERA], {"*": _ONE}),
}


# ------------------------------------------------------------------------------ the functions

def as_cloud(points):
    """A float64 (N, 3) array as a legacy PointCloud, a float32 one as a tensor PointCloud, else as is."""
    if isinstance(points, np.ndarray) and points.ndim == 2 and points.shape[1] == 3:
        if points.dtype == np.float64:
            return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        if points.dtype == np.float32:
            return o3d.t.geometry.PointCloud(o3d.core.Tensor(points))
    return points


def _tagged(cloud):
    """A copy of a cloud whose points carry their index (colour / attribute), to read back a selection."""
    if isinstance(cloud, o3d.geometry.PointCloud):
        tagged = o3d.geometry.PointCloud(cloud)
        n = len(cloud.points)
        tagged.colors = o3d.utility.Vector3dVector(np.c_[np.arange(n) / max(n, 1), np.zeros((n, 2))])
        return tagged
    if isinstance(cloud, o3d.t.geometry.PointCloud):
        tagged = cloud.clone()
        tagged.point["index"] = o3d.core.Tensor(np.arange(len(cloud.point.positions))[:, None])
        return tagged
    return cloud


def _selected(result, n: int) -> np.ndarray:
    if isinstance(result, o3d.geometry.PointCloud):
        index = np.rint(np.asarray(result.colors)[:, 0] * n).astype(np.int64)
    else:
        index = result.point["index"].numpy()[:, 0]
    assert (np.diff(index) > 0).all(), "the selection is not in the cloud's order"
    mask = np.zeros(n, dtype=bool)
    mask[index] = True
    return mask


def _points_of(cloud) -> np.ndarray:
    if isinstance(cloud, o3d.geometry.PointCloud):
        return np.asarray(cloud.points)
    if isinstance(cloud, o3d.t.geometry.PointCloud):
        return cloud.point.positions.numpy().astype(np.float64)
    return np.asarray(cloud, dtype=np.float64)


def _mask_answer(mask, n: int) -> dict:
    mask = np.asarray(mask)
    assert mask.dtype == bool and mask.shape in ((n,), (1, n)), (mask.dtype, mask.shape)
    return {"visible": mask.reshape(n)}


def _hpr_neural(cloud, camera, vis):
    mesh, pt_map = o3dvis.hidden_point_removal_neural(cloud, camera, model=vis, triangulate=True)
    vertices = (np.asarray(mesh.vertices) if isinstance(mesh, o3d.geometry.TriangleMesh)
                else mesh.vertex.positions.numpy())
    index = np.asarray(pt_map if isinstance(pt_map, list) else pt_map.numpy(), dtype=np.int64)
    np.testing.assert_array_equal(vertices, _points_of(cloud)[index].astype(vertices.dtype))
    return index


def _index_answer(index, n: int) -> dict:
    mask = np.zeros(n, dtype=bool)
    mask[index] = True
    return {"visible": mask}


def _probability_answer(probs, n: int) -> dict:
    assert isinstance(probs, torch.Tensor) and probs.shape == (1, n)
    probs = probs[0].numpy()
    assert ((probs >= 0) & (probs <= 1)).all()
    return {"visible": probs > 0.5, "probability": probs}


def _image_answer(image, shape: tuple, dtype) -> dict:
    array = np.asarray(image)
    assert array.shape == shape and array.dtype == dtype and np.isfinite(array).all()
    assert (array >= 0).all()
    return {"image": array}


def _mesh_answer(mesh, origin) -> dict:
    vertices, triangles = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    assert np.isfinite(vertices).all()
    assert len(triangles) == 0 or (triangles.min() >= 0 and triangles.max() < len(vertices))
    return {"vertices": vertices - origin, "triangles": triangles}


def _same_surface(answer: dict, expected: dict, what: str) -> None:
    """Poisson meshes come in a thread-dependent order: compare vertex sets (both ways)."""
    a, b = answer["vertices"], expected["vertices"]
    tolerance = 1e-5 * np.linalg.norm(b.max(axis=0) - b.min(axis=0))
    far = max(cKDTree(b).query(a)[0].max(), cKDTree(a).query(b)[0].max())
    assert far <= tolerance, f"the surface is {far:.3g} away from {what} (tolerance {tolerance:.3g})"


def _normals_answer(pcd, n: int) -> dict:
    normals = np.asarray(pcd.normals) if isinstance(pcd, o3d.geometry.PointCloud) else pcd.point.normals.numpy()
    assert normals.shape == (n, 3)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)
    return {"normals": normals}


def _axes(answer: dict) -> dict:
    """Normals up to their sign (each turned so that its largest coordinate is positive)."""
    normals = answer["normals"]
    sign = np.sign(normals[np.arange(len(normals)), np.abs(normals).argmax(axis=1)])
    return {"normals": normals * sign[:, None]}


def _with_normals(cloud):
    """A copy of a cloud with Open3D's PCA normals, for orient_normals_neural to orient.

    The normals are estimated on the centred points: Open3D's PCA loses digits far from the origin.
    """
    if not isinstance(cloud, (o3d.geometry.PointCloud, o3d.t.geometry.PointCloud)):
        return cloud
    legacy = o3d.geometry.PointCloud(cloud if isinstance(cloud, o3d.geometry.PointCloud) else cloud.to_legacy())
    centred = o3d.geometry.PointCloud(legacy).translate(-legacy.get_axis_aligned_bounding_box().get_center())
    centred.estimate_normals()
    legacy.normals = centred.normals
    return legacy


def _best_view_answer(result, points: np.ndarray, origin) -> dict:
    camera, loss = result
    lo, hi = points.min(axis=0), points.max(axis=0)
    assert camera.shape == (3,) and np.isfinite(camera).all() and np.isfinite(loss).all()
    np.testing.assert_allclose(np.linalg.norm(camera - (lo + hi) / 2), np.linalg.norm(hi - lo), rtol=1e-6)
    return {"camera": camera - origin, "loss": loss}


@dataclass(frozen=True)
class Func:
    """A public function as the matrix calls it.

    Attributes:
        family: ``"pcd"`` takes Open3D clouds only, ``"any"`` clouds or arrays, ``"array"`` arrays or lists.
        call: ``call(cloud, camera, method)``; ``method`` is the shared model or ``all_visible``.
        answer: ``answer(result, points, origin)`` checks the result's form and returns its
            answer as arrays (positions relative to ``origin``).
        camera: whether the function takes a camera.
        method: whether the function takes a visibility method (else: a mask answer).
        risky: runs Open3D/qhull on the input: only in the child process.
        errors: case name -> ``(type, regex)`` where this function answers differently.
        skip: cases that another test file covers for this function.
        truths: case name -> truth where this function's answer is only ``"valid"``.
        canonical: maps an answer to what the ``all`` truth compares (default: all of it).
        same: ``same(answer, expected, what)`` asserts two answers equal (default: array by array).
    """

    family: str
    call: Callable
    answer: Callable
    camera: bool = True
    method: bool = True
    risky: bool = False
    errors: dict = field(default_factory=dict)
    skip: frozenset = frozenset()
    truths: dict = field(default_factory=dict)
    canonical: Callable | None = None
    same: Callable | None = None


_NO_VOLUME = (ValueError, "no volume")
# Functions that read any cloud's points before asking for an Open3D cloud report the array's problem.
_ARRAY_CHECKED_FIRST = {"points of shape (N, 2)": _SHAPE, "points of shape (1, N, 3)": _SHAPE,
                        "complex points": _REAL, "bool points": _REAL, "string points": _REAL}
_TOO_FEW = (ValueError, "too few or all on one line")
_TEST_API = frozenset({"empty cloud", "NaN point", "Inf point", "NaN camera", "Inf camera",
                       "camera at a point", "camera inside the cloud", "points of shape (N, 2)",
                       "points of shape (1, N, 3)", "complex points", "bool points", "points as a list",
                       "camera of 2 numbers", "camera as a string"})
_TEST_BASELINES = frozenset({"empty cloud", "NaN point", "1 point", "2 points", "3 points",
                             "one point 10 times", "cloud listed twice", "planar", "collinear",
                             "a hair off planar (1e-9)", "camera 1e9 away",
                             "camera at a point", "points of shape (N, 2)"})
_IMAGE = (24, 32)
_LIGHT_ON_A_POINT = (ValueError, "^the light at .* lies on a point")
_FAR_PICTURE = {"camera 1e9 away": "valid"}  # framed anew at each distance (tests/test_view_limits.py)

FUNCS: dict[str, Func] = {
    "select_visible": Func(
        "any", lambda c, cam, vis: o3dvis.select_visible(_tagged(c), cam, model=vis),
        lambda r, p, o: {"visible": _selected(r, len(p))}, method=False),
    "hidden_point_removal_neural": Func(
        "pcd", lambda c, cam, vis: _hpr_neural(c, cam, vis), lambda r, p, o: _index_answer(r, len(p)),
        method=False, risky=True),
    "NeuralVisibility.encode/VisibilityField.query": Func(
        "any", lambda c, cam, vis: vis.encode(c).query(cam), lambda r, p, o: _mask_answer(r, len(p)),
        method=False, skip=_TEST_API | {"two cameras"}),
    "VisibilityField.probabilities": Func(
        "any", lambda c, cam, vis: vis.encode(c).probabilities(cam),
        lambda r, p, o: _probability_answer(r, len(p)), method=False, skip=_TEST_API | {"two cameras"}),
    "points_in_shadow": Func(
        "any", lambda c, cam, m: ~o3dvis.points_in_shadow(c, cam, m), lambda r, p, o: _mask_answer(r, len(p)),
        errors={"camera at a point": _LIGHT_ON_A_POINT}),
    "shadow_map": Func(
        "any", lambda c, cam, m: o3dvis.shadow_map(c, cam, 32, m),
        lambda r, p, o: _image_answer(r, (32, 32), np.float32), risky=True, truths=_FAR_PICTURE,
        errors={"camera at a point": _LIGHT_ON_A_POINT}),
    "depth_image": Func(
        "any", lambda c, cam, m: o3dvis.depth_image(c, cam, width=32, height=24, model=m),
        lambda r, p, o: _image_answer(r, _IMAGE, np.float32), truths=_FAR_PICTURE),
    "render_points": Func(
        "pcd", lambda c, cam, m: o3dvis.render_points(c, cam, True, 32, 24, m),
        lambda r, p, o: _image_answer(r, (*_IMAGE, 3), np.uint8), truths=_FAR_PICTURE),
    "render_with_shadows": Func(
        "pcd", lambda c, cam, m: o3dvis.render_with_shadows(c, cam, cam, 32, 24, m),
        lambda r, p, o: _image_answer(r, (*_IMAGE, 3), np.uint8), truths=_FAR_PICTURE),
    "reconstruct_view_dependent": Func(
        "pcd", lambda c, cam, m: o3dvis.reconstruct_view_dependent(c, cam, m),
        lambda r, p, o: _mesh_answer(r, o), risky=True, truths=_FAR_PICTURE),
    "estimate_normals_neural": Func(
        "pcd", lambda c, cam, m: o3dvis.estimate_normals_neural(c, num_views=6, model=m, refine_views=4),
        lambda r, p, o: _normals_answer(r, len(p)), camera=False, risky=True, canonical=_axes,
        errors={"1 point": _NO_VOLUME, "one point 10 times": _NO_VOLUME, "2 points": _TOO_FEW,
                "3 points": _TOO_FEW, "collinear": _TOO_FEW, **_ARRAY_CHECKED_FIRST}),
    "orient_normals_neural": Func(
        "pcd", lambda c, cam, m: o3dvis.orient_normals_neural(_with_normals(c), 6, m, refine_views=4),
        lambda r, p, o: _normals_answer(r, len(p)), camera=False, risky=True, canonical=_axes,
        errors={"1 point": _NO_VOLUME, "one point 10 times": _NO_VOLUME, **_ARRAY_CHECKED_FIRST}),
    "reconstruct_poisson": Func(
        "pcd", lambda c, cam, m: o3dvis.reconstruct_poisson(c, 4, m, num_views=6)[0],
        lambda r, p, o: {"vertices": _mesh_answer(r, o)["vertices"]}, camera=False, risky=True,
        same=_same_surface, errors={"1 point": _NO_VOLUME, "one point 10 times": _NO_VOLUME, "2 points": _TOO_FEW,
                "3 points": _TOO_FEW, "collinear": _TOO_FEW},
        truths={"planar": "valid", "a hair off planar (1e-9)": "valid"}),  # an open sheet has no inside
    "best_view": Func(
        "any", lambda c, cam, m: o3dvis.best_view(c, steps=3, model=m, starts=2),
        lambda r, p, o: _best_view_answer(r, p, o), camera=False, method=False,
        errors={"1 point": _NO_VOLUME, "one point 10 times": _NO_VOLUME}),
    "hidden_point_removal_mask": Func(
        "array", lambda p, cam, m: o3dvis.hidden_point_removal_mask(p, cam, 1000.0),
        lambda r, p, o: _mask_answer(r, len(p)), method=False, risky=True, skip=_TEST_BASELINES | {"two cameras"},
        truths={"camera inside the cloud": "all"}),
    "exponential_hpr_mask": Func(
        "array", lambda p, cam, m: o3dvis.exponential_hpr_mask(p, cam, -0.01),
        lambda r, p, o: _mask_answer(r, len(p)), method=False, risky=True, skip=_TEST_BASELINES | {"two cameras"},
        truths={"camera inside the cloud": "all"}),
    "visibility_from_mesh": Func(
        "array", lambda p, cam, m: o3dvis.visibility_from_mesh(FAR_TRIANGLE, p, cam),
        lambda r, p, o: _mask_answer(r, len(p)), method=False, risky=True,
        errors={"empty cloud": None, "camera at a point": None}, truths={"cloud listed twice": "all"},
        skip=frozenset({"NaN point", "Inf camera", "points of shape (N, 2)", "camera of 2 numbers", "two cameras"})),
}


_BOX = o3d.geometry.TriangleMesh.create_box().translate([-0.5, -0.5, -0.5])
_BOX_ARRAYS = (np.asarray(_BOX.vertices), np.asarray(_BOX.triangles))
_CORNERS = np.asarray(_BOX.vertices)

MESH_CASES: dict[str, dict] = {
    "NaN vertex": dict(mesh=(np.r_[_BOX_ARRAYS[0][:-1], [[np.nan, 0, 0]]], _BOX_ARRAYS[1]),
                       error=(ValueError, "(?i)vertices.*(nan|finite)")),
    "complex vertices": dict(mesh=(_BOX_ARRAYS[0].astype(complex), _BOX_ARRAYS[1]), error=_REAL),
    "fractional triangle indices": dict(mesh=(_BOX_ARRAYS[0], _BOX_ARRAYS[1] + 0.5),
                                        error=(TypeError, "triangles")),
    "NaN tolerance": dict(tolerance=np.nan, error=(ValueError, "tolerance")),
    "negative tolerance": dict(tolerance=-1e-3, error=(ValueError, "tolerance")),
    # a mesh of zero area hides nothing; a camera on the surface sees the points it is on
    "zero-area triangles": dict(mesh=(np.zeros((3, 3)), np.array([[0, 1, 2]])), visible=np.ones(8, bool)),
    "collinear triangle": dict(mesh=(np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0.0]]), np.array([[0, 1, 2]])),
                               visible=np.ones(8, bool)),
    "camera on a corner": dict(cameras=_CORNERS[0], visible=np.arange(8) == 0),
}
"""visibility_from_mesh on bad meshes and parameters (the box's corners as the points, a camera at z = 3)."""


def run_mesh_case(name: str) -> None:
    spec = MESH_CASES[name]
    args = (spec.get("mesh", _BOX), _CORNERS, spec.get("cameras", [0.2, 0.1, 3.0]))
    if "error" in spec:
        with pytest.raises(spec["error"][0], match=spec["error"][1]):
            o3dvis.visibility_from_mesh(*args, tolerance=spec.get("tolerance", 1e-4))
        return
    np.testing.assert_array_equal(o3dvis.visibility_from_mesh(*args)[0], spec["visible"])


_PCD = as_cloud(SPHERE)

PARAMETERS: dict[str, tuple[Callable, tuple, bool]] = {
    "query threshold NaN": (lambda vis: vis.encode(SPHERE).query(CAMERA, threshold=np.nan),
                            (ValueError, "threshold"), False),
    "chunk_size 0": (lambda vis: o3dvis.NeuralVisibility(vis.network, chunk_size=0), (ValueError, "chunk_size"), False),
    "shadow_map resolution 0": (lambda vis: o3dvis.shadow_map(_PCD, CAMERA, 0, vis), (ValueError, "resolution"), False),
    "render_points width 0": (lambda vis: o3dvis.render_points(_PCD, CAMERA, True, 0, 24, vis),
                              (ValueError, "width"), False),
    "depth_image point_size NaN": (lambda vis: o3dvis.depth_image(_PCD, CAMERA, point_size=np.nan, model=vis),
                                   (ValueError, "point_size"), False),
    "render_with_shadows ambient 2": (lambda vis: o3dvis.render_with_shadows(_PCD, CAMERA, CAMERA, 32, 24, vis,
                                                                             ambient=2), (ValueError, "ambient"), False),
    "points spanning 2e308": (lambda vis: vis.encode(np.r_[SPHERE, [[-1e308, 0, 0], [1e308, 0, 0]]]),
                              (ValueError, "spans more than float64"), False),
    "render_points 10^6 x 10^6 pixels": (lambda vis: o3dvis.render_points(_PCD, CAMERA, True, 10**6, 10**6, vis),
                                         (ValueError, "1000000000000 pixels"), False),
    "shadow_map resolution 10^5": (lambda vis: o3dvis.shadow_map(_PCD, CAMERA, 10**5, vis), (ValueError, "pixels"),
                                   False),
    "best_view steps 0": (lambda vis: o3dvis.best_view(_PCD, steps=0, model=vis), (ValueError, "steps"), False),
    "best_view negative distance": (lambda vis: o3dvis.best_view(_PCD, steps=2, model=vis, distance=-1.0),
                                    (ValueError, "distance"), False),
    "estimate_normals_neural 0 views": (lambda vis: o3dvis.estimate_normals_neural(o3d.geometry.PointCloud(_PCD), num_views=0, model=vis),
                                        (ValueError, "num_views"), False),
    # Open3D's Poisson raises on an octree of fewer than 2 levels, then aborts the process at exit
    "reconstruct_poisson depth 1": (lambda vis: o3dvis.reconstruct_poisson(_PCD, 1, vis, num_views=6),
                                    (ValueError, "depth"), True),
    # Open3D's Poisson crashes the process, or exhausts memory, on an octree this deep
    "reconstruct_poisson depth 30": (lambda vis: o3dvis.reconstruct_poisson(_PCD, 30, vis, num_views=6),
                                     (ValueError, "depth=30"), True),
    "reconstruct_poisson width of the cloud": (lambda vis: o3dvis.reconstruct_poisson(_PCD, 8, vis, num_views=6,
                                                                                      width=2.0),
                                               (ValueError, "width"), True),
}
"""Bad parameters other than the cloud and camera: the call, the error, and whether it is risky."""


def _expected_error(func: Func, name: str, case: Case):
    if name in func.errors:
        return func.errors[name]
    return case.error.get(func.family, case.error.get("*"))


def _call(func: Func, points, camera, method):
    cloud = points if func.family == "array" else as_cloud(points)
    return func.call(cloud, camera, method)


def _assert_same(answer: dict, expected: dict, what: str) -> None:
    assert answer.keys() == expected.keys()
    for key, value in expected.items():
        assert np.shape(answer[key]) == np.shape(value), f"{key} of {what}: {np.shape(answer[key])} vs {np.shape(value)}"
        if np.asarray(value).dtype == bool or np.asarray(value).dtype.kind in "iu":
            np.testing.assert_array_equal(answer[key], value, err_msg=f"{key} of {what}")
        else:
            np.testing.assert_allclose(answer[key], value, atol=1e-5, rtol=1e-6, err_msg=f"{key} of {what}")


def run_case(func_name: str, case_name: str, vis) -> None:
    """Runs one cell of the matrix; raises AssertionError (or pytest's Failed) when it goes wrong."""
    if func_name == "visibility_from_mesh (meshes)":
        return run_mesh_case(case_name)
    if func_name == "parameters":
        call, (error, message), _ = PARAMETERS[case_name]
        with pytest.raises(error, match=message):
            call(vis)
        return
    func, case = FUNCS[func_name], CASES[case_name]
    camera = case.cam()
    error = _expected_error(func, case_name, case)
    if error is not None:
        with pytest.raises(error[0], match=error[1]):
            _call(func, case.points, camera, vis)
        return
    points = np.asarray(case.points, dtype=np.float64)
    origin = case.base[2] if case.base else np.zeros(3)
    answer = func.answer(_call(func, case.points, camera, vis), points, origin)
    truth = func.truths.get(case_name, case.truth)
    if truth == "all":
        if "visible" in answer:
            assert answer["visible"].all(), f"{(~answer['visible']).sum()} of {len(points)} points hidden"
        elif func.method:
            expected = func.answer(_call(func, case.points, camera, all_visible), points, origin)
            canonical = func.canonical or (lambda a: a)
            _assert_same(canonical(answer), canonical(expected), "the answer with every point visible")
    elif truth == "same":
        base_points, base_camera, _ = case.base
        base = func.answer(_call(func, base_points, base_camera, vis), base_points, np.zeros(3))
        (func.same or _assert_same)(answer, base, "the unmoved cloud")
    elif truth == "pairs" and "visible" in answer:
        half = len(points) // 2
        np.testing.assert_array_equal(answer["visible"][:half], answer["visible"][half:])
        assert 0 < answer["visible"].mean() < 1
    elif truth == "pairs" and "normals" in answer:
        half = len(points) // 2
        np.testing.assert_array_equal(answer["normals"][:half], answer["normals"][half:])


def _cells(risky: bool) -> list:
    cells = [pytest.param(f, c, id=f"{f}-{c}") for f, func in FUNCS.items() if func.risky == risky
             for c in CASES if c not in func.skip and (func.camera or not _camera_case(c))]
    if risky:
        cells += [pytest.param("visibility_from_mesh (meshes)", c, id=f"visibility_from_mesh-{c}")
                  for c in MESH_CASES]
    return cells + [pytest.param("parameters", c, id=c) for c, (_, _, r) in PARAMETERS.items() if r == risky]


def _camera_case(name: str) -> bool:
    return "camera" in name


@pytest.mark.parametrize("func_name, case_name", _cells(risky=False))
def test_bad_input(vis, func_name, case_name):
    run_case(func_name, case_name, vis)


# ------------------------------------------------------------------------------ Open3D/qhull in a child

_CHILD_TIMEOUT = 240


@pytest.fixture(scope="module")
def child_results() -> tuple[dict, subprocess.CompletedProcess]:
    """Runs every risky cell in one child process; returns its per-cell results and the process."""
    cells = [p.values[:2] for p in _cells(risky=True)]
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    proc = subprocess.run([sys.executable, __file__, json.dumps(cells)], capture_output=True, text=True,
                          env=env, timeout=_CHILD_TIMEOUT)
    results = {}
    for line in proc.stdout.splitlines():
        if line.startswith("{"):
            record = json.loads(line)
            results[(record["func"], record["case"])] = record
    return results, proc


@pytest.mark.parametrize("func_name, case_name", _cells(risky=True))
def test_bad_input_in_a_child_process(child_results, func_name, case_name):
    results, proc = child_results
    record = results.get((func_name, case_name))
    if record is None or "error" not in record:
        started = [line for line in proc.stdout.splitlines() if line.startswith("start ")]
        pytest.fail(f"the child process died (exit code {proc.returncode}) "
                    f"{'in ' + started[-1][6:] if started else 'before any cell'}: {proc.stderr[-2000:]}")
    assert record["error"] is None, record["error"]


def test_child_process_exits_normally(child_results):
    results, proc = child_results
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert len(results) == len(_cells(risky=True))


def _child(cells: list) -> None:
    torch.set_num_threads(1)
    vis = o3dvis.NeuralVisibility.pretrained()
    for func_name, case_name in cells:
        print(f"start {func_name} / {case_name}", flush=True)
        try:
            run_case(func_name, case_name, vis)
            error = None
        except BaseException as e:  # pytest's Failed is a BaseException
            error = f"{type(e).__name__}: {e}"[:3000]
        print(json.dumps({"func": func_name, "case": case_name, "error": error}), flush=True)


if __name__ == "__main__":
    _child(json.loads(sys.argv[1]))


# ------------------------------------------------------------------------------ 10 M points

@pytest.mark.skipif(os.environ.get("O3DVIS_LARGE") != "1",
                    reason="10 M points take minutes and ~5 GB: set O3DVIS_LARGE=1 (benchmarks/large_cloud.py "
                           "prints time and memory)")
def test_ten_million_points(vis):
    points = fibonacci_sphere(10_000_000)
    camera = np.array([0.3, -0.2, 3.0])
    mask = vis.encode(points).query(camera)
    assert mask.shape == (1, len(points)) and mask.dtype == bool
    truth = points @ camera > 1.0  # on the unit sphere, p is visible from c exactly when p . c > |p|^2
    assert (mask[0] == truth).mean() > 0.95


def test_a_flat_cloud_is_all_visible_from_off_its_plane_and_left_to_the_network_in_it():
    from o3dvis.nn import NetworkConfig, VisibilityNetwork

    torch.manual_seed(1)
    vis = o3dvis.NeuralVisibility(VisibilityNetwork(NetworkConfig(depth=5, channels=(8, 8, 8, 8),
                                                                  feature_channels=8, hidden=(16,))))
    tilted = PLANE @ o3d.geometry.get_rotation_matrix_from_xyz([0.3, -0.7, 1.1]).T + [5.0, -2.0, 7.0]
    noisy = tilted + 1e-13 * np.random.default_rng(0).normal(size=tilted.shape)
    normal = np.cross(tilted[1] - tilted[0], tilted[12] - tilted[0])
    normal /= np.linalg.norm(normal)
    in_plane = tilted.mean(axis=0) + 3 * (tilted[-1] - tilted[0])
    for cloud in (tilted, noisy):
        field = vis.encode(cloud)
        raw = o3dvis.VisibilityField(field.network, field.features, field.points, None,
                                     dataclasses.replace(field.frame, hull=None), rank=field.rank,
                                     matmul_dtype=field.matmul_dtype)  # without the flat rule
        off = [tilted.mean(axis=0) + 4 * normal, tilted.mean(axis=0) - 5 * normal]
        assert (field.probabilities(off) == 1).all() and not (raw.probabilities(off) == 1).all()
        torch.testing.assert_close(field.probabilities(in_plane), raw.probabilities(in_plane), rtol=0, atol=0)
        assert (field.probabilities(direction=normal) == 1).all()
        torch.testing.assert_close(field.probabilities(direction=tilted[1] - tilted[0]),
                                   raw.probabilities(direction=tilted[1] - tilted[0]), rtol=0, atol=0)
    sphere = vis.encode(SPHERE)
    assert sphere.frame.hull is None and not (sphere.probabilities(CAMERA) == 1).all()


# ------------------------------------------------------------------------------ the CLI's readers

def _ply(fmt: str, count: int, body: bytes, props: str = "property float x\nproperty float y\nproperty float z\n"
         ) -> bytes:
    return (f"ply\nformat {fmt} 1.0\nelement vertex {count}\n{props}end_header\n").encode() + body


def _pcd(data: str, points: int, body: bytes, fields: str = "x y z", sizes: str = "4 4 4", types: str = "F F F",
         counts: str = "1 1 1") -> bytes:
    return (f"VERSION 0.7\nFIELDS {fields}\nSIZE {sizes}\nTYPE {types}\nCOUNT {counts}\nWIDTH {points}\nHEIGHT 1\n"
            f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {points}\nDATA {data}\n").encode() + body


_XYZ = "".join(f"{x} {y} {z}\n" for x, y, z in SPHERE[:10]).encode()
_FLOATS = SPHERE[:10].astype(np.float32).tobytes()
_XYZ_PROPS = "property float x\nproperty float y\nproperty float z\n"

FILE_CASES: dict[str, tuple[str, bytes | None, str]] = {
    # name: (file name, content (None: the folder itself), the error's message)
    "binary PLY declaring 100000 vertices, holding 30 floats": (
        "lie.ply", _ply("binary_little_endian", 100_000, np.arange(30, dtype=np.float32).tobytes()),
        "truncated PLY.*element vertex 100000"),
    "binary PLY cut short": ("cut.ply", _ply("binary_little_endian", 10, _FLOATS[:-6]), "truncated PLY"),
    "ASCII PLY cut short": ("cut_ascii.ply", _ply("ascii", 10, _XYZ[:len(_XYZ) // 2]), "truncated PLY"),
    "PLY without end_header": ("open.ply", _ply("ascii", 10, b"").replace(b"end_header\n", b""), "end_header"),
    "PLY with a negative count": ("negative.ply", _ply("ascii", -3, _XYZ), "bad count"),
    "PLY of an unknown format": ("format.ply", _ply("binary_middle_endian", 10, _FLOATS), "unknown PLY format"),
    "PLY without vertices": ("faces.ply", b"ply\nformat ascii 1.0\nelement face 0\n"
                                          b"property list uchar int vertex_indices\nend_header\n", "no vertex"),
    "binary PCD cut short": ("cut.pcd", _pcd("binary", 10, _FLOATS[:-5]), "truncated PCD"),
    "ASCII PCD declaring 1000 points, holding 10": ("lie.pcd", _pcd("ascii", 1000, _XYZ), "truncated PCD.*1000"),
    "compressed PCD cut short": ("cut_compressed.pcd", _pcd("binary_compressed", 10, b"\x40\0\0\0\x78\0\0\0"),
                                 "compressed PCD"),
    "PLY vertex without z": ("xy.ply", _ply("binary_little_endian", 10, SPHERE[:10, :2].astype(np.float32).tobytes(),
                                            "property float x\nproperty float y\n"), "lacks z"),
    "PLY vertex with x as a list": ("list.ply", _ply("binary_little_endian", 10, b"".join(
        b"\x01" + row.tobytes() for row in SPHERE[:10].astype(np.float32)), "property list uchar float x\n"
        "property float y\nproperty float z\n"), "'x' is a list"),
    "PLY vertex with nx but no ny, nz": ("nx.ply", _ply("binary_little_endian", 10, np.c_[
        SPHERE[:10], SPHERE[:10, :1]].astype(np.float32).tobytes(), _XYZ_PROPS + "property float nx\n"),
        "lacks ny, nz"),
    "PLY vertex with red but no green, blue": ("red.ply", _ply("binary_little_endian", 10, b"".join(
        row.tobytes() + b"\x80" for row in SPHERE[:10].astype(np.float32)), _XYZ_PROPS + "property uchar red\n"),
        "lacks green, blue"),
    "PLY vertex declaring z before y": ("xzy.ply", _ply("binary_little_endian", 10, _FLOATS,
                                                       "property float x\nproperty float z\nproperty float y\n"),
                                        "'z' before x, y"),
    "ASCII PLY with a word for a number": ("word.ply", _ply("ascii", 10, b"abc" + _XYZ[_XYZ.index(b" "):]),
                                           "not lines of 3 numbers.*'abc'"),
    "PCD of TYPE F SIZE 2": ("half.pcd", _pcd("binary", 10, SPHERE[:10].astype(np.float16).tobytes(), sizes="2 2 2"),
                             "'x' is TYPE F SIZE 2"),
    "PCD of TYPE F SIZE 1": ("byte.pcd", _pcd("binary", 10, bytes(30), sizes="1 1 1"), "'x' is TYPE F SIZE 1"),
    "compressed PCD of TYPE F SIZE 8": ("double.pcd", _pcd("binary_compressed", 10, lzf_literal(
        SPHERE[:10].tobytes()), sizes="8 8 8"), "'x' is TYPE F SIZE 8.*binary_compressed"),
    "PCD with x of COUNT 2": ("count.pcd", _pcd("binary", 10, np.c_[SPHERE[:10, :1], SPHERE[:10]].astype(
        np.float32).tobytes(), counts="2 1 1"), "'x' is TYPE F SIZE 4 COUNT 2"),
    "PCD with a TYPE letter not F, I or U": ("type.pcd", _pcd("binary", 10, _FLOATS, types="F F Q"),
                                             "unknown TYPE 'Q'"),
    "PCD with 2 TYPE letters for 3 fields": ("types.pcd", _pcd("binary", 10, _FLOATS, types="F F"),
                                             "TYPE line has 2 values for 3 fields"),
    "PCD with COUNT before SIZE": ("order.pcd", _pcd("binary", 10, _FLOATS).replace(b"SIZE 4 4 4\n", b"").replace(
        b"COUNT 1 1 1\n", b"COUNT 1 1 1\nSIZE 4 4 4\n"), "SIZE line comes before its COUNT"),
    "PCD with DATA in upper case": ("upper.pcd", _pcd("BINARY", 10, _FLOATS), "unknown PCD data kind 'BINARY'"),
    "ASCII PCD with a line of 2 numbers": ("short.pcd", _pcd("ascii", 2, b"1 2\n3 4 5 6\n"), "line 1 of its data"),
    "compressed PCD with corrupted compressed data": ("lzf.pcd", _pcd("binary_compressed", 10, np.array(
        [124, 120], dtype="<u4").tobytes() + b"\x20\x00" + bytes(122)), "corrupted compressed PCD"),
    "PTS declaring 100 points, holding 10": ("lie.pts", b"100\n" + _XYZ, "declares 100 points but 10"),
    "XYZ with a line of two numbers": ("short.xyz", _XYZ + b"1.5 2.5\n", "line 11 .* not a point"),
    "XYZ with a line of words": ("words.xyz", b"x y z\n" + _XYZ, "line 1 .* not a point"),
    "XYZN with points of 3 numbers": ("three.xyzn", _XYZ, "line 1 .* not a point of 6"),
    "XYZ with a NaN point": ("nan.xyz", _XYZ + b"nan 0 0\n", "1 of 11 points have NaN"),
    "empty XYZ": ("empty.xyz", b"", "no points"),
    "unknown suffix": ("cloud.txt", _XYZ, "unknown point cloud format"),
    "a folder": ("folder.ply", None, "is a folder"),
    "a missing file": ("missing.ply", b"", "not found"),
}
"""Point cloud files the CLI must refuse: each command that reads a cloud prints one line naming the problem."""

_NORMAL_X = {"fields": "x y z normal_x", "sizes": "4 4 4 4", "types": "F F F F", "counts": "1 1 1 1"}
_NORMALS = {"fields": "x y z normal_x normal_y normal_z", "sizes": "4 4 4 4 4 4", "types": "F F F F F F",
            "counts": "1 1 1 1 1 1"}
CRASH_CASES: dict[str, tuple[str, bytes, str]] = {
    "ASCII PCD with normal_x but no normal_y, normal_z": (
        "normal_ascii.pcd", _pcd("ascii", 1, b"1 2 3 4\n", **_NORMAL_X), "lacks normal_y, normal_z"),
    "binary PCD with normal_x but no normal_y, normal_z": (
        "normal_binary.pcd", _pcd("binary", 1, np.float32([1, 2, 3, 4]).tobytes(), **_NORMAL_X),
        "lacks normal_y, normal_z"),
    "compressed PCD with normal_x but no normal_y, normal_z": (
        "normal_compressed.pcd", _pcd("binary_compressed", 1, lzf_literal(np.float32([1, 2, 3, 4]).tobytes()),
                                      **_NORMAL_X), "lacks normal_y, normal_z"),
    "compressed PCD with one corrupted header byte (normal_Y)": (
        "corrupted.pcd", _pcd("binary_compressed", 1, lzf_literal(np.float32([1, 2, 3, 0, 0, 1]).tobytes()), **_NORMALS
                              ).replace(b"normal_y", b"normal_Y"), "lacks normal_y"),
}
"""PCD files Open3D's reader crashes the process on (SIGSEGV): refused by the command in a child process."""

CLI_READERS = {
    "visible": ["--camera", "0,0,3", "-o", "{out}.ply"],
    "normals": ["-o", "{out}.ply"],
    "reconstruct": ["-o", "{out}.ply"],
    "shadow": ["--light", "0,0,3", "--camera", "0,3,0", "-o", "{out}.png"],
    "best-view": [],
    "render": ["--camera", "0,0,3", "-o", "{out}.png"],
}


def _write_case(folder: Path, name: str) -> Path:
    file_name, content, _ = FILE_CASES[name]
    path = folder / file_name
    if content is None:
        path.mkdir()
    elif name != "a missing file":
        path.write_bytes(content)
    return path


def _cli_error(capsys, *argv: str) -> str:
    """Runs the ``o3dvis`` command; asserts it failed with one line and no traceback; returns that line."""
    from o3dvis.cli import main

    code = main(list(argv))
    err = capsys.readouterr().err.strip().splitlines()
    assert code != 0, "the command succeeded"
    assert err and not any("Traceback" in line for line in err)
    return err[-1]


@pytest.mark.parametrize("command", CLI_READERS)
@pytest.mark.parametrize("case", FILE_CASES)
def test_cli_refuses_a_bad_point_cloud_file(tmp_path, capsys, command, case):
    path = _write_case(tmp_path, case)
    args = [a.format(out=tmp_path / "out") for a in CLI_READERS[command]]
    line = _cli_error(capsys, command, str(path), *args)
    assert line.startswith(f"o3dvis {command}: error: ")
    assert __import__("re").search(FILE_CASES[case][2], line), line
    assert sorted(p.name for p in tmp_path.iterdir()) == ([] if case == "a missing file" else [path.name])


@pytest.mark.parametrize("case", CRASH_CASES)
def test_cli_refuses_a_pcd_that_crashes_open3d_in_a_child_process(tmp_path, case):
    file_name, content, message = CRASH_CASES[case]
    path = tmp_path / file_name
    path.write_bytes(content)
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    run = subprocess.run([sys.executable, "-m", "o3dvis", "visible", str(path), "--camera", "0,0,3", "-o",
                          str(tmp_path / "out.ply")], capture_output=True, text=True, env=env, timeout=_CHILD_TIMEOUT)
    assert run.returncode > 0, f"exit code {run.returncode}: {run.stderr[-2000:]}"  # < 0: killed by a signal
    err = run.stderr.strip().splitlines()
    assert err and "Traceback" not in run.stderr, run.stderr[-2000:]
    assert err[-1].startswith("o3dvis visible: error: ") and __import__("re").search(message, err[-1]), err[-1]
    assert sorted(p.name for p in tmp_path.iterdir()) == [file_name]


@pytest.mark.parametrize("normals", ["F 8", "F 4", None])
def test_a_binary_pcd_of_doubles_is_read_as_its_doubles(tmp_path, normals):
    """Open3D reads binary 8-byte floats as zeros: the reader decodes the points' and normals' own."""
    from o3dvis.io import read_point_cloud

    rng = np.random.default_rng(4)
    points, unit = rng.normal(size=(200, 3)), SPHERE[rng.integers(0, len(SPHERE), 200)]
    names, sizes, columns = "x y z", "8 8 8", [points]
    if normals is not None:
        size = normals.split()[1]
        names, sizes = names + " normal_x normal_y normal_z", f"{sizes} {size} {size} {size}"
    layout = [("xyz", "<f8", (3,))] + ([("n", f"<f{normals.split()[1]}", (3,))] if normals else [])
    table = np.zeros(len(points), layout)
    table["xyz"] = points
    if normals:
        table["n"] = unit
    count = len(names.split())
    header = (f"VERSION 0.7\nFIELDS {names}\nSIZE {sizes}\nTYPE {' '.join(['F'] * count)}\n"
              f"COUNT {' '.join(['1'] * count)}\nWIDTH {len(points)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
              f"POINTS {len(points)}\nDATA binary\n")
    path = tmp_path / "doubles.pcd"
    path.write_bytes(header.encode() + table.tobytes())
    read = read_point_cloud(path)
    np.testing.assert_array_equal(np.asarray(read.points), points)
    assert read.has_normals() == (normals is not None)
    if normals:
        np.testing.assert_array_equal(np.asarray(read.normals), table["n"].astype(np.float64))


@pytest.mark.parametrize("suffix, options", [(".ply", {}), (".ply", {"write_ascii": True}), (".pcd", {}),
                                             (".pcd", {"write_ascii": True}), (".pcd", {"compressed": True}),
                                             (".xyz", {}), (".xyzn", {}), (".xyzrgb", {}), (".pts", {})])
def test_the_reader_gives_what_open3d_wrote(tmp_path, suffix, options):
    from o3dvis.io import read_point_cloud

    rng = np.random.default_rng(3)
    pcd = as_cloud(rng.normal(size=(500, 3)))
    pcd.normals = o3d.utility.Vector3dVector(SPHERE[rng.integers(0, len(SPHERE), 500)])
    pcd.colors = o3d.utility.Vector3dVector(rng.random((500, 3)))
    path = tmp_path / f"cloud{suffix}"
    assert o3d.io.write_point_cloud(str(path), pcd, **options)
    read = read_point_cloud(path)
    expected = o3d.io.read_point_cloud(str(path))
    np.testing.assert_array_equal(np.asarray(read.points), np.asarray(expected.points))
    np.testing.assert_allclose(np.asarray(read.points), np.asarray(pcd.points), atol=1e-5, rtol=1e-5)  # ASCII PLY: 6 digits
    assert read.has_normals() == expected.has_normals() and read.has_colors() == expected.has_colors()


@pytest.mark.parametrize("command", ["calibrate", "publish"])
@pytest.mark.parametrize("what", ["not safetensors", "a folder"])
def test_cli_checkpoint_commands_refuse_a_bad_file_in_one_line(tmp_path, capsys, command, what):
    path = tmp_path / "ckpt.safetensors"
    if what == "a folder":
        path.mkdir()
    else:
        path.write_bytes(b"this is no checkpoint at all, just some text" * 10)
    rest = [str(tmp_path), "-o", str(tmp_path / "out.safetensors")] if command == "calibrate" else [
        "--name", "x", "--root", str(tmp_path)]
    before = sorted(tmp_path.rglob("*"))
    line = _cli_error(capsys, command, str(path), *rest)
    assert __import__("re").search("is a folder" if what == "a folder" else "not a safetensors file", line), line
    assert sorted(tmp_path.rglob("*")) == before


def test_cli_bench_creates_no_folder_it_was_not_given(tmp_path, capsys):
    out = tmp_path / "missing" / "b.json"
    line = _cli_error(capsys, "bench", "--methods", "hpr", "--points", "200", "--views", "1", "-o", str(out))
    assert "no folder" in line and str(out.parent) in line
    assert not out.parent.exists()


# ------------------------------------------------------------------------------ errors made clear

def test_a_max_range_beyond_1e154_or_a_tiny_cloud_crops_by_true_distances(vis):
    """Distances to the camera are compared, not their squares: a range of 1e200 crops nothing, and a
    cloud of 1e-170 units (whose squared distances underflow) is cropped as the unit one."""
    pcd = as_cloud(SPHERE)
    whole = np.asarray(o3dvis.select_visible(pcd, CAMERA, model=vis, max_range=10.0).points)
    np.testing.assert_array_equal(np.asarray(o3dvis.select_visible(pcd, CAMERA, model=vis, max_range=1e200).points),
                                  whole)
    np.testing.assert_array_equal(vis.encode(SPHERE).query(CAMERA, max_range=1e300),
                                  vis.encode(SPHERE).query(CAMERA, max_range=10.0))
    tiny = 1e-170
    for max_range in (2.7, 3.2):  # a crop that cuts the sphere
        unit = o3dvis.hidden_point_removal_neural(pcd, CAMERA, model=vis, max_range=max_range)[1]
        small = o3dvis.hidden_point_removal_neural(as_cloud(SPHERE * tiny), CAMERA * tiny, model=vis,
                                                   max_range=max_range * tiny)[1]
        assert 0 < len(small) == len(unit) and small == unit
        field = vis.encode(SPHERE * tiny).query(CAMERA * tiny, max_range=max_range * tiny)
        np.testing.assert_array_equal(field, vis.encode(SPHERE).query(CAMERA, max_range=max_range))


def test_select_visible_takes_a_tensor_that_requires_grad(vis):
    points = torch.tensor(SPHERE, requires_grad=True)
    visible = o3dvis.select_visible(points, CAMERA, model=vis)
    np.testing.assert_array_equal(np.asarray(visible.points), np.asarray(o3dvis.select_visible(SPHERE, CAMERA,
                                                                                                model=vis).points))


def test_a_camera_on_a_point_is_reported_with_a_true_distance_and_a_light_as_the_light(vis):
    """A camera 2.5 units from every point of a sphere stretched by an outlier 1e9 away is on its
    points at the network's resolution (float32 coordinates of the normalised frame, some 100 units
    here): refused, with a bound that holds the true distance. One 5e-7 off a point of the unit
    sphere is refused with that distance; a light on a point is named the light."""
    import re

    stretched = np.r_[2.5 * SPHERE, [[1e9, 0.0, 0.0]]]
    with pytest.raises(o3dvis.field.OnPointError, match=r"^camera 0 at \(0, 0, 0\) lies on a point") as error:
        vis.encode(stretched).query(np.zeros(3))
    assert float(re.search(r"nearest is within ([0-9.e+]+),", str(error.value))[1]) >= 2.5
    off = SPHERE[7] * (1 - 5e-7)
    with pytest.raises(ValueError, match="lies on a point") as error:
        vis.encode(SPHERE).query([CAMERA, off])
    assert error.value.view == 1 and error.value.args[0].startswith("camera 1 at")
    assert float(re.search(r"nearest is ([0-9.e+-]+) away", str(error.value))[1]) == pytest.approx(5e-7, rel=0.5)
    for shadows in (lambda: o3dvis.points_in_shadow(SPHERE, SPHERE[7], vis),
                    lambda: o3dvis.render_with_shadows(as_cloud(SPHERE), SPHERE[7], CAMERA, 32, 24, vis)):
        with pytest.raises(ValueError, match=r"^the light at .* lies on a point"):
            shadows()


@pytest.mark.parametrize("command", ["render", "shadow"])
def test_cli_refuses_an_image_too_large_in_one_line(tmp_path, capsys, command):
    path = tmp_path / "sphere.ply"
    o3d.io.write_point_cloud(str(path), as_cloud(SPHERE))
    args = [a.format(out=tmp_path / "out") for a in CLI_READERS[command]]
    line = _cli_error(capsys, command, str(path), *args, "--width", "1000000", "--height", "1000000")
    assert line.startswith(f"o3dvis {command}: error: ") and "1000000 x 1000000 image" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sphere.ply"]
