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

Open3D and qhull calls (HPR baselines, triangulations, Poisson, ray casting) run in one child
process, so a segfault or an abort fails the cell it happened in instead of killing pytest. Cells
that the tests of the model (tests/test_neural.py, test_field.py, test_cameras.py) or of the
baselines (tests/test_baselines.py) already cover are left out.
"""

from __future__ import annotations

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

from conftest import SPHERE, as_cloud
from .conftest import CAMERA, PLANE, _CHILD_TIMEOUT

OFFSET = np.array([1e6, -1e6, 1e6])
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
# Cells the tests of the model cover (tests/test_neural.py, test_field.py, test_cameras.py).
_TEST_MODEL = frozenset({"empty cloud", "NaN point", "Inf point", "NaN camera", "Inf camera",
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
        method=False, skip=_TEST_MODEL | {"two cameras"}),
    "VisibilityField.probabilities": Func(
        "any", lambda c, cam, vis: vis.encode(c).probabilities(cam),
        lambda r, p, o: _probability_answer(r, len(p)), method=False, skip=_TEST_MODEL | {"two cameras"}),
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

@pytest.fixture(scope="module")
def child_results() -> tuple[dict, subprocess.CompletedProcess]:
    """Runs every risky cell in one child process; returns its per-cell results and the process."""
    cells = [p.values[:2] for p in _cells(risky=True)]
    tests = Path(__file__).resolve().parents[1]  # the folder of this package and of its conftest
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tests.parent), str(tests)]))
    proc = subprocess.run([sys.executable, "-m", f"robustness.{Path(__file__).stem}", json.dumps(cells)],
                          capture_output=True, text=True, env=env, timeout=_CHILD_TIMEOUT)
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
