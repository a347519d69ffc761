"""The two-pass encoding (``o3dvis.two_pass``): normals estimated in a first pass for dense, clean
clouds; and a cloud's own normals reach the normals model only where they face out: normals that
point either way (``estimate_normals``), flipped at random or facing one sensor are estimated anew,
with a warning; oriented ones, and normals the caller vouches for (``normals=True`` or an array), are
used as given."""

from __future__ import annotations

import warnings

import numpy as np
import open3d as o3d
import pytest
import torch

import o3dvis
from o3dvis.cameras import viewpoints_around
from o3dvis.nn import NetworkConfig, VisibilityNetwork
from o3dvis.orientation import voted_normals
from o3dvis.two_pass import first_pass_normals

from conftest import SMALL, _camera


def test_normals_estimated_in_a_first_pass_for_dense_clean_clouds(network):
    torch.manual_seed(5)
    normals_net = VisibilityNetwork(NetworkConfig(**SMALL, use_normals=True))
    paired = o3dvis.NeuralVisibility(network, normals_net)
    rng = np.random.default_rng(0)
    sphere = rng.normal(size=(20_000, 3))
    sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)
    field = paired.encode(sphere, normals="estimate")
    assert field.network is normals_net
    cameras = viewpoints_around(sphere, 14)  # the first pass's probabilities orient the normals
    expected = voted_normals(sphere, cameras, paired.encode(sphere, normals=False).probabilities(cameras).numpy())
    np.testing.assert_allclose(field.normals[field.rank].numpy(), expected, atol=1e-6)
    first, rank = paired.encode(sphere, normals=False), field.rank.numpy()
    np.testing.assert_array_equal(first_pass_normals(first, sphere[np.argsort(rank)], stored=True)[rank],
                                  first_pass_normals(first, sphere))  # in the field's order or the cloud's
    given = paired.encode(sphere, normals=field.normals[field.rank].double().numpy())  # the passes share
    torch.testing.assert_close(field.probabilities(cameras), given.probabilities(cameras))  # octree, noise
    assert paired.encode(sphere).network is network  # by default: one pass for a cloud without normals
    noisy = sphere * (1 + 0.05 * rng.uniform(-1, 1, (len(sphere), 1)))
    assert paired.encode(noisy, normals="estimate").network is network  # rough neighbourhoods: one pass
    assert paired.encode(sphere[:900], normals="estimate").network is network  # too sparse
    plane = sphere * [1, 1, 0]
    assert paired.encode(plane, normals="estimate").network is network  # flat: one pass is exact
    corners = np.repeat(np.eye(4, 3), 500, axis=0)  # 3-D, but every neighbourhood one point repeated
    assert paired.encode(corners, normals="estimate").network is network
    with pytest.raises(ValueError, match="needs a normals model"):
        o3dvis.NeuralVisibility(network).encode(sphere, normals="estimate")
    with pytest.raises(ValueError, match="got 'estimated'"):
        paired.encode(sphere, normals="estimated")
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(sphere))
    camera = _camera(sphere)
    _, two = o3dvis.hidden_point_removal_neural(cloud, camera, model=paired, normals="estimate")
    assert two == np.flatnonzero(field.query(camera)[0]).tolist()
    assert len(o3dvis.select_visible(cloud, camera, model=paired, normals="estimate").points) == len(two)
    _, cropped = o3dvis.hidden_point_removal_neural(cloud, camera, model=paired, normals="estimate", max_range=10.0)
    assert cropped == two  # a range that keeps every point changes nothing


# ---------------------------------------------------------------- a cloud's own normals

CAMERA = np.array([0.4, -0.3, 3.5])


@pytest.fixture(scope="module")
def torus() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A torus's points, their outward normals and which of them ``CAMERA`` sees (ray casting)."""
    mesh = o3d.geometry.TriangleMesh.create_torus(torus_radius=1.0, tube_radius=0.3)
    mesh.compute_triangle_normals()
    o3d.utility.random.seed(0)
    pcd = mesh.sample_points_uniformly(6000, use_triangle_normal=True)
    points = np.asarray(pcd.points)
    return points, np.asarray(pcd.normals), o3dvis.visibility_from_mesh(mesh, points, CAMERA)[0]


def _cloud(points: np.ndarray, normals: np.ndarray | None) -> o3d.geometry.PointCloud:
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    if normals is not None:
        pcd.normals = o3d.utility.Vector3dVector(normals)
    return pcd


