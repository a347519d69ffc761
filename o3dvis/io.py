"""Reading point cloud files, checked against what their headers and sizes promise.

Open3D's ``read_point_cloud`` only warns when a file is shorter than its header
says: a binary PLY that declares 100 000 vertices and holds 30 floats comes back
as 100 000 points, most of them zeros, and a PCD or PTS header that overstates
its count gives points made of whatever memory held. :func:`read_point_cloud`
checks the file before Open3D reads it (its header, its size, the numbers on
each line) and what Open3D read after, and raises a ``ValueError`` that names
the file and the problem instead.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["read_point_cloud", "SUFFIXES"]

# the formats Open3D reads point clouds from, and the numbers on each data line of the text ones
SUFFIXES = (".ply", ".pcd", ".xyz", ".xyzn", ".xyzrgb", ".pts")
_LINE_NUMBERS = {".xyz": 3, ".xyzn": 6, ".xyzrgb": 6, ".pts": 3}
_PLY_TYPES = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2, "uint16": 2,
              "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}
_MAX_HEADER = 1 << 20  # bytes searched for the end of a PLY or PCD header
_CHUNK = 1 << 24  # bytes of a text file scanned at once


@dataclass
class _Text:
    """Statistics of a text file's data: numbers (whitespace-separated tokens), non-blank lines,
    and the first non-blank line with fewer numbers than a data line needs (1-based, 0: none)."""

    tokens: int = 0
    lines: int = 0
    first_short: int = 0


def _scan_text(f, min_tokens: int, first_line: int) -> _Text:
    """Scans the rest of an open binary file line by line, in chunks (see :class:`_Text`)."""
    stats, carry, line = _Text(), b"", first_line
    while True:
        chunk = f.read(_CHUNK)
        data = carry + chunk
        cut = len(data) if not chunk else data.rfind(b"\n") + 1
        carry, data = data[cut:], data[:cut]
        if data:
            byte = np.frombuffer(data, dtype=np.uint8)
            space = byte <= 32  # whitespace and control characters separate numbers
            starts = np.flatnonzero(~space & np.concatenate([[True], space[:-1]]))
            newlines = np.flatnonzero(byte == 10)
            lines = len(newlines) + (byte[-1] != 10)
            per_line = np.bincount(np.searchsorted(newlines, starts), minlength=lines)
            stats.tokens += int(per_line.sum())
            stats.lines += int((per_line > 0).sum())
            short = np.flatnonzero((per_line > 0) & (per_line < min_tokens))
            if len(short) and not stats.first_short:
                stats.first_short = line + int(short[0])
            line += lines
        if not chunk:
            return stats


def _line(path: Path, number: int) -> str:
    """Line ``number`` (1-based) of a text file, shortened for a message."""
    with open(path, "rb") as f:
        for i, text in enumerate(f, 1):
            if i == number:
                text = text.decode("utf-8", "replace").strip()
                return text if len(text) <= 60 else text[:57] + "..."
    return ""


def _header(f, path: Path, end: bytes, kind: str) -> list[str]:
    """The header lines of a PLY or PCD file up to and including the one starting with ``end``;
    leaves ``f`` at the first byte after it."""
    lines: list[str] = []
    while f.tell() < _MAX_HEADER:
        raw = f.readline(_MAX_HEADER)
        if not raw:
            break
        text = raw.decode("ascii", "replace").strip()
        lines.append(text)
        if text.split()[:1] == [end.decode()]:
            return lines
    raise ValueError(f"{path}: not a {kind} file or a truncated one (no '{end.decode()}' line in its header)")


def _count(path: Path, word: str, text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise ValueError(f"{path}: bad {word} {text!r} in the header")
    return value


def _check_ply(path: Path, f, size: int) -> int:
    """Checks a PLY file's data against its header; returns its number of vertices."""
    if f.readline().strip() != b"ply":
        raise ValueError(f"{path}: not a PLY file (it does not start with 'ply')")
    lines = _header(f, path, b"end_header", "PLY")
    data = size - f.tell()
    fmt, elements = None, []  # elements: [name, count, fixed bytes per row, tokens per row]
    for text in lines[:-1]:
        words = text.split()
        if words[:1] == ["format"] and len(words) >= 2:
            fmt = words[1]
        elif words[:1] == ["element"] and len(words) == 3:
            elements.append([words[1], _count(path, f"count of '{words[1]}'", words[2]), 0, 0])
        elif words[:1] == ["property"] and elements:
            types = words[2:4] if words[1:2] == ["list"] else words[1:2]  # a list: its length's type
            if len(types) < 1 or types[0] not in _PLY_TYPES:
                raise ValueError(f"{path}: bad property line {text!r} in the header")
            elements[-1][2] += _PLY_TYPES[types[0]]
            elements[-1][3] += 1
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise ValueError(f"{path}: unknown PLY format {fmt!r}")
    vertices = next((count for name, count, _, _ in elements if name == "vertex"), None)
    if vertices is None:
        raise ValueError(f"{path}: the PLY header declares no vertex element")
    if fmt == "ascii":
        need = sum(count * tokens for _, count, _, tokens in elements)
        have = _scan_text(f, 0, 0).tokens
        if have < need:
            raise ValueError(f"{path}: truncated PLY file: its header declares {_declared(elements)} "
                             f"({need} numbers at least) but it holds {have} numbers")
    else:
        need = sum(count * row for _, count, row, _ in elements)
        if data < need:
            raise ValueError(f"{path}: truncated PLY file: its header declares {_declared(elements)} "
                             f"({need} bytes at least) but it holds {data} bytes of data")
    return vertices


