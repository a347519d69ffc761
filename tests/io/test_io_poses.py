"""Camera poses read through o3dvis.io.read_poses: Open3D trajectory JSON and LOG files written by
Open3D, COLMAP models (text and binary) written here, read back exactly; broken files refused with
an error naming the file and the problem."""

import json
import re
import struct
import warnings

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial.transform import Rotation

from o3dvis.io import Poses, read_poses

_MODEL_IDS = {"SIMPLE_PINHOLE": 0, "PINHOLE": 1, "SIMPLE_RADIAL": 2, "RADIAL": 3, "OPENCV": 4, "OPENCV_FISHEYE": 5}


def _escaped(path) -> str:
    return re.escape(str(path))


def _trajectory(count=3, seed=0) -> o3d.camera.PinholeCameraTrajectory:
    rng = np.random.default_rng(seed)
    trajectory = o3d.camera.PinholeCameraTrajectory()
    cameras = []
    for k in range(count):
        params = o3d.camera.PinholeCameraParameters()
        params.intrinsic = o3d.camera.PinholeCameraIntrinsic(640 + k, 480, 500.0 + k, 510.0, 319.5, 239.5)
        extrinsic = np.eye(4)
        extrinsic[:3, :3] = Rotation.random(random_state=seed + k).as_matrix()
        extrinsic[:3, 3] = rng.normal(size=3) * 10
        params.extrinsic = extrinsic
        cameras.append(params)
    trajectory.parameters = cameras
    return trajectory


def _assert_same_cameras(read: Poses, expected: list, atol: float = 0.0) -> None:
    assert len(read) == len(read.trajectory.parameters) == len(expected)
    for got, want in zip(read.trajectory.parameters, expected):
        np.testing.assert_allclose(np.asarray(got.extrinsic), np.asarray(want.extrinsic), rtol=0, atol=atol)
        np.testing.assert_array_equal(got.intrinsic.intrinsic_matrix, want.intrinsic.intrinsic_matrix)
        assert (got.intrinsic.width, got.intrinsic.height) == (want.intrinsic.width, want.intrinsic.height)


def test_an_open3d_json_trajectory_is_read_exactly(tmp_path):
    path = tmp_path / "poses.json"
    trajectory = _trajectory()
    assert o3d.io.write_pinhole_camera_trajectory(str(path), trajectory)
    poses = read_poses(path)
    _assert_same_cameras(poses, list(trajectory.parameters))
    assert poses.names == ("0", "1", "2")


def test_one_open3d_camera_json_is_a_trajectory_of_one(tmp_path):
    path = tmp_path / "camera.json"
    params = _trajectory(1).parameters[0]
    assert o3d.io.write_pinhole_camera_parameters(str(path), params)
    _assert_same_cameras(read_poses(path), [params])


def test_an_open3d_log_trajectory_is_read_with_the_intrinsic_given(tmp_path):
    path = tmp_path / "poses.log"
    trajectory = _trajectory()
    assert o3d.io.write_pinhole_camera_trajectory(str(path), trajectory)
    intrinsic = o3d.camera.PinholeCameraIntrinsic(320, 240, 300.0, 300.0, 159.5, 119.5)
    poses = read_poses(path, intrinsic=intrinsic)
    for got, open3d, written in zip(poses.trajectory.parameters, o3d.io.read_pinhole_camera_trajectory(
            str(path)).parameters, trajectory.parameters):
        np.testing.assert_array_equal(got.extrinsic, open3d.extrinsic)  # Open3D's reading, checked
        np.testing.assert_allclose(got.extrinsic, written.extrinsic, atol=1e-6)  # LOG files hold 8 decimals
        np.testing.assert_array_equal(got.intrinsic.intrinsic_matrix, intrinsic.intrinsic_matrix)
    assert len(poses) == 3


def _edited_json(tmp_path, edit) -> str:
    path = tmp_path / "poses.json"
    assert o3d.io.write_pinhole_camera_trajectory(str(path), _trajectory())
    document = json.loads(path.read_text())
    edit(document)
    path.write_text(json.dumps(document))
    return path


def _scaled(document):
    document["parameters"][1]["extrinsic"][0] *= 2.0  # a column of the rotation twice as long


def _reflected(document):
    document["parameters"][1]["extrinsic"][:3] = [-x for x in document["parameters"][1]["extrinsic"][:3]]


def _nan(document):
    document["parameters"][2]["extrinsic"][13] = float("nan")


