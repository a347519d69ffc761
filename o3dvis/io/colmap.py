"""Reading the cameras of a COLMAP model: ``cameras.txt`` and ``images.txt``, or the binary
``cameras.bin`` and ``images.bin``, as Open3D ``PinholeCameraParameters``.

Layouts, from COLMAP's documentation (``doc/format.rst``) and its model reader
(``scripts/python/read_write_model.py``); binary numbers are little-endian:

- ``cameras.txt``: a line per camera, ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]``.
- ``images.txt``: two lines per image, ``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME``,
  then its 2D points as triples ``X Y POINT3D_ID`` (the line may be empty).
- ``cameras.bin``: uint64 count, then per camera uint32 id, int32 model id, uint64 width,
  uint64 height, and the model's number of float64 parameters.
- ``images.bin``: uint64 count, then per image uint32 id, 4 float64 ``qvec``, 3 float64
  ``tvec``, uint32 camera id, the name's bytes ended by a zero byte, uint64 count of 2D
  points and that many (float64 x, float64 y, int64 point id).

A pose is world-to-camera, the rotation a unit quaternion ``(w, x, y, z)``: Open3D's extrinsic
convention too. COLMAP puts the centre of the top-left pixel at (0.5, 0.5), Open3D (and
o3dvis) at (0, 0): the principal point is moved by half a pixel.
"""

from __future__ import annotations

import struct
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ._quaternions import rotation_matrix

if TYPE_CHECKING:
    import open3d as o3d

__all__ = ["COLMAP_FILES", "PINHOLE_MODELS", "read_colmap"]

COLMAP_FILES = ("cameras.bin", "images.bin", "cameras.txt", "images.txt")
# COLMAP's camera models by id (sensor/models.h): name and number of parameters
_MODELS = {0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5), 4: ("OPENCV", 8),
           5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5), 8: ("SIMPLE_RADIAL_FISHEYE", 4),
           9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12), 11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
           12: ("SIMPLE_DIVISION", 4), 13: ("DIVISION", 5), 14: ("SIMPLE_FISHEYE", 3), 15: ("FISHEYE", 4),
           16: ("EUCM", 6), 17: ("EQUIRECTANGULAR", 2)}
_PARAMETERS = dict(_MODELS.values())
PINHOLE_MODELS = {"SIMPLE_PINHOLE": (0, 0, 1, 2), "PINHOLE": (0, 1, 2, 3), "SIMPLE_RADIAL": (0, 0, 1, 2),
                  "RADIAL": (0, 0, 1, 2), "OPENCV": (0, 1, 2, 3)}
"""The models read, each with the indices of fx, fy, cx and cy in its parameters; the parameters
after those are distortion coefficients, which are ignored (with a warning where not all zero)."""
_MAX_SIZE = 2**31 - 1  # Open3D holds an image's width and height as C ints


@dataclass(frozen=True)
class _Camera:
    model: str
    width: int
    height: int
    params: tuple[float, ...]


@dataclass(frozen=True)
class _Image:
    id: int
    qvec: tuple[float, ...]
    tvec: tuple[float, ...]
    camera_id: int
    name: str


