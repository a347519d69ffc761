"""Camera frames of a map (o3dvis.apps.map_frames, apps.frame_tiles) and the crops of a field they query."""

import numpy as np
import open3d as o3d
import pytest
import torch

import o3dvis
from o3dvis.apps import map_frames
from o3dvis.apps.map_frames import Frame, FrameMap, frames, pinhole_frames, tile_centres, visible_in_frame
from o3dvis.apps.pinhole import PinholeView, look_at
from o3dvis.groundtruth import visibility_from_mesh
from conftest import box_surface

_K = np.array([[160.0, 0, 159.5], [0, 160.0, 119.5], [0, 0, 1]])  # 320 x 240, 90 degrees across
_W, _H = 320, 240
_ROOM, _PILLAR = ([0, 0, 0], [10, 6, 3]), ([5, 2.5, 0], [6, 3.5, 3])


def _box_mesh(lo, hi) -> o3d.geometry.TriangleMesh:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return o3d.geometry.TriangleMesh.create_box(*(hi - lo)).translate(lo)


@pytest.fixture(scope="module")
def room():
    """A room with a pillar in it: (points, the mesh they lie on)."""
    rng = np.random.default_rng(0)
    points = np.concatenate([box_surface(*_ROOM, 12_000, rng), box_surface(*_PILLAR, 3_000, rng)])
    return points, _box_mesh(*_ROOM) + _box_mesh(*_PILLAR)


def _params(extrinsic: np.ndarray) -> o3d.camera.PinholeCameraParameters:
    params = o3d.camera.PinholeCameraParameters()
    params.intrinsic = o3d.camera.PinholeCameraIntrinsic(_W, _H, _K[0, 0], _K[1, 1], _K[0, 2], _K[1, 2])
    params.extrinsic = extrinsic
    return params


def _towards_pillar() -> np.ndarray:
    return look_at(np.array([1.0, 3.0, 1.5]), np.array([10.0, 3.0, 1.5]))


def _in_view(points: np.ndarray, extrinsic: np.ndarray, max_range: float | None = None) -> np.ndarray:
    """The points in the image, in front of the camera (and within max_range), as the frames crop them."""
    view = PinholeView(extrinsic, _K, _W, _H)
    uv, depth = view.project(points)
    inside = (depth > 0) & (uv >= -0.5).all(axis=1) & (uv[:, 0] < _W - 0.5) & (uv[:, 1] < _H - 0.5)
    if max_range is not None:
        inside &= np.linalg.norm(points - view.location, axis=1) <= max_range
    return np.flatnonzero(inside)


def test_a_frame_gives_the_visible_points_their_pixels_and_depths(room, vis):
    points, mesh = room
    extrinsic = _towards_pillar()
    frame = visible_in_frame(points, _params(extrinsic), model=vis)
    assert isinstance(frame, Frame) and frame.depth_image is None and frame.index_image is None
    assert frame.indices.dtype == np.int64 and np.all(np.diff(frame.indices) > 0)
    assert frame.pixels.dtype == np.float32 and frame.pixels.shape == (len(frame), 2)
    uv, depth = PinholeView(extrinsic, _K, _W, _H).project(points[frame.indices])
    np.testing.assert_allclose(frame.pixels, uv, atol=1e-3)
    np.testing.assert_allclose(frame.depths, depth, rtol=1e-6)
    in_view = _in_view(points, extrinsic)
    assert np.isin(frame.indices, in_view).all()
    truth = visibility_from_mesh(mesh, points[in_view], _towards_pillar_location())[0]
    seen = np.isin(in_view, frame.indices)
    balanced = (seen[truth].mean() + (~seen[~truth]).mean()) / 2
    assert balanced > 0.9, balanced
    behind = in_view[(points[in_view, 0] > 9.99) & (np.abs(points[in_view, 1] - 3) < 0.3)]
    assert len(behind) > 20 and not np.isin(behind, frame.indices).any()  # the wall behind the pillar


def _towards_pillar_location() -> np.ndarray:
    return np.array([1.0, 3.0, 1.5])


