"""Reading LAS, LAZ and E57 maps, the formats laser scanners and mapping pipelines write.

LAS and LAZ are read with laspy (LAZ decompressed by lazrs), E57 with pye57:
optional extras (``pip install "o3dvis[las]"``, ``pip install "o3dvis[e57]"``).
:func:`read_scan` checks what those libraries take on trust: laspy reads an
uncompressed LAS cut at a whole point as the points before the cut, and both
raise their own exceptions on a file cut elsewhere; here a file cut short, a
header that is not a LAS or E57 one, or a pose that is no rotation gives a
``ValueError`` that names the file and the problem.
"""

from __future__ import annotations

import importlib
import warnings
from pathlib import Path
from types import ModuleType

import numpy as np

from ._quaternions import rotation_matrix

__all__ = ["SCANNER_SUFFIXES", "read_scan"]

SCANNER_SUFFIXES = (".las", ".laz", ".e57")
_E57_CARTESIAN = ("cartesianX", "cartesianY", "cartesianZ")
_E57_SPHERICAL = ("sphericalRange", "sphericalAzimuth", "sphericalElevation")
_E57_COLOURS = ("colorRed", "colorGreen", "colorBlue")


def _require(module: str, extra: str, path: Path) -> ModuleType:
    """``module``, imported.

    Raises:
        ImportError: it is not installed, naming the extra that installs it.
    """
    try:
        return importlib.import_module(module)
    except ImportError:
        raise ImportError(f'reading {path.suffix} files ({path}) needs {module}; install it with: '
                          f'pip install "o3dvis[{extra}]"') from None


def read_scan(path: str | Path):
    """Reads a LAS, LAZ or E57 map as an Open3D point cloud.

    Colours are the file's red, green and blue scaled to [0, 1]: a LAS file's
    16-bit values divided by 65535, or by 255 where none exceeds 255 (files
    that store 8-bit colours in the 16-bit fields); an E57 scan's by its
    colour limits. Where a file (or an E57 scan) has no colours but
    intensities, the colours are grey levels of the intensity: a LAS file's
    divided by its largest, an E57 scan's scaled by its intensity limits.
    Several E57 scans are merged, each moved by its pose into the file's
    frame; the merged cloud has colours only where every scan has some.

    Args:
        path: a ``.las``, ``.laz`` or ``.e57`` file.

    Returns:
        ``o3d.geometry.PointCloud`` with float64 points and, where the file
        holds them, colours.

    Raises:
        ImportError: laspy (and for LAZ lazrs) or pye57 is not installed.
        ValueError: an unknown suffix, not a LAS or E57 file, a file cut
            short or corrupted, fewer points read than its header declares,
            bad LAS scale factors, an E57 scan without coordinates, or an E57
            pose whose rotation is not a unit quaternion.
    """
    import open3d as o3d

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in (".las", ".laz"):
        points, colours = _read_las(path)
    elif suffix == ".e57":
        points, colours = _read_e57(path)
    else:
        raise ValueError(f"{path}: unknown scanner format {path.suffix!r}; use one of {', '.join(SCANNER_SUFFIXES)}")
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    if colours is not None:
        pcd.colors = o3d.utility.Vector3dVector(colours)
    return pcd