@pytest.mark.parametrize("edit, message", [
    (_scaled, r"camera 1 \(1\): .*not a rigid transform"),
    (_reflected, r"camera 1 \(1\): .*not a rigid transform"),
    (_nan, r"camera 2's extrinsic has NaN or infinite numbers"),
    (lambda document: document.update(parameters=[]), "no camera pose in it"),
    (lambda document: document.update(class_name="PinholeCameraIntrinsic"), "not an Open3D camera file"),
    (lambda document: document["parameters"][0].pop("extrinsic"), "camera 0's extrinsic must be a list of 16"),
])
def test_a_bad_json_trajectory_is_refused(tmp_path, edit, message):
    path = _edited_json(tmp_path, edit)
    with pytest.raises(ValueError, match=rf"^{_escaped(path)}: {message}"):
        read_poses(path)


def test_a_file_that_is_not_json_is_refused(tmp_path):
    path = tmp_path / "poses.json"
    path.write_text('{"class_name": "PinholeCameraTrajectory", "parameters": [')
    with pytest.raises(ValueError, match=rf"^{_escaped(path)}: not JSON \(.*line 1 column"):
        read_poses(path)


def _edited_log(tmp_path, edit) -> str:
    path = tmp_path / "poses.log"
    assert o3d.io.write_pinhole_camera_trajectory(str(path), _trajectory())
    lines = path.read_text().splitlines()
    path.write_text("\n".join(edit(lines)) + "\n")
    return path


def _log_row(lines, line, values):
    lines[line] = " ".join(map(str, values))
    return lines


@pytest.mark.parametrize("edit, message", [
    (lambda lines: lines[:-2], r"truncated LOG file: its last frame has 3 of the 5 lines"),
    (lambda lines: lines[:5] + [""] + lines[5:], r"line 6 is blank"),
    (lambda lines: _log_row(lines, 7, [0.0, 1.0, "nan", 0.0]), r"line 8 .* should be row 2 of frame 1's pose: 4 finite"),
    (lambda lines: _log_row(lines, 7, [0.0, 1.0, 0.0]), r"line 8 .* should be row 2 of frame 1's pose"),
    (lambda lines: _log_row(lines, 1, [2.0, 0.0, 0.0, 0.0]), r"camera 0 \(0\): .*not a rigid transform"),
    (lambda lines: _log_row(lines, 5, ["a", "b", "c"]), r"line 6 .* should hold frame 1's 3 integers"),
])
def test_a_bad_log_trajectory_is_refused(tmp_path, edit, message):
    path = _edited_log(tmp_path, edit)
    with pytest.raises(ValueError, match=rf"^{_escaped(path)}: {message}"):
        read_poses(path)