def test_every_form_of_camera_gives_the_same_frame(room, vis):
    points, _ = room
    extrinsic = _towards_pillar()
    expected = visible_in_frame(points, _params(extrinsic), model=vis)
    intrinsic = o3d.camera.PinholeCameraIntrinsic(_W, _H, _K[0, 0], _K[1, 1], _K[0, 2], _K[1, 2])
    for frame in (visible_in_frame(points, extrinsic, intrinsic=_K, width=_W, height=_H, model=vis),
                  visible_in_frame(points, extrinsic, intrinsic=intrinsic, model=vis),
                  visible_in_frame(points, PinholeView(extrinsic, _K, _W, _H), model=vis),
                  visible_in_frame(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)), _params(extrinsic),
                                   model=vis)):
        np.testing.assert_array_equal(frame.indices, expected.indices)
        np.testing.assert_array_equal(frame.pixels, expected.pixels)


def test_images_hold_the_nearest_visible_point_of_each_pixel(room, vis):
    points, _ = room
    frame = visible_in_frame(points, _params(_towards_pillar()), images=True, model=vis)
    depth, index = frame.depth_image, frame.index_image
    assert depth.shape == index.shape == (_H, _W) and depth.dtype == np.float32 and index.dtype == np.int64
    assert np.array_equal(depth == 0, index == -1)
    shown = index >= 0
    assert set(np.unique(index[shown])) <= set(frame.indices.tolist())
    position = np.searchsorted(frame.indices, index[shown])
    np.testing.assert_array_equal(depth[shown], frame.depths[position])
    cell = np.floor(frame.pixels.astype(np.float64) + 0.5).astype(np.int64)
    np.testing.assert_array_equal(index[shown], frame.indices[position])
    assert (depth[cell[:, 1], cell[:, 0]] <= frame.depths).all()  # no visible point nearer than its pixel's


def test_max_range_leaves_out_the_points_beyond_it(room, vis):
    points, _ = room
    frame = visible_in_frame(points, _params(_towards_pillar()), max_range=5.0, model=vis)
    assert len(frame) and np.isin(frame.indices, _in_view(points, _towards_pillar(), 5.0)).all()
    assert frame.depths.max() <= 5.0


def test_a_frame_that_sees_no_point_is_empty(room, vis):
    points, _ = room
    away = look_at(np.array([1.0, 3.0, 50.0]), np.array([1.0, 3.0, 100.0]))  # above the room, looking up
    frame = visible_in_frame(points, _params(away), images=True, model=vis)
    assert len(frame) == 0 and frame.indices.dtype == np.int64 and frame.pixels.shape == (0, 2)
    assert (frame.index_image == -1).all() and (frame.depth_image == 0).all()


@pytest.mark.parametrize("case, error", [
    ("not a rotation", "rigid"), ("nan extrinsic", "finite"), ("nan intrinsic", "finite"),
    ("no size", "width"), ("no image size", "image size"), ("negative focal", "positive")])
def test_bad_cameras_are_refused_with_a_clear_error(room, vis, case, error):
    points, _ = room
    extrinsic, k = _towards_pillar(), _K.copy()
    kwargs = {"intrinsic": k, "width": _W, "height": _H}
    if case == "not a rotation":
        extrinsic[:3, :3] *= 2
    elif case == "nan extrinsic":
        extrinsic[0, 3] = np.nan
    elif case == "nan intrinsic":
        k[0, 2] = np.inf
    elif case == "no size":
        del kwargs["width"]
    elif case == "negative focal":
        k[1, 1] = -160
    camera = extrinsic
    if case == "no image size":
        camera, kwargs = o3d.camera.PinholeCameraParameters(), {}
        camera.extrinsic = extrinsic
    with pytest.raises(ValueError, match=error):
        visible_in_frame(points, camera, model=vis, **kwargs)