def _read_las(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """The points of a LAS or LAZ file and their colours (see :func:`read_scan`)."""
    laspy = _require("laspy", "las", path)
    errors = (laspy.errors.LaspyException, ValueError, RuntimeError, EOFError)  # lazrs raises RuntimeErrors
    wanted = laspy.DecompressionSelection
    try:
        reader = laspy.open(path, decompression_selection=wanted.XY_RETURNS_CHANNEL | wanted.Z | wanted.RGB
                            | wanted.INTENSITY)
    except errors as error:
        raise ValueError(f"{path}: not a LAS file, or a truncated one ({error})") from None
    with reader:
        header = reader.header
        _check_las_header(path, header, laspy)
        try:
            data = reader.read_points(header.point_count)
        except errors as error:
            raise ValueError(f"{path}: a truncated or corrupted LAS file ({error})") from None
    if len(data) != header.point_count:
        raise ValueError(f"{path}: truncated LAS file: its header declares {header.point_count} points but "
                         f"{len(data)} could be read")
    points = np.stack([np.asarray(data.x), np.asarray(data.y), np.asarray(data.z)], axis=1).astype(np.float64)
    names = set(header.point_format.dimension_names)
    if {"red", "green", "blue"} <= names:
        colours = np.stack([np.asarray(data[name]) for name in ("red", "green", "blue")], axis=1).astype(np.float64)
        return points, colours / (255.0 if len(colours) and colours.max() <= 255 else 65535.0)
    return points, _grey(np.asarray(data.intensity, dtype=np.float64), 0.0, None) if "intensity" in names else None


def _check_las_header(path: Path, header, laspy: ModuleType) -> None:
    """Checks what a LAS header promises: finite non-zero scale factors, finite offsets, a LAZ decompressor
    where the points are compressed, and for uncompressed points a file long enough to hold them all.

    Raises:
        ImportError: compressed points and no LAZ backend (lazrs) installed.
        ValueError: any of the others broken.
    """
    scales, offsets = np.asarray(header.scales, dtype=np.float64), np.asarray(header.offsets, dtype=np.float64)
    if not (np.isfinite(scales).all() and (scales != 0).all() and np.isfinite(offsets).all()):
        raise ValueError(f"{path}: bad scale factors {scales.tolist()} or offsets {offsets.tolist()} in the LAS "
                         "header; a corrupted file")
    if header.are_points_compressed:
        if not laspy.LazBackend.detect_available():
            raise ImportError(f'reading compressed LAS points ({path}) needs lazrs; install it with: '
                              'pip install "o3dvis[las]"')
        return
    need = header.offset_to_point_data + header.point_count * header.point_format.size
    size = path.stat().st_size
    if size < need:
        raise ValueError(f"{path}: truncated LAS file: its header declares {header.point_count} points of "
                         f"{header.point_format.size} bytes from byte {header.offset_to_point_data} ({need} bytes "
                         f"in all) but the file holds {size} bytes")


def _grey(intensity: np.ndarray, low: float, high: float | None) -> np.ndarray | None:
    """Grey colours (N, 3) in [0, 1] of intensities between ``low`` and ``high`` (None: their largest);
    None where there is no spread to show (all at ``low``)."""
    high = float(intensity.max(initial=low)) if high is None else high
    if not np.isfinite(intensity).all() or not high > low:
        return None
    return np.repeat(np.clip((intensity - low) / (high - low), 0.0, 1.0)[:, None], 3, axis=1)


def _read_e57(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """The points of every scan of an E57 file, each moved by its pose, and their colours where every scan
    has some (see :func:`read_scan`)."""
    pye57 = _require("pye57", "e57", path)
    error_type = pye57.libe57.E57Exception
    try:
        e57 = pye57.E57(str(path))
    except error_type as error:
        raise ValueError(f"{path}: not an E57 file, or a truncated or corrupted one "
                         f"({_first_line(error)})") from None
    with e57:
        try:
            scans = [_e57_scan(path, e57, index) for index in range(e57.scan_count)]
        except error_type as error:
            raise ValueError(f"{path}: a corrupted E57 file ({_first_line(error)})") from None
    if not scans:
        raise ValueError(f"{path}: the E57 file holds no scan")
    points = np.concatenate([scan[0] for scan in scans])
    uncoloured = [index for index, (_, colours) in enumerate(scans) if colours is None]
    if uncoloured and len(uncoloured) < len(scans):
        warnings.warn(f"{path}: scans {uncoloured} of {len(scans)} have no colours nor intensities; the merged "
                      "cloud has no colours", stacklevel=4)
    return points, None if uncoloured else np.concatenate([scan[1] for scan in scans])


def _first_line(error: Exception) -> str:
    """The first line of an exception's text (libE57's go on with debugging details)."""
    return (str(error).strip().splitlines() or [type(error).__name__])[0]


def _e57_scan(path: Path, e57, index: int) -> tuple[np.ndarray, np.ndarray | None]:
    """Scan ``index`` of an open E57 file: its valid points moved by its pose, and their colours
    (the scan's own, else grey levels of its intensity, else None)."""
    from pye57.utils import convert_spherical_to_cartesian

    header = e57.get_header(index)
    fields = set(header.point_fields)
    coordinates = next((names for names in (_E57_CARTESIAN, _E57_SPHERICAL) if set(names) <= fields), None)
    if coordinates is None:
        raise ValueError(f"{path}: scan {index} has neither cartesian nor spherical coordinates (its fields: "
                         f"{', '.join(sorted(fields))})")
    state = "cartesianInvalidState" if coordinates == _E57_CARTESIAN else "sphericalInvalidState"
    shade = _E57_COLOURS if set(_E57_COLOURS) <= fields else ("intensity",) if "intensity" in fields else ()
    data = _e57_fields(path, e57, header, index, [*coordinates, *shade, *([state] if state in fields else [])])
    valid = data.pop(state) == 0 if state in data else slice(None)  # 1: a direction only, 2: no point
    local = np.stack([data[name][valid] for name in coordinates], axis=1)
    if coordinates == _E57_SPHERICAL:
        local = convert_spherical_to_cartesian(local)
    rotation, translation = _e57_pose(path, header, index)
    points = local @ rotation.T + translation
    if shade == _E57_COLOURS:
        limits = [_limits(header, "colorLimits", f"{name}Minimum", f"{name}Maximum", (0.0, 255.0))
                  for name in _E57_COLOURS]
        colours = np.stack([(data[name][valid] - low) / (high - low) if high > low else np.zeros(len(points))
                            for name, (low, high) in zip(_E57_COLOURS, limits)], axis=1)
        return points, np.clip(colours, 0.0, 1.0)
    if shade:
        low, high = _limits(header, "intensityLimits", "intensityMinimum", "intensityMaximum", (0.0, None))
        return points, _grey(data["intensity"][valid], low, high)
    return points, None


def _e57_fields(path: Path, e57, header, index: int, names: list[str]) -> dict[str, np.ndarray]:
    """The fields ``names`` of scan ``index``'s points, each as float64 (libE57 converts integers and
    scales scaled integers).

    Raises:
        ValueError: fewer points read than the scan declares.
    """
    from pye57 import libe57

    count = header.point_count
    data = {name: np.zeros(count) for name in names}
    if not count:
        return data
    buffers = libe57.VectorSourceDestBuffer()
    for name, values in data.items():
        buffers.append(libe57.SourceDestBuffer(e57.image_file, name, values, count, True, True))
    reader = header.points.reader(buffers)
    try:
        read = reader.read()
    finally:
        reader.close()
    if read != count:
        raise ValueError(f"{path}: scan {index} declares {count} points but {read} could be read; a corrupted file")
    return data


def _limits(header, node: str, low: str, high: str, default: tuple[float, float | None]) -> tuple[float, float | None]:
    """A scan's limits of a field (``node``'s ``low`` and ``high`` children), or ``default`` where it has none."""
    if not header.node.isDefined(node):
        return default
    limits = header.node[node]
    return tuple(float(limits[name].value()) if limits.isDefined(name) else value
                 for name, value in zip((low, high), default))


def _e57_pose(path: Path, header, index: int) -> tuple[np.ndarray, np.ndarray]:
    """An E57 scan's pose, scan to file frame: its rotation matrix and translation (identity and zero where
    it has none).

    Raises:
        ValueError: non-finite numbers, or a rotation that is not a unit quaternion (see
            :func:`~o3dvis.io._quaternions.rotation_matrix`).
    """
    node = header.node
    if not node.isDefined("pose"):
        return np.eye(3), np.zeros(3)
    pose = node["pose"]
    q = np.array([1.0, 0.0, 0.0, 0.0])
    t = np.zeros(3)
    if pose.isDefined("rotation"):
        q = np.array([float(pose["rotation"][name].value()) for name in "wxyz"])
    if pose.isDefined("translation"):
        t = np.array([float(pose["translation"][name].value()) for name in "xyz"])
    if not np.isfinite(t).all():
        raise ValueError(f"{path}: scan {index}'s pose has NaN or infinite translation {t.tolist()}")
    return rotation_matrix(q, f"{path}: scan {index}'s pose rotation"), t