def test_a_missing_file_a_wrong_suffix_and_a_misplaced_intrinsic_are_refused(tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        read_poses(tmp_path / "none.json")
    (tmp_path / "poses.txt").write_text("1 2 3\n")
    with pytest.raises(ValueError, match=r"unknown pose format '\.txt'"):
        read_poses(tmp_path / "poses.txt")
    path = tmp_path / "poses.json"
    assert o3d.io.write_pinhole_camera_trajectory(str(path), _trajectory())
    with pytest.raises(ValueError, match="an intrinsic is taken for a .log file only"):
        read_poses(path, intrinsic=o3d.camera.PinholeCameraIntrinsic(320, 240, 300.0, 300.0, 159.5, 119.5))


# COLMAP models, written here as COLMAP's documentation lays them out

def _write_colmap(folder, cameras, images, binary: bool) -> None:
    """cameras: (id, model, width, height, params); images: (id, qvec, tvec, camera id, name, 2D points as
    (x, y, point id))."""
    folder.mkdir(exist_ok=True)
    if binary:
        data = struct.pack("<Q", len(cameras)) + b"".join(
            struct.pack(f"<IiQQ{len(params)}d", camera_id, _MODEL_IDS[model], width, height, *params)
            for camera_id, model, width, height, params in cameras)
        (folder / "cameras.bin").write_bytes(data)
        data = struct.pack("<Q", len(images)) + b"".join(
            struct.pack("<I7dI", image_id, *qvec, *tvec, camera_id) + name.encode() + b"\0"
            + struct.pack("<Q", len(points)) + b"".join(struct.pack("<ddq", *point) for point in points)
            for image_id, qvec, tvec, camera_id, name, points in images)
        (folder / "images.bin").write_bytes(data)
        return
    lines = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"]
    lines += [" ".join(map(repr, [camera_id, model, width, height, *params])).replace("'", "")
              for camera_id, model, width, height, params in cameras]
    (folder / "cameras.txt").write_text("\n".join(lines) + "\n")
    lines = ["# Image list with two lines of data per image:", "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME"]
    for image_id, qvec, tvec, camera_id, name, points in images:
        lines.append(" ".join(map(repr, [image_id, *qvec, *tvec, camera_id])) + f" {name}")
        lines.append(" ".join(f"{x!r} {y!r} {point}" for x, y, point in points))
    (folder / "images.txt").write_text("\n".join(lines) + "\n")


_CAMERAS = [(1, "SIMPLE_PINHOLE", 640, 480, [500.0, 320.0, 240.0]),
            (2, "PINHOLE", 800, 600, [700.0, 710.0, 401.25, 299.5]),
            (7, "OPENCV", 1024, 768, [900.0, 905.0, 512.0, 384.0, -0.1, 0.01, 0.001, -0.002])]


def _images(seed=0, camera_ids=(2, 1, 7, 1)):
    rng = np.random.default_rng(seed)
    ids = [5, 2, 9, 3][:len(camera_ids)]  # stored out of order
    images = []
    for k, (image_id, camera_id) in enumerate(zip(ids, camera_ids)):
        x, y, z, w = Rotation.random(random_state=seed + k).as_quat().tolist()
        points = [(float(rng.uniform(0, 600)), float(rng.uniform(0, 400)), int(rng.integers(-1, 100)))
                  for _ in range(k)]
        images.append((image_id, (w, x, y, z), tuple((rng.normal(size=3) * 5).tolist()), camera_id,
                       f"frame {image_id:04d}.jpg", points))
    return images


def _expected(images):
    """Open3D cameras of the images, by id, independently of the reader: scipy's rotation of each
    quaternion, and the principal point half a pixel up and left (COLMAP's top-left pixel centre is
    at 0.5, 0.5, Open3D's at 0, 0)."""
    cameras = {camera_id: (width, height, params) for camera_id, _, width, height, params in _CAMERAS}
    expected = []
    for _, (w, x, y, z), tvec, camera_id, _, _ in sorted(images):
        width, height, params = cameras[camera_id]
        fx, fy, cx, cy = (params[0], params[0], *params[1:3]) if len(params) == 3 else params[:4]
        camera = o3d.camera.PinholeCameraParameters()
        camera.intrinsic = o3d.camera.PinholeCameraIntrinsic(width, height, fx, fy, cx - 0.5, cy - 0.5)
        extrinsic = np.eye(4)
        extrinsic[:3, :3], extrinsic[:3, 3] = Rotation.from_quat([x, y, z, w]).as_matrix(), tvec
        camera.extrinsic = extrinsic
        expected.append(camera)
    return expected


@pytest.mark.parametrize("binary", [False, True])
def test_a_colmap_model_is_read_with_a_warning_that_distortion_is_ignored(tmp_path, binary):
    images = _images()
    _write_colmap(tmp_path / "sparse", _CAMERAS, images, binary)
    with pytest.warns(UserWarning, match="distortion coefficients of the OPENCV cameras are ignored") as caught:
        poses = read_poses(tmp_path / "sparse")
    assert len([w for w in caught if "distortion" in str(w.message)]) == 1
    _assert_same_cameras(poses, _expected(images), atol=1e-12)
    for got, (_, _, tvec, *_) in zip(poses.trajectory.parameters, sorted(images)):
        np.testing.assert_array_equal(np.asarray(got.extrinsic)[:3, 3], tvec)
    assert poses.names == ("frame 0002.jpg", "frame 0003.jpg", "frame 0005.jpg", "frame 0009.jpg")


def test_a_colmap_file_names_its_model_and_binary_comes_first(tmp_path):
    images = _images(camera_ids=(1, 2))
    _write_colmap(tmp_path, _CAMERAS, images, binary=False)
    text = read_poses(tmp_path / "images.txt")
    shifted = [(image_id, qvec, tuple(t + 1.0 for t in tvec), *rest) for image_id, qvec, tvec, *rest in images]
    _write_colmap(tmp_path, _CAMERAS, shifted, binary=True)  # as COLMAP does, the binary model is read
    binary = read_poses(tmp_path / "cameras.txt")
    offset = [np.asarray(b.extrinsic)[:3, 3] - np.asarray(t.extrinsic)[:3, 3]
              for b, t in zip(binary.trajectory.parameters, text.trajectory.parameters)]
    np.testing.assert_allclose(offset, 1.0, rtol=0, atol=1e-12)


def test_zero_distortion_coefficients_give_no_warning(tmp_path):
    cameras = [(7, "OPENCV", 1024, 768, [900.0, 905.0, 512.0, 384.0, 0.0, 0.0, 0.0, 0.0])]
    _write_colmap(tmp_path, cameras, _images(camera_ids=(7,)), binary=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(read_poses(tmp_path)) == 1


def test_the_trajectory_is_what_the_library_takes_for_cameras(tmp_path):
    from o3dvis.cameras import as_views

    _write_colmap(tmp_path, _CAMERAS[:2], _images(camera_ids=(1, 2, 2)), binary=True)
    views = as_views(read_poses(tmp_path).trajectory)
    assert len(views) == 3


def _fisheye(tmp_path, binary):
    cameras = [*_CAMERAS, (3, "OPENCV_FISHEYE", 640, 480, [300.0, 300.0, 320.0, 240.0, 0.1, 0.0, 0.0, 0.0])]
    _write_colmap(tmp_path, cameras, _images(camera_ids=(1, 3)), binary)


def _cut_images(tmp_path, binary):
    _write_colmap(tmp_path, _CAMERAS, _images(), binary=True)
    content = (tmp_path / "images.bin").read_bytes()
    (tmp_path / "images.bin").write_bytes(content[:-30])


def _trailing_bytes(tmp_path, binary):
    _write_colmap(tmp_path, _CAMERAS, _images(), binary=True)
    with open(tmp_path / "cameras.bin", "ab") as f:
        f.write(b"\0" * 8)


def _with_image(qvec=(1.0, 0.0, 0.0, 0.0), tvec=(0.0, 0.0, 0.0), camera_id=1):
    def write(tmp_path, binary):
        _write_colmap(tmp_path, _CAMERAS, [(4, qvec, tvec, camera_id, "a.jpg", [])], binary)
    return write


def _no_points_lines(tmp_path, binary):
    _write_colmap(tmp_path, _CAMERAS, _images(), binary=False)
    lines = (tmp_path / "images.txt").read_text().splitlines()
    (tmp_path / "images.txt").write_text("\n".join(line for line in lines[2:] if line.startswith(("5", "2", "9", "3"))
                                                   and "jpg" in line) + "\n")


@pytest.mark.parametrize("binary", [False, True])
@pytest.mark.parametrize("write, message", [
    (_fisheye, r"image 2 \('frame 0002\.jpg'\) uses camera 3 of model OPENCV_FISHEYE, which is no pinhole model"),
    (_with_image(qvec=(2.0, 0.0, 0.0, 0.0)), r"image 4 \('a\.jpg'\): its rotation qvec .* not a unit quaternion"),
    (_with_image(qvec=(0.0, 0.0, 0.0, 0.0)), r"image 4 \('a\.jpg'\): its rotation qvec .* not a unit quaternion"),
    (_with_image(tvec=(0.0, float("nan"), 0.0)), r"image 4 \('a\.jpg'\): its tvec .* NaN or infinite"),
    (_with_image(camera_id=4), r"image 4 \('a\.jpg'\) uses camera 4, which cameras\.(txt|bin) lacks"),
    (lambda tmp_path, binary: _write_colmap(tmp_path, _CAMERAS, [], binary), r"no image in it"),
], ids=["fisheye", "qvec of norm 2", "qvec of zeros", "nan tvec", "missing camera", "no image"])
def test_a_bad_colmap_model_is_refused(tmp_path, binary, write, message):
    write(tmp_path, binary)
    with pytest.raises(ValueError, match=rf"^{_escaped(tmp_path)}/images\.{'bin' if binary else 'txt'}: {message}"):
        read_poses(tmp_path)


@pytest.mark.parametrize("write, message", [
    (_cut_images, r"images\.bin: truncated COLMAP file: it ends inside image record 3"),
    (_trailing_bytes, r"cameras\.bin: 8 bytes follow its 3 cameras"),
    (_no_points_lines, r"images\.txt: line 2 should hold the 2D points of image 5 as triples"),
], ids=["cut", "trailing bytes", "no lines of points"])
def test_a_damaged_colmap_file_is_refused(tmp_path, write, message):
    write(tmp_path, True)
    with pytest.raises(ValueError, match=rf"^{_escaped(tmp_path)}/{message}"):
        read_poses(tmp_path)


def test_an_unknown_colmap_camera_model_is_named(tmp_path):
    _write_colmap(tmp_path, _CAMERAS, _images(camera_ids=(1, 7)), binary=False)
    text = (tmp_path / "cameras.txt").read_text().replace("OPENCV", "WEIRD_LENS")
    (tmp_path / "cameras.txt").write_text(text)
    with pytest.raises(ValueError, match=r"uses camera 7 of model WEIRD_LENS, which is no pinhole model"):
        read_poses(tmp_path)


@pytest.mark.parametrize("missing", ["cameras.txt", "images.txt"])
def test_a_colmap_folder_without_its_cameras_or_images_file_is_refused(tmp_path, missing):
    _write_colmap(tmp_path, _CAMERAS, _images(), binary=False)
    (tmp_path / missing).unlink()
    with pytest.raises(FileNotFoundError, match=rf"^{_escaped(tmp_path)}: no COLMAP model: it holds "
                                                r"(cameras|images)\.txt, where one needs"):
        read_poses(tmp_path)