def read_colmap(folder: str | Path) -> list[tuple[str, o3d.camera.PinholeCameraParameters]]:
    """The registered images of a COLMAP model as (name, camera), by image id.

    Args:
        folder: the model's folder (in a COLMAP workspace, e.g. ``sparse/0``).

    Returns:
        (image name, ``PinholeCameraParameters``) per image.

    Warns:
        UserWarning: once, where the cameras used have distortion coefficients
            (SIMPLE_RADIAL, RADIAL, OPENCV) that are not all zero: they are ignored.

    Raises:
        FileNotFoundError: no cameras or images file (binary or text).
        ValueError: a file cut short, a line that is not a camera's or an
            image's, bytes after the last record, an id twice, no image, an
            image whose camera is missing or of a model other than
            ``PINHOLE_MODELS`` (fisheye ones and the others), a camera's size
            that is not positive, NaN or infinite numbers, or a ``qvec`` that
            is not a unit quaternion.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: no such folder")
    kind = next((suffix for suffix in (".bin", ".txt") if all(
        (folder / f"{name}{suffix}").is_file() for name in ("cameras", "images"))), None)
    if kind is None:
        present = [name for name in COLMAP_FILES if (folder / name).is_file()]
        raise FileNotFoundError(f"{folder}: no COLMAP model: it holds {', '.join(present) or 'none of its files'}, "
                                "where one needs cameras.bin and images.bin, or cameras.txt and images.txt (COLMAP "
                                "writes each model to a folder of its own, e.g. sparse/0)")
    cameras_path, images_path = folder / f"cameras{kind}", folder / f"images{kind}"
    if kind == ".bin":
        cameras, images = _cameras_bin(cameras_path), _images_bin(images_path)
    else:
        cameras, images = _cameras_txt(cameras_path), _images_txt(images_path)
    if not images:
        raise ValueError(f"{images_path}: no image in it (a model with no registered image)")
    return _frames(cameras_path, images_path, cameras, images)


def _frames(cameras_path: Path, images_path: Path, cameras: dict[int, _Camera],
            images: list[_Image]) -> list[tuple[str, o3d.camera.PinholeCameraParameters]]:
    """The images as (name, camera), by id (see :func:`read_colmap`)."""
    import open3d as o3d

    frames, distorted = [], set()
    for image in sorted(images, key=lambda image: image.id):
        where = f"{images_path}: image {image.id} ({image.name!r})"
        camera = cameras.get(image.camera_id)
        if camera is None:
            raise ValueError(f"{where} uses camera {image.camera_id}, which {cameras_path.name} lacks")
        if camera.model not in PINHOLE_MODELS:
            raise ValueError(f"{where} uses camera {image.camera_id} of model {camera.model}, which is no pinhole "
                             f"model; the models read are {', '.join(PINHOLE_MODELS)}")
        fx, fy, cx, cy = (camera.params[i] for i in PINHOLE_MODELS[camera.model])
        if any(camera.params[max(PINHOLE_MODELS[camera.model]) + 1:]):
            distorted.add(camera.model)
        rotation = rotation_matrix(image.qvec, f"{where}: its rotation qvec")
        if not np.isfinite(image.tvec).all():
            raise ValueError(f"{where}: its tvec {list(image.tvec)} has NaN or infinite numbers")
        params = o3d.camera.PinholeCameraParameters()
        params.intrinsic = o3d.camera.PinholeCameraIntrinsic(camera.width, camera.height, fx, fy, cx - 0.5, cy - 0.5)
        extrinsic = np.eye(4)
        extrinsic[:3, :3], extrinsic[:3, 3] = rotation, image.tvec
        params.extrinsic = extrinsic
        frames.append((image.name, params))
    if distorted:
        warnings.warn(f"{cameras_path}: the distortion coefficients of the {', '.join(sorted(distorted))} cameras "
                      "are ignored; the poses have their pinhole part (fx, fy, cx, cy) only", stacklevel=4)
    return frames


def _camera(path: Path, where: str, camera_id: int, model: str, width: int, height: int,
            params: list[float]) -> _Camera:
    """A camera, checked: a positive size, finite parameters, as many as a known model has."""
    if not (0 < width <= _MAX_SIZE and 0 < height <= _MAX_SIZE):
        raise ValueError(f"{path}: {where}: camera {camera_id} is {width} x {height} pixels")
    if model in _PARAMETERS and len(params) != _PARAMETERS[model]:
        raise ValueError(f"{path}: {where}: camera {camera_id} of model {model} has {len(params)} parameters where "
                         f"the model has {_PARAMETERS[model]}")
    if not np.isfinite(params).all():
        raise ValueError(f"{path}: {where}: camera {camera_id} has NaN or infinite parameters {params}")
    return _Camera(model, width, height, tuple(params))


def _add(path: Path, where: str, table: dict, key: int, value, what: str) -> None:
    if key in table:
        raise ValueError(f"{path}: {where}: {what} {key} twice")
    table[key] = value


def _lines(path: Path) -> list[str]:
    return path.read_text(encoding="utf-8", errors="surrogateescape").splitlines()


def _numbers(path: Path, number: int, words: list[str], kind, what: str) -> list:
    """``words`` as numbers of ``kind`` (int or float), or a ValueError naming line ``number``."""
    try:
        return [kind(word) for word in words]
    except ValueError:
        raise ValueError(f"{path}: line {number}: {what} must be {'integers' if kind is int else 'numbers'}, got "
                         f"{' '.join(words)[:80]!r}") from None


def _cameras_txt(path: Path) -> dict[int, _Camera]:
    cameras: dict[int, _Camera] = {}
    for number, line in enumerate(_lines(path), 1):
        words = line.split()
        if not words or words[0].startswith("#"):
            continue
        if len(words) < 4:
            raise ValueError(f"{path}: line {number} ({line.strip()[:80]!r}) is not a camera: CAMERA_ID MODEL WIDTH "
                             "HEIGHT PARAMS[]")
        camera_id, width, height = _numbers(path, number, [words[0], *words[2:4]], int, "CAMERA_ID, WIDTH and HEIGHT")
        params = _numbers(path, number, words[4:], float, "the parameters")
        where = f"line {number}"
        _add(path, where, cameras, camera_id, _camera(path, where, camera_id, words[1], width, height, params),
             "camera")
    return cameras


def _images_txt(path: Path) -> list[_Image]:
    lines, images, ids, number = _lines(path), [], {}, 0
    while number < len(lines):
        line, number = lines[number], number + 1
        words = line.split(maxsplit=9)
        if not words or words[0].startswith("#"):
            continue
        if len(words) < 10:
            raise ValueError(f"{path}: line {number} ({line.strip()[:80]!r}) is not an image: IMAGE_ID QW QX QY QZ TX "
                             "TY TZ CAMERA_ID NAME")
        image_id, camera_id = _numbers(path, number, [words[0], words[8]], int, "IMAGE_ID and CAMERA_ID")
        pose = _numbers(path, number, words[1:8], float, "QW QX QY QZ TX TY TZ")
        _add(path, f"line {number}", ids, image_id, None, "image")
        images.append(_Image(image_id, tuple(pose[:4]), tuple(pose[4:]), camera_id, words[9].strip()))
        if number < len(lines):  # the image's 2D points, triples X Y POINT3D_ID
            points = lines[number].split()
            if len(points) % 3:
                raise ValueError(f"{path}: line {number + 1} should hold the 2D points of image {image_id} as "
                                 f"triples X Y POINT3D_ID; it has {len(points)} words (a missing line of points?)")
            # a pose line in its place (images.txt without its lines of points) fails at its name, word 10
            _numbers(path, number + 1, points[:12], float, f"the 2D points of image {image_id}")
            number += 1
    return images


class _Records:
    """A binary COLMAP file read record by record, each read checked against its end."""

    def __init__(self, path: Path, f) -> None:
        self.path, self.f, self.size = path, f, path.stat().st_size

    def unpack(self, fmt: str, what: str) -> tuple:
        size = struct.calcsize(fmt)
        data = self.f.read(size)
        if len(data) < size:
            raise ValueError(f"{self.path}: truncated COLMAP file: it ends inside {what}")
        return struct.unpack(fmt, data)

    def skip(self, size: int, what: str) -> None:
        if self.f.tell() + size > self.size:
            raise ValueError(f"{self.path}: truncated COLMAP file: it ends inside {what}")
        self.f.seek(size, 1)

    def name(self, what: str) -> str:
        """A string ended by a zero byte."""
        start, data = self.f.tell(), b""
        while b"\0" not in data:
            chunk = self.f.read(256)
            if not chunk:
                raise ValueError(f"{self.path}: truncated COLMAP file: it ends inside {what}")
            data += chunk
        end = data.index(b"\0")
        self.f.seek(start + end + 1)
        return data[:end].decode("utf-8", errors="surrogateescape")

    def count(self, what: str) -> int:
        return self.unpack("<Q", f"its number of {what}")[0]

    def end(self, count: int, what: str) -> None:
        if self.f.tell() != self.size:
            raise ValueError(f"{self.path}: {self.size - self.f.tell()} bytes follow its {count} {what}; not a COLMAP "
                             "file of this layout, or a corrupted one")


def _cameras_bin(path: Path) -> dict[int, _Camera]:
    cameras: dict[int, _Camera] = {}
    with open(path, "rb") as f:
        records = _Records(path, f)
        count = records.count("cameras")
        for index in range(count):
            where = f"camera record {index}"
            camera_id, model_id, width, height = records.unpack("<IiQQ", where)
            if model_id not in _MODELS:
                raise ValueError(f"{path}: {where}: camera {camera_id} has the unknown model id {model_id}")
            model, size = _MODELS[model_id]
            params = list(records.unpack(f"<{size}d", where))
            _add(path, where, cameras, camera_id, _camera(path, where, camera_id, model, width, height, params),
                 "camera")
        records.end(count, "cameras")
    return cameras


def _images_bin(path: Path) -> list[_Image]:
    images, ids = [], {}
    with open(path, "rb") as f:
        records = _Records(path, f)
        count = records.count("images")
        for index in range(count):
            where = f"image record {index}"
            image_id, *pose, camera_id = records.unpack("<I7dI", where)
            name = records.name(where)
            records.skip(24 * records.unpack("<Q", where)[0], where)
            _add(path, where, ids, image_id, None, "image")
            images.append(_Image(image_id, tuple(pose[:4]), tuple(pose[4:]), camera_id, name))
        records.end(count, "images")
    return images