def _declared(elements: list) -> str:
    return ", ".join(f"'element {name} {count}'" for name, count, _, _ in elements)


def _check_pcd(path: Path, f, size: int) -> int:
    """Checks a PCD file's data against its header; returns its number of points."""
    fields = {}
    for text in _header(f, path, b"DATA", "PCD"):
        words = text.split()
        if words and not words[0].startswith("#"):
            fields[words[0].upper()] = words[1:]
    sizes = fields.get("SIZE", [])
    counts = fields.get("COUNT", ["1"] * len(sizes))
    if "POINTS" in fields:
        points = _count(path, "POINTS", " ".join(fields["POINTS"]))
    else:
        points = (_count(path, "WIDTH", " ".join(fields.get("WIDTH", [])))
                  * _count(path, "HEIGHT", " ".join(fields.get("HEIGHT", ["1"]))))
    if not sizes or len(counts) != len(sizes):
        raise ValueError(f"{path}: the PCD header needs SIZE and COUNT for every field")
    row = sum(_count(path, "SIZE", s) * _count(path, "COUNT", c) for s, c in zip(sizes, counts))
    kind, data = fields["DATA"][0].lower() if fields["DATA"] else "", size - f.tell()
    if kind == "ascii":
        need = points * sum(_count(path, "COUNT", c) for c in counts)
        have = _scan_text(f, 0, 0).tokens
        if have < need:
            raise ValueError(f"{path}: truncated PCD file: its header declares {points} points "
                             f"({need} numbers) but it holds {have} numbers")
    elif kind == "binary":
        if data < points * row:
            raise ValueError(f"{path}: truncated PCD file: its header declares {points} points "
                             f"({points * row} bytes) but it holds {data} bytes of data")
    elif kind == "binary_compressed":
        sizes = np.frombuffer(f.read(8), dtype="<u4")
        if len(sizes) < 2 or sizes[0] > data - 8 or sizes[1] != points * row:
            raise ValueError(f"{path}: truncated or corrupted compressed PCD file ({data} bytes of data "
                             f"for {points} points)")
    else:
        raise ValueError(f"{path}: unknown PCD data kind {kind!r}")
    return points


def _check_text(path: Path, f, suffix: str) -> int:
    """Checks that every non-blank line of an XYZ-like or PTS file is a point; returns their number."""
    first = 1
    declared = None
    if suffix == ".pts":  # a first line with the number of points
        first_line = f.readline()
        declared = _count(path, "number of points", first_line.decode("ascii", "replace").strip())
        first = 2
    stats = _scan_text(f, _LINE_NUMBERS[suffix], first)
    if stats.first_short:
        raise ValueError(f"{path}: line {stats.first_short} ({_line(path, stats.first_short)!r}) is not a point "
                         f"of {_LINE_NUMBERS[suffix]} numbers; truncated or not a {suffix} file")
    if declared is not None and declared != stats.lines:
        raise ValueError(f"{path}: its first line declares {declared} points but {stats.lines} lines follow")
    return stats.lines


def _first_unread_line(path: Path, suffix: str) -> str:
    """For a message: the first data line of a text file that does not start with enough numbers."""
    needed = _LINE_NUMBERS[suffix]
    with open(path, "rb") as f:
        for i, raw in enumerate(f, 1):
            words = raw.split()
            if not words or (suffix == ".pts" and i == 1):
                continue
            try:
                [float(w) for w in words[:needed]]
            except ValueError:
                return f"; line {i} ({_line(path, i)!r}) is not a point"
    return ""


def read_point_cloud(path: str | Path):
    """Reads a point cloud file as ``o3d.io.read_point_cloud`` does, checking it first and after.

    Args:
        path: a ``.ply`` (ASCII or binary), ``.pcd`` (ASCII, binary or
            compressed), ``.xyz``, ``.xyzn``, ``.xyzrgb`` or ``.pts`` file.

    Returns:
        The ``o3d.geometry.PointCloud``, with the colours and normals the file holds.

    Raises:
        FileNotFoundError: no such file.
        ValueError: a folder, an unknown suffix, a file shorter than its
            header declares or with a line that is not a point, fewer or more
            points read than the file declares, no point, or NaN or infinite
            coordinates.
    """
    import open3d as o3d

    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{path} is a folder, not a point cloud file")
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found")
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise ValueError(f"{path}: unknown point cloud format {path.suffix!r}; use one of {', '.join(SUFFIXES)}")
    size = path.stat().st_size
    with open(path, "rb") as f:
        if suffix == ".ply":
            expected = _check_ply(path, f, size)
        elif suffix == ".pcd":
            expected = _check_pcd(path, f, size)
        else:
            expected = _check_text(path, f, suffix)
    pcd = o3d.io.read_point_cloud(str(path), format="auto")
    points = np.asarray(pcd.points)
    if len(points) != expected:
        detail = _first_unread_line(path, suffix) if suffix in _LINE_NUMBERS else ""
        raise ValueError(f"{path}: {len(points)} points could be read where the file holds {expected}{detail}")
    if len(points) == 0:
        raise ValueError(f"no points could be read from {path}")
    bad = int((~np.isfinite(points).all(axis=1)).sum())
    if bad:
        raise ValueError(f"{path}: {bad} of {len(points)} points have NaN or infinite coordinates")
    return pcd
