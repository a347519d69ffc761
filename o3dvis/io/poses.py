"""Reading camera poses: Open3D's trajectory JSON and LOG files, and COLMAP models.

Open3D's ``read_pinhole_camera_trajectory`` only warns where it fails, and gives
an empty trajectory; it reads a LOG file up to its first blank line and fills a
pose row that lacks a number from the next line, without a word. Here the file
is checked first (a JSON parser's message with its line and column, each
pose's numbers, the LOG file's lines), Open3D reads it, and what it read is
compared with the file's numbers; then every pose must be a rigid transform
with a valid intrinsic, as the rest of the library takes them
(:func:`o3dvis.cameras.frustum_from_pinhole`). COLMAP models are read by
:mod:`o3dvis.io.colmap`.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .colmap import COLMAP_FILES, read_colmap

if TYPE_CHECKING:
    import open3d as o3d

__all__ = ["Poses", "POSE_SUFFIXES", "read_poses"]

POSE_SUFFIXES = (".json", ".log")
_TOL = 1e-9  # relative difference allowed between Open3D's reading of a pose and the file's numbers
_JSON_CLASSES = ("PinholeCameraTrajectory", "PinholeCameraParameters")


@dataclass(frozen=True)
class Poses:
    """Camera poses read by :func:`read_poses`.

    Attributes:
        trajectory: the cameras, each a ``PinholeCameraParameters`` with its world-to-camera extrinsic
            and its intrinsic, in the file's order (a COLMAP model's: by image id); what
            :func:`o3dvis.cameras.as_views` and the rest of the library take.
        names: a name per camera: a COLMAP model's image names (relative to its image folder);
            for JSON and LOG files, which name none, the camera's index in the file (``"0"``, ``"1"``, ...).
    """

    trajectory: o3d.camera.PinholeCameraTrajectory
    names: tuple[str, ...]

    def __len__(self) -> int:
        return len(self.names)

    def __repr__(self) -> str:
        shown = ", ".join(map(repr, self.names[:3])) + (", ..." if len(self) > 3 else "")
        return f"Poses({len(self)} cameras: {shown})"


def read_poses(path: str | Path, intrinsic: o3d.camera.PinholeCameraIntrinsic | None = None) -> Poses:
    """Reads camera poses from an Open3D trajectory file or a COLMAP model.

    Args:
        path: an Open3D ``.json`` file (a ``PinholeCameraTrajectory``, or one
            ``PinholeCameraParameters``), an Open3D ``.log`` file, or a folder
            holding a COLMAP model (``cameras.bin`` and ``images.bin``, or
            ``cameras.txt`` and ``images.txt``; binary first, as COLMAP reads
            them) or one of those files.
        intrinsic: for a LOG file, which holds poses only, every camera's
            intrinsic (default: what Open3D gives, its PrimeSense default of
            640 x 480 pixels and focal length 525).

    Returns:
        :class:`Poses`: the trajectory and a name per camera.

    Raises:
        FileNotFoundError: no such file or folder, or a COLMAP folder without
            its cameras or images file.
        ValueError: an unknown suffix, an ``intrinsic`` for a file that holds
            its own, a file that is not JSON or not a trajectory, a LOG file
            cut short or with a line that is not a pose's, no pose, NaN or
            infinite numbers, poses Open3D read otherwise than the file
            holds them, an extrinsic that is not a rigid transform (an
            orthonormal rotation with determinant +1, last row 0 0 0 1), a bad
            intrinsic, or a COLMAP model that is broken (see
            :func:`o3dvis.io.colmap.read_colmap`).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path} not found")
    suffix = "" if path.is_dir() or path.name in COLMAP_FILES else path.suffix.lower()
    if suffix not in ("", *POSE_SUFFIXES):
        raise ValueError(f"{path}: unknown pose format {path.suffix!r}; use a {' or '.join(POSE_SUFFIXES)} file or a "
                         "COLMAP model's folder")
    if intrinsic is not None and suffix != ".log":
        raise ValueError(f"{path} holds its cameras' intrinsics; an intrinsic is taken for a .log file only")
    if not suffix:
        frames = read_colmap(path if path.is_dir() else path.parent)
    else:
        frames = _read_json(path) if suffix == ".json" else _read_log(path, intrinsic)
    return _checked(path, frames)