def _encode(vis, pcd, normals=None):
    """The field and the warnings the encode gave."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        field = vis.encode(pcd, normals=normals)
    return field, [str(w.message) for w in caught if "unoriented" in str(w.message)]


def _unoriented(torus, kind: str) -> np.ndarray:
    points, normals, _ = torus
    rng = np.random.default_rng(1)
    if kind == "estimate_normals":
        pcd = _cloud(points, None)
        pcd.estimate_normals()
        return np.asarray(pcd.normals)
    if kind == "random signs":
        return normals * rng.choice([-1.0, 1.0], size=(len(normals), 1))
    sensor = np.array([2.0, 1.0, 0.5])  # normals facing a sensor beside the torus, into it on the far side
    return np.where(np.einsum("ij,ij->i", sensor - points, normals)[:, None] < 0, -normals, normals)


@pytest.mark.parametrize("kind", ["estimate_normals", "random signs", "facing a sensor"])
def test_unoriented_normals_are_estimated_anew_with_a_warning(vis, torus, kind):
    points, _, truth = torus
    field, said = _encode(vis, _cloud(points, _unoriented(torus, kind)))
    assert len(said) == 1, said
    estimated = vis.encode(points, normals="estimate")
    assert torch.equal(field.probabilities(CAMERA), estimated.probabilities(CAMERA))
    alone = vis.encode(points, normals=False).query(CAMERA)[0]
    assert (field.query(CAMERA)[0] == truth).mean() >= (alone == truth).mean()


def test_oriented_normals_are_used_as_given(vis, torus):
    points, normals, _ = torus
    field, said = _encode(vis, _cloud(points, normals))
    assert not said
    assert torch.equal(field.probabilities(CAMERA), vis.encode(points, normals=normals).probabilities(CAMERA))


@pytest.mark.parametrize("vouched", [True, "array"])
def test_normals_the_caller_vouches_for_are_not_checked(vis, torus, vouched):
    points, _, _ = torus
    unoriented = _unoriented(torus, "random signs")
    pcd = _cloud(points, unoriented)
    field, said = _encode(vis, pcd, True if vouched is True else unoriented)
    assert not said
    assert torch.equal(field.probabilities(CAMERA), vis.encode(points, normals=unoriented).probabilities(CAMERA))


def test_the_drop_in_warns_and_answers_as_the_estimate(vis, torus):
    points, _, _ = torus
    pcd = _cloud(points, _unoriented(torus, "estimate_normals"))
    o3dvis.encodings.clear()
    with pytest.warns(UserWarning, match="unoriented"):
        _, index = o3dvis.hidden_point_removal_neural(pcd, CAMERA, model=vis)
    expected = np.flatnonzero(vis.encode(points, normals="estimate").query(CAMERA)[0])
    assert np.array_equal(np.asarray(index), expected)


def test_oriented_normals_the_check_doubts_are_kept_where_the_estimates_side_with_them(vis, torus, monkeypatch):
    """Thin walls can make the check doubt oriented normals: the two passes it then runs keep them
    where they lie on the side of the estimated normals, and estimate the unoriented ones anew."""
    from o3dvis import two_pass

    monkeypatch.setattr(two_pass, "MAX_FACING_AWAY", -1.0)  # every cloud's normals doubted
    points, normals, _ = torus
    field, said = _encode(vis, _cloud(points, normals))
    assert not said
    assert torch.equal(field.probabilities(CAMERA), vis.encode(points, normals=normals).probabilities(CAMERA))
    field, said = _encode(vis, _cloud(points, _unoriented(torus, "random signs")))
    assert len(said) == 1
    assert torch.equal(field.probabilities(CAMERA), vis.encode(points, normals="estimate").probabilities(CAMERA))


def test_on_a_noisy_cloud_doubted_normals_are_kept_or_ignored_by_the_same_test(vis, torus, monkeypatch):
    """A noisy cloud keeps one pass under normals="estimate": its estimates still tell oriented normals
    from unoriented ones, which are then ignored (one pass without normals)."""
    from o3dvis import two_pass
    from o3dvis.training.data.perturb import add_noise

    points, normals, _ = torus
    noisy = add_noise(points, 0.03, 3.0, np.random.default_rng(2))
    alone = vis.encode(noisy, normals=False).probabilities(CAMERA)
    assert torch.equal(vis.encode(noisy, normals="estimate").probabilities(CAMERA), alone)  # one pass there
    monkeypatch.setattr(two_pass, "MAX_FACING_AWAY", -1.0)  # every cloud's normals doubted
    field, said = _encode(vis, _cloud(noisy, normals))
    assert not said
    assert torch.equal(field.probabilities(CAMERA), vis.encode(noisy, normals=normals).probabilities(CAMERA))
    field, said = _encode(vis, _cloud(noisy, _unoriented(torus, "random signs")))
    assert len(said) == 1
    assert torch.allclose(field.probabilities(CAMERA), alone, atol=1e-5)  # the one pass (threads may round apart)