def test_a_bad_frame_of_a_trajectory_is_named_before_any_frame_is_answered(room, vis):
    points, _ = room
    trajectory = o3d.camera.PinholeCameraTrajectory()
    bad = _towards_pillar()
    bad[:3, :3] = np.diag([1.0, 1.0, -1.0])  # a reflection
    trajectory.parameters = [_params(_towards_pillar()), _params(bad)]
    with pytest.raises(ValueError, match="frame 1: .*rigid"):
        frames(points, trajectory, model=vis)


def test_a_trajectory_is_answered_from_one_encoding_as_each_frame_alone(room, vis, monkeypatch, capsys):
    points, _ = room
    extrinsics = np.stack([look_at(np.array([1.0 + i, 3.0 + 0.2 * i, 1.5]), np.array([10.0, 3.0, 1.0]))
                           for i in range(3)])
    encodings = []
    encode = vis.encode
    monkeypatch.setattr(vis, "encode", lambda pcd, *a, **k: encodings.append(k) or encode(pcd, *a, **k))
    answered = list(frames(points, extrinsics, intrinsic=_K, width=_W, height=_H, model=vis, progress=True))
    assert len(answered) == 3 and len(encodings) == 1 and encodings[0]["views"] is not None  # the scene model's alone
    assert "frames" in capsys.readouterr().err  # the progress bar
    for extrinsic, frame in zip(extrinsics, answered):
        alone = visible_in_frame(points, extrinsic, intrinsic=_K, width=_W, height=_H, model=vis)
        np.testing.assert_array_equal(frame.indices, alone.indices)


def test_a_field_answers_as_the_map_it_encodes_inside_the_box_and_outside(room, vis):
    points, _ = room
    field = vis.encode(points)
    outside = look_at(np.array([-6.0, 3.0, 1.5]), np.array([5.0, 3.0, 1.5]))  # the default model's camera
    fmap = FrameMap(points, model=vis)  # its sides encoded as their cameras come
    for extrinsic in (_towards_pillar(), outside, _towards_pillar()):
        from_field = visible_in_frame(field, _params(extrinsic))
        from_map = fmap.frame(_params(extrinsic))
        assert len(from_map)
        np.testing.assert_array_equal(from_field.indices, from_map.indices)
        np.testing.assert_allclose(from_field.pixels, from_map.pixels, atol=1e-3)


@pytest.fixture(scope="module")
def corridor():
    """A corridor 120 long, 6 wide, 3 high, and cameras walking along it looking ahead."""
    points = box_surface([0, 0, 0], [120, 6, 3], 30_000, np.random.default_rng(1))
    extrinsics = np.stack([look_at(np.array([x, 3.0, 1.5]), np.array([x + 10, 3.0, 1.5])) for x in range(5, 60, 4)])
    return points, extrinsics


def test_a_long_map_is_encoded_in_crops_each_shared_by_nearby_frames(corridor, vis, monkeypatch):
    points, extrinsics = corridor
    views = pinhole_frames(extrinsics, _K, _W, _H)
    centres = tile_centres(points, views, 8.0)
    reach = map_frames.TILE_SLACK * 8.0
    for view, centre in zip(views, centres):
        assert np.linalg.norm(view.location - centre) <= reach
    distinct = [c for i, c in enumerate(centres) if i == 0 or not np.array_equal(c, centres[i - 1])]
    assert 1 < len(distinct) < len(views)
    sizes = []
    encode = vis.encode
    monkeypatch.setattr(vis, "encode", lambda pcd, *a, **k: sizes.append(len(pcd)) or encode(pcd, *a, **k))
    fmap = FrameMap(points, max_range=8.0, model=vis)
    answered = list(fmap.frames(extrinsics, intrinsic=_K, width=_W, height=_H, progress=False))
    assert len(sizes) == len(distinct) and max(sizes) < len(points) / 3  # crops, each encoded once
    for extrinsic, centre, frame in zip(extrinsics, centres, answered):
        assert len(frame) and frame.depths.max() <= 8.0
        assert np.isin(frame.indices, _in_view(points, extrinsic, 8.0)).all()
        again = FrameMap(points, max_range=8.0, model=vis).frame(extrinsic, intrinsic=_K, width=_W, height=_H,
                                                                 centre=centre)
        np.testing.assert_array_equal(again.indices, frame.indices)