def _checked(path: Path, frames: list[tuple[str, o3d.camera.PinholeCameraParameters]]) -> Poses:
    """The frames as :class:`Poses`, each checked as the library takes a camera.

    Raises:
        ValueError: no frame, or one that :func:`o3dvis.cameras.frustum_from_pinhole` refuses.
    """
    import open3d as o3d

    from ..cameras import frustum_from_pinhole

    if not frames:
        raise ValueError(f"{path}: no camera pose in it")
    for index, (name, params) in enumerate(frames):
        try:
            frustum_from_pinhole(params)
        except ValueError as error:
            raise ValueError(f"{path}: camera {index} ({name}): {error}") from None
    trajectory = o3d.camera.PinholeCameraTrajectory()
    trajectory.parameters = [params for _, params in frames]
    return Poses(trajectory, tuple(name for name, _ in frames))


def _read_text(path: Path, kind: str) -> str:
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a {kind} file (not UTF-8 text)") from None


def _read_json(path: Path) -> list[tuple[str, o3d.camera.PinholeCameraParameters]]:
    """The cameras of an Open3D JSON file, checked before and after Open3D reads them."""
    import open3d as o3d

    try:
        document = json.loads(_read_text(path, "JSON"))
    except json.JSONDecodeError as error:
        raise ValueError(f"{path}: not JSON ({error})") from None
    kind = document.get("class_name") if isinstance(document, dict) else None
    if kind not in _JSON_CLASSES:
        raise ValueError(f"{path}: not an Open3D camera file: its class_name is {kind!r}, not "
                         f"{' or '.join(map(repr, _JSON_CLASSES))}")
    entries = document.get("parameters") if kind == _JSON_CLASSES[0] else [document]
    if not isinstance(entries, list):
        raise ValueError(f"{path}: its 'parameters' is not a list of PinholeCameraParameters")
    expected = [_json_camera(path, index, entry) for index, entry in enumerate(entries)]
    if kind == _JSON_CLASSES[0]:
        read = list(o3d.io.read_pinhole_camera_trajectory(str(path)).parameters)
    else:
        read = [o3d.io.read_pinhole_camera_parameters(str(path))]
    if len(read) != len(expected):
        raise ValueError(f"{path}: Open3D read {len(read)} camera poses where the file holds {len(expected)}")
    for index, (params, (extrinsic, matrix, width, height)) in enumerate(zip(read, expected)):
        intrinsic = params.intrinsic
        if not (_close(np.asarray(params.extrinsic), extrinsic) and _close(intrinsic.intrinsic_matrix, matrix)
                and (intrinsic.width, intrinsic.height) == (width, height)):
            raise ValueError(f"{path}: Open3D read camera {index} otherwise than the file holds it")
    return [(str(index), params) for index, params in enumerate(read)]


def _json_camera(path: Path, index: int, entry) -> tuple[np.ndarray, np.ndarray, int, int]:
    """A ``PinholeCameraParameters`` of a JSON file as its numbers: the extrinsic (4, 4), the intrinsic
    matrix (3, 3) (both stored column by column), the width and the height.

    Raises:
        ValueError: not such an object, a list of the wrong length, or numbers that are not finite.
    """
    where = f"{path}: camera {index}"
    if not isinstance(entry, dict) or entry.get("class_name") != "PinholeCameraParameters":
        raise ValueError(f"{where} is not a PinholeCameraParameters object")
    intrinsic = entry.get("intrinsic")
    if not isinstance(intrinsic, dict):
        raise ValueError(f"{where} has no intrinsic object")
    extrinsic = _json_numbers(where, "extrinsic", entry.get("extrinsic"), 16).reshape(4, 4, order="F")
    matrix = _json_numbers(where, "intrinsic_matrix", intrinsic.get("intrinsic_matrix"), 9).reshape(3, 3, order="F")
    size = [intrinsic.get(key) for key in ("width", "height")]
    if not all(isinstance(value, int) and not isinstance(value, bool) for value in size):
        raise ValueError(f"{where}'s intrinsic width and height must be integers, got {size}")
    return extrinsic, matrix, size[0], size[1]


def _json_numbers(where: str, key: str, value, count: int) -> np.ndarray:
    if not (isinstance(value, list) and len(value) == count and all(
            isinstance(x, (int, float)) and not isinstance(x, bool) for x in value)):
        raise ValueError(f"{where}'s {key} must be a list of {count} numbers")
    numbers = np.asarray(value, dtype=np.float64)
    if not np.isfinite(numbers).all():
        raise ValueError(f"{where}'s {key} has NaN or infinite numbers")
    return numbers


def _close(read, expected: np.ndarray) -> bool:
    read = np.asarray(read, dtype=np.float64)
    return read.shape == expected.shape and bool(np.all(np.abs(read - expected) <= _TOL * max(1.0, np.abs(
        expected).max())))


def _read_log(path: Path, intrinsic) -> list[tuple[str, o3d.camera.PinholeCameraParameters]]:
    """The cameras of an Open3D LOG file (each a camera-to-world pose, whose inverse is the extrinsic),
    checked before and after Open3D reads them; with ``intrinsic`` where given."""
    import open3d as o3d

    poses = _log_poses(path)
    read = list(o3d.io.read_pinhole_camera_trajectory(str(path)).parameters)
    if len(read) != len(poses):
        raise ValueError(f"{path}: Open3D read {len(read)} camera poses where the file holds {len(poses)}")
    for index, (params, pose) in enumerate(zip(read, poses)):
        extrinsic = np.asarray(params.extrinsic)
        # a pose with no inverse reads as a non-finite extrinsic, which the rigid-transform check refuses
        if np.isfinite(extrinsic).all() and not _close(extrinsic @ pose, np.eye(4)):
            raise ValueError(f"{path}: Open3D read camera {index} otherwise than the file holds it")
        if intrinsic is not None:
            params.intrinsic = intrinsic
    return [(str(index), params) for index, params in enumerate(read)]


def _log_poses(path: Path) -> np.ndarray:
    """The poses of a LOG file, (F, 4, 4): frames of 5 lines, 3 integers (frame numbers) and 4 rows of
    4 finite numbers, with no blank line before the last frame.

    Raises:
        ValueError: any line otherwise, or a last frame cut short.
    """
    lines = _read_text(path, "LOG").splitlines()
    while lines and not lines[-1].strip():
        lines.pop()
    poses = np.zeros((len(lines) // 5, 4, 4))
    for number, line in enumerate(lines, 1):
        words = line.split()
        frame, row = divmod(number - 1, 5)
        if not words:
            raise ValueError(f"{path}: line {number} is blank; Open3D stops reading a LOG file at a blank line")
        if row == 0:
            if len(words) != 3 or not all(word.lstrip("+-").isdigit() for word in words):
                raise ValueError(f"{path}: line {number} ({line.strip()[:60]!r}) should hold frame {frame}'s 3 "
                                 "integers; not a LOG trajectory, or a corrupted one")
            continue
        try:
            numbers = [float(word) for word in words]
        except ValueError:
            numbers = []
        if len(numbers) != 4 or not all(map(math.isfinite, numbers)):
            raise ValueError(f"{path}: line {number} ({line.strip()[:60]!r}) should be row {row} of frame "
                             f"{frame}'s pose: 4 finite numbers")
        if frame < len(poses):
            poses[frame, row - 1] = numbers
    if len(lines) % 5:
        raise ValueError(f"{path}: truncated LOG file: its last frame has {len(lines) % 5} of the 5 lines of a "
                         "frame (3 frame numbers, then 4 rows of its pose)")
    return poses