def test_a_crop_centre_too_far_from_the_camera_is_refused(corridor, vis):
    points, extrinsics = corridor
    with pytest.raises(ValueError, match="centre"):
        FrameMap(points, max_range=8.0, model=vis).frame(extrinsics[0], intrinsic=_K, width=_W, height=_H,
                                                         centre=[100.0, 3.0, 1.5])


def test_the_frames_are_exported():
    assert o3dvis.visible_in_frame is visible_in_frame and o3dvis.frames is frames and o3dvis.Frame is Frame


# --- the crops of a field that a frame queries ---------------------------------------------------

def test_a_field_restricted_to_all_its_points_answers_as_itself(room, vis):
    points, _ = room
    field = vis.encode(points)
    cameras = np.array([[1.0, 3.0, 1.5], [20.0, 3.0, 1.5]])  # inside (the scene field) and outside
    whole = field.restricted(np.arange(len(points)))
    np.testing.assert_array_equal(whole.query(cameras), field.query(cameras))


def test_a_restricted_field_answers_its_rows_in_their_order_and_only_they_occlude(room, vis):
    points, _ = room
    field = vis.encode(points)
    camera = _towards_pillar_location()
    wall = np.flatnonzero((points[:, 0] > 9.99) & (np.abs(points[:, 1] - 3) < 0.4))  # behind the pillar
    rows = np.concatenate([wall, np.flatnonzero(points[:, 0] < 9.99)])
    hidden = field.restricted(rows).probabilities(camera, as_numpy=True)[0, :len(wall)]
    alone = field.restricted(wall[::-1].copy()).probabilities(camera, as_numpy=True)[0]
    assert (hidden < 0.5).mean() > 0.9 and (alone > 0.5).mean() > 0.9  # no pillar: nothing hides the wall
    by_point = np.zeros(len(points), dtype=bool)
    by_point[rows] = field.restricted(rows).query(camera)[0]
    shuffled = np.random.default_rng(0).permutation(rows)
    np.testing.assert_array_equal(field.restricted(shuffled).query(camera)[0], by_point[shuffled])


def test_a_restricted_field_refuses_bad_rows_and_takes_none_for_all(room, vis):
    field = vis.encode(room[0])
    with pytest.raises(IndexError):
        field.restricted([len(room[0])])
    with pytest.raises(TypeError):
        field.restricted([0.5])
    camera = [1.0, 3.0, 1.5]
    np.testing.assert_array_equal(field.restricted(None).query(camera), field.query(camera))
    assert field.restricted(torch.arange(3)).num_points == 3


def test_frames_side_by_side_or_a_subset_are_the_frames_one_at_a_time(corridor, vis):
    points, extrinsics = corridor
    kwargs = {"intrinsic": _K, "width": _W, "height": _H, "progress": False}
    one = list(FrameMap(points, max_range=8.0, model=vis).frames(extrinsics, workers=1, **kwargs))
    two = list(FrameMap(points, max_range=8.0, model=vis).frames(extrinsics, workers=2, **kwargs))
    some = list(FrameMap(points, max_range=8.0, model=vis).frames(extrinsics, indices=[9, 1, 4], workers=2, **kwargs))
    for a, b in zip(one, two):
        np.testing.assert_array_equal(a.indices, b.indices)
        np.testing.assert_array_equal(a.pixels, b.pixels)
    for i, frame in zip([1, 4, 9], some):
        np.testing.assert_array_equal(frame.indices, one[i].indices)
    fmap = FrameMap(points, max_range=8.0, model=vis)
    for bad, error in (({"workers": 0}, ValueError), ({"indices": [len(extrinsics)]}, ValueError),
                       ({"indices": [0.5]}, TypeError)):
        with pytest.raises(error):
            fmap.frames(extrinsics, **bad, **kwargs)
