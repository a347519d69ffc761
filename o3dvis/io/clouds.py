"""Reading point cloud files, checked against what their headers and sizes promise.

The formats Open3D reads are checked here; :func:`read_point_cloud` reads LAS,
LAZ and E57 maps through :mod:`o3dvis.io.scanners` with the same final checks.

Open3D's ``read_point_cloud`` only warns when a file is shorter than its header
says: a binary PLY that declares 100 000 vertices and holds 30 floats comes back
as 100 000 points, most of them zeros, and a PCD or PTS header that overstates
its count gives points made of whatever memory held. Headers mislead it too: a
PLY vertex without ``z`` or with ``x`` as a list, or a PCD field of ``TYPE F
SIZE 2``, gives unset memory or zeros as points, and a PCD with ``normal_x``
but no ``normal_y`` crashes the process. :func:`read_point_cloud` checks the
file before Open3D reads it (its header, its size, the numbers on each line, a
compressed PCD's compressed data) and what Open3D read after (the points,
against the file's own decoded here), and raises a ``ValueError`` that names the
file and the problem instead.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .scanners import SCANNER_SUFFIXES, read_scan

__all__ = ["read_point_cloud", "SUFFIXES"]

# the formats Open3D reads point clouds from, all the formats read here, and the numbers on each data line of
# Open3D's text ones
_OPEN3D_SUFFIXES = (".ply", ".pcd", ".xyz", ".xyzn", ".xyzrgb", ".pts")
SUFFIXES = _OPEN3D_SUFFIXES + SCANNER_SUFFIXES
_LINE_NUMBERS = {".xyz": 3, ".xyzn": 6, ".xyzrgb": 6, ".pts": 3}
_PLY_TYPES = {"char": "i1", "uchar": "u1", "int8": "i1", "uint8": "u1", "short": "i2", "ushort": "u2", "int16": "i2",
              "uint16": "u2", "int": "i4", "uint": "u4", "int32": "i4", "uint32": "u4", "float": "f4", "float32": "f4",
              "double": "f8", "float64": "f8"}
# the sets of properties (PLY) or fields (PCD) Open3D reads: a point's, needed, and a normal's and a colour's, each
# whole or absent (Open3D fills a partial set from unset memory, or crashes on it)
_PLY_SETS = {"point": ("x", "y", "z"), "normal": ("nx", "ny", "nz"), "colour": ("red", "green", "blue")}
_PCD_SETS = {"point": ("x", "y", "z"), "normal": ("normal_x", "normal_y", "normal_z")}
# the PCD (TYPE, SIZE) pairs Open3D 0.20 reads as numbers from binary data, with their numpy types: it reads any
# other pair as 0; from ASCII data it parses the text, so a double (F 8) is read there too. Binary doubles of
# the points and normals are decoded here and replace the zeros it reads (not in compressed data)
_PCD_DOUBLE = ("F", 8)
_PCD_NUMBERS = {("F", 4): "<f4", ("I", 1): "i1", ("I", 2): "<i2", ("I", 4): "<i4", ("U", 1): "u1", ("U", 2): "<u2",
                ("U", 4): "<u4"}
_PCD_KEYWORDS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS", "DATA")
_PCD_LINE = 1023  # bytes of a PCD line Open3D reads at once: a longer line is read as several
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


def _header(f, path: Path, end: bytes, kind: str, max_line: int = _MAX_HEADER) -> list[str]:
    """The header lines of a PLY or PCD file up to and including the one starting with ``end``;
    leaves ``f`` at the first byte after it.

    Raises:
        ValueError: no such line, a line longer than ``max_line`` bytes, or a control byte other
            than a tab (a corrupted header: Open3D's readers split lines at some of them, words
            at others, not as this check does).
    """
    lines: list[str] = []
    while f.tell() < _MAX_HEADER:
        raw = f.readline(_MAX_HEADER)
        if not raw:
            break
        body = raw.rstrip(b"\r\n")
        byte = np.frombuffer(body, dtype=np.uint8)
        odd = np.flatnonzero(((byte < 32) & (byte != 9)) | (byte == 127))
        if len(odd):
            raise ValueError(f"{path}: control byte {body[odd[0]]:#04x} in line {len(lines) + 1} of the {kind} header; "
                             f"a corrupted {kind} file")
        if len(raw) > max_line:
            raise ValueError(f"{path}: line {len(lines) + 1} of the {kind} header is longer than {max_line} bytes")
        text = body.decode("ascii", "replace").strip()
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


def _check_sets(path: Path, names: list[str], sets: dict[str, tuple[str, ...]], kind: str, ordered: bool) -> None:
    """Checks the names of a PLY vertex's properties or a PCD's fields: each once, a point's whole,
    a normal's and a colour's whole or absent, and with ``ordered`` each set's last name after the
    others (Open3D's PLY reader moves to the next point, normal or colour at it).

    Raises:
        ValueError: a name twice, or a set partial or out of order.
    """
    twice = sorted({name for name in names if names.count(name) > 1})
    if twice:
        raise ValueError(f"{path}: the {kind} declares {twice[0]!r} twice")
    for what, group in sets.items():
        missing = [name for name in group if name not in names]
        if missing and (what == "point" or len(missing) < len(group)):
            raise ValueError(f"{path}: the {kind} lacks {', '.join(missing)} (a {what} needs {', '.join(group)})")
        if ordered and not missing and names.index(group[-1]) < max(names.index(name) for name in group[:-1]):
            raise ValueError(f"{path}: the {kind} declares {group[-1]!r} before {', '.join(group[:-1])}; a {what}'s "
                             f"{group[-1]!r} must follow them for Open3D to read it")


@dataclass
class _Element:
    """A PLY element: its name, its count, and its properties as (name, numpy type of the value or
    of a list's length, whether it is a list)."""

    name: str
    count: int
    properties: list[tuple[str, str, bool]]

    @property
    def row(self) -> int:
        """Bytes of a row in binary, at least (a list's length only)."""
        return sum(np.dtype(kind).itemsize for _, kind, _ in self.properties)

    @property
    def lists(self) -> list[str]:
        return [name for name, _, is_list in self.properties if is_list]


def _ply_header(path: Path, f) -> tuple[str, list[_Element]]:
    """A PLY file's format and elements; leaves ``f`` at the first byte of its data."""
    if f.readline().strip() != b"ply":
        raise ValueError(f"{path}: not a PLY file (it does not start with 'ply')")
    fmt, elements = None, []
    for text in _header(f, path, b"end_header", "PLY")[:-1]:
        words = text.split()
        if words[:1] == ["format"] and len(words) >= 2:
            fmt = words[1]
        elif words[:1] == ["element"] and len(words) == 3:
            elements.append(_Element(words[1], _count(path, f"count of '{words[1]}'", words[2]), []))
        elif words[:1] == ["property"] and elements:
            is_list = words[1:2] == ["list"]
            kind = words[2:3] if is_list else words[1:2]  # a list: its length's type
            if len(words) != (5 if is_list else 3) or kind[0] not in _PLY_TYPES or (
                    is_list and words[3] not in _PLY_TYPES):
                raise ValueError(f"{path}: bad property line {text!r} in the header")
            elements[-1].properties.append((words[-1], _PLY_TYPES[kind[0]], is_list))
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise ValueError(f"{path}: unknown PLY format {fmt!r}")
    return fmt, elements


def _check_ply(path: Path, f, size: int) -> tuple[int, np.ndarray]:
    """Checks a PLY file's header and data; returns its number of vertices and their x, y, z as the file declares
    them (decoded here, to compare with what Open3D reads)."""
    fmt, elements = _ply_header(path, f)
    at = next((i for i, element in enumerate(elements) if element.name == "vertex"), None)
    if at is None:
        raise ValueError(f"{path}: the PLY header declares no vertex element")
    vertex = elements[at]
    _check_sets(path, [name for name, _, _ in vertex.properties], _PLY_SETS, "PLY vertex element", ordered=True)
    if vertex.lists:
        raise ValueError(f"{path}: the PLY vertex property {vertex.lists[0]!r} is a list; Open3D reads a vertex's "
                         "properties as single numbers")
    fixed = not any(element.lists for element in elements)  # then the data's size is known exactly
    start = f.tell()
    if fmt == "ascii":
        need = sum(element.count * len(element.properties) for element in elements)
        have = _scan_text(f, 0, 0).tokens
        if have < need or (fixed and have > need):
            raise ValueError(f"{path}: {'truncated PLY file: ' if have < need else ''}its header declares "
                             f"{_declared(elements)} ({need} numbers{'' if fixed else ' at least'}) but it holds "
                             f"{have} numbers")
        f.seek(start)
        names = [name for name, _, _ in vertex.properties]
        return vertex.count, _text_points(path, f, sum(element.count for element in elements[:at]), vertex.count,
                                          len(names), [names.index(name) for name in "xyz"], "PLY vertex rows")
    need = sum(element.count * element.row for element in elements)
    if size - start < need or (fixed and size - start > need):
        raise ValueError(f"{path}: {'truncated PLY file: ' if size - start < need else ''}its header declares "
                         f"{_declared(elements)} ({need} bytes{'' if fixed else ' at least'}) but it holds "
                         f"{size - start} bytes of data")
    before = next((element.name for element in elements[:at] if element.lists), None)
    if before is not None:
        raise ValueError(f"{path}: its vertex element follows {before!r}, an element with list properties; only "
                         "vertices after elements of fixed size are read")
    f.seek(start + sum(element.count * element.row for element in elements[:at]))
    order = "<" if fmt == "binary_little_endian" else ">"
    rows = np.fromfile(f, np.dtype([(name, order + kind) for name, kind, _ in vertex.properties]), vertex.count)
    return vertex.count, np.stack([rows[name] for name in "xyz"], axis=1).astype(np.float64)


def _text_points(path: Path, f, skip: int, count: int, columns: int, xyz: list[int], what: str) -> np.ndarray:
    """The x, y, z (at the columns ``xyz``) of ``count`` lines of ``columns`` numbers after ``skip`` lines."""
    if not count:
        return np.zeros((0, 3))
    try:
        rows = np.loadtxt(f, comments=None, skiprows=skip, max_rows=count, ndmin=2)
    except ValueError as error:
        raise ValueError(f"{path}: the {what} are not lines of {columns} numbers ({error})") from None
    if rows.shape != (count, columns):
        raise ValueError(f"{path}: the {what} are {rows.shape[0]} lines of {rows.shape[1]} numbers where the header "
                         f"declares {count} of {columns}")
    return rows[:, xyz]


def _declared(elements: list[_Element]) -> str:
    return ", ".join(f"'element {element.name} {element.count}'" for element in elements)


def _pcd_header(path: Path, f) -> dict[str, list[str]]:
    """A PCD header's values by keyword, each keyword once, with SIZE, TYPE and COUNT after FIELDS and
    COUNT after SIZE (Open3D's reader recomputes the fields' offsets at each of them, dropping the
    counts at a SIZE after them); leaves ``f`` at the first byte of the data."""
    values: dict[str, list[str]] = {}
    for text in _header(f, path, b"DATA", "PCD", max_line=_PCD_LINE):
        words = text.split()
        if not words or words[0].startswith("#"):
            continue
        key = "FIELDS" if words[0] == "COLUMNS" else words[0]
        if key not in _PCD_KEYWORDS:
            raise ValueError(f"{path}: unknown line {text!r} in the PCD header")
        if key in values:
            raise ValueError(f"{path}: the PCD header has two {key} lines")
        late = "FIELDS" if key in ("SIZE", "TYPE", "COUNT") and "FIELDS" not in values else (
            "COUNT" if key == "SIZE" and "COUNT" in values else None)
        if late:
            raise ValueError(f"{path}: the PCD header's {key} line comes before its {late} line")
        values[key] = words[1:]
    return values


@dataclass
class _Field:
    """A PCD field: its name, TYPE letter, SIZE, COUNT and first number in a row (``column``) and first byte
    in a binary row (``offset``)."""

    name: str
    kind: str
    size: int
    count: int
    column: int
    offset: int


def _pcd_fields(path: Path, values: dict[str, list[str]]) -> list[_Field]:
    """The fields of a PCD header, checked: FIELDS, SIZE, TYPE and COUNT of one length, known TYPE letters,
    positive sizes and counts, a point's fields whole and a normal's whole or absent, each field once.

    Raises:
        ValueError: any of these broken.
    """
    names = values.get("FIELDS", [])
    if not names or "SIZE" not in values:
        raise ValueError(f"{path}: the PCD header needs a FIELDS and a SIZE line")
    columns = {key: values.get(key, [default] * len(names)) for key, default in (("SIZE", ""), ("TYPE", "F"),
                                                                                 ("COUNT", "1"))}
    for key, given in columns.items():
        if len(given) != len(names):
            raise ValueError(f"{path}: the PCD header's {key} line has {len(given)} values for {len(names)} fields")
    unknown = [kind for kind in columns["TYPE"] if kind not in ("F", "I", "U")]
    if unknown:
        raise ValueError(f"{path}: unknown TYPE {unknown[0]!r} in the PCD header (F, I or U)")
    fields, column, offset = [], 0, 0
    for name, size, kind, count in zip(names, columns["SIZE"], columns["TYPE"], columns["COUNT"]):
        size, count = _count(path, "SIZE", size), _count(path, "COUNT", count)
        if not size or not count:
            raise ValueError(f"{path}: the PCD field {name!r} has SIZE {size} and COUNT {count}; both must be positive")
        fields.append(_Field(name, kind, size, count, column, offset))
        column, offset = column + count, offset + size * count
    _check_sets(path, names, _PCD_SETS, "PCD header", ordered=False)
    return fields


def _check_pcd_numbers(path: Path, fields: list[_Field], data: str) -> None:
    """Checks that Open3D reads a PCD's coordinates and normals as the header declares them: single numbers of a
    (TYPE, SIZE) it reads from ``data`` (see ``_PCD_NUMBERS``), and colours as one 4-byte rgb or rgba.

    Raises:
        ValueError: another TYPE, SIZE or COUNT of these fields, or both rgb and rgba.
    """
    readable = set(_PCD_NUMBERS) | ({_PCD_DOUBLE} if data != "binary_compressed" else set())
    allowed = ", ".join(f"{kind} {size}" for kind, size in sorted(readable))
    colours = [field for field in fields if field.name in ("rgb", "rgba")]
    for field in fields:
        if field.name in _PCD_SETS["point"] + _PCD_SETS["normal"] and (
                (field.kind, field.size) not in readable or field.count != 1):
            raise ValueError(f"{path}: the PCD field {field.name!r} is TYPE {field.kind} SIZE {field.size} COUNT "
                             f"{field.count}; from {data} data Open3D reads x, y, z and normals as COUNT 1 of TYPE "
                             f"and SIZE {allowed} only")
    if len(colours) > 1 or any(field.size != 4 or field.count != 1 for field in colours):
        raise ValueError(f"{path}: the PCD colours must be one field, rgb or rgba, of SIZE 4 COUNT 1")


def _check_pcd(path: Path, f, size: int) -> tuple[int, np.ndarray | None, dict[str, np.ndarray]]:
    """Checks a PCD file's header and data; returns its number of points, unless compressed their x, y, z as the
    file declares them (decoded here, to compare with what Open3D reads), and the points and normals Open3D reads
    as zeros from binary doubles, decoded here (``"points"``, ``"normals"``: (N, 3) float64; else empty)."""
    values = _pcd_header(path, f)
    fields = _pcd_fields(path, values)
    if "POINTS" in values:
        points = _count(path, "POINTS", " ".join(values["POINTS"]))
    else:
        points = (_count(path, "WIDTH", " ".join(values.get("WIDTH", [])))
                  * _count(path, "HEIGHT", " ".join(values.get("HEIGHT", ["1"]))))
    kind, start = (values["DATA"] or [""])[0], f.tell()
    if kind not in ("ascii", "binary", "binary_compressed"):
        raise ValueError(f"{path}: unknown PCD data kind {kind!r}")
    _check_pcd_numbers(path, fields, kind)
    xyz = [next(field for field in fields if field.name == name) for name in "xyz"]
    row = sum(field.size * field.count for field in fields)
    if kind == "ascii":
        numbers = sum(field.count for field in fields)
        stats = _scan_text(f, numbers, 1)
        if stats.first_short:
            raise ValueError(f"{path}: line {stats.first_short} of its data is not a point of {numbers} numbers")
        if stats.lines != points:
            raise ValueError(f"{path}: {'truncated PCD file: ' if stats.lines < points else ''}its header declares "
                             f"{points} points ({points * numbers} numbers) but it holds {stats.lines} lines of data")
        f.seek(start)
        return points, _text_points(path, f, 0, points, numbers, [field.column for field in xyz], "PCD data lines"), {}
    data = size - start
    if kind == "binary":
        if data != points * row:
            raise ValueError(f"{path}: {'truncated PCD file: ' if data < points * row else ''}its header declares "
                             f"{points} points ({points * row} bytes) but it holds {data} bytes of data")
        sets = {"points": xyz, "normals": [field for name in _PCD_SETS["normal"] for field in fields
                                           if field.name == name]}
        wanted = [field for group in sets.values() for field in group]
        formats = {**_PCD_NUMBERS, _PCD_DOUBLE: "<f8"}
        rows = np.fromfile(f, np.dtype({"names": [field.name for field in wanted],
                                        "offsets": [field.offset for field in wanted],
                                        "formats": [formats[field.kind, field.size] for field in wanted],
                                        "itemsize": row}), points)
        decoded = {key: np.stack([rows[field.name] for field in group], axis=1).astype(np.float64)
                   for key, group in sets.items() if group}
        doubles = {key: decoded[key] for key, group in sets.items()
                   if any((field.kind, field.size) == _PCD_DOUBLE for field in group)}
        return points, decoded["points"], doubles
    sizes = np.frombuffer(f.read(8), dtype="<u4")
    if len(sizes) < 2 or sizes[0] > data - 8 or sizes[1] != points * row or not _lzf_complete(
            f.read(int(sizes[0])), int(sizes[1])):
        raise ValueError(f"{path}: truncated or corrupted compressed PCD file ({data} bytes of data "
                         f"for {points} points)")
    return points, None, {}


def _lzf_complete(data: bytes, size: int) -> bool:
    """Whether LZF decompresses ``data`` into exactly ``size`` bytes: walks its runs and back-references as
    liblzf's ``lzf_decompress`` does, with its checks, without copying."""
    i = out = 0
    while i < len(data):
        ctrl = data[i]
        if ctrl < 32:  # a run of ctrl + 1 literal bytes
            i, out = i + ctrl + 2, out + ctrl + 1
            if i > len(data):
                return False
        else:  # a back-reference: its length in the top 3 bits (7: plus the next byte), then its distance
            if ctrl >= 224:
                i += 1
            if i + 1 >= len(data) or ((ctrl & 31) << 8) + data[i + 1] >= out:
                return False
            out += (ctrl >> 5) + 2 + (data[i] if ctrl >= 224 else 0)
            i += 2
        if out > size:
            return False
    return out == size


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
    """Reads a point cloud file, checking it first and after.

    The formats Open3D reads are read as ``o3d.io.read_point_cloud`` reads
    them; LAS, LAZ and E57 maps are read by :mod:`o3dvis.io.scanners`.

    Args:
        path: a ``.ply`` (ASCII or binary), ``.pcd`` (ASCII, binary or
            compressed), ``.xyz``, ``.xyzn``, ``.xyzrgb`` or ``.pts`` file, or
            a ``.las``, ``.laz`` or ``.e57`` map (optional extras ``las`` and
            ``e57``).

    Returns:
        The ``o3d.geometry.PointCloud``, float64 points with the colours and
        normals the file holds (a scanner's colours, or its intensity as grey
        levels: see :func:`o3dvis.io.scanners.read_scan`).

    Raises:
        FileNotFoundError: no such file.
        ImportError: a LAS, LAZ or E57 file where its optional extra is not
            installed.
        ValueError: a folder, an unknown suffix, a file shorter than its
            header declares or with a line that is not a point, a PLY or PCD
            header Open3D would misread (a partial set of coordinates, normals
            or colours, a list or a type it does not read as a number, a
            corrupted line), fewer or more points read than the file declares,
            points other than the file's (compared in full, except in a
            compressed PCD, whose compressed data is checked instead), a LAS,
            LAZ or E57 file that is not one or is cut short, no point, or NaN
            or infinite coordinates.
    """
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{path} is a folder, not a point cloud file")
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found")
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise ValueError(f"{path}: unknown point cloud format {path.suffix!r}; use one of {', '.join(SUFFIXES)}")
    pcd = read_scan(path) if suffix in SCANNER_SUFFIXES else _read_open3d(path, suffix)
    points = np.asarray(pcd.points)
    if len(points) == 0:
        raise ValueError(f"no points could be read from {path}")
    bad = int((~np.isfinite(points).all(axis=1)).sum())
    if bad:
        raise ValueError(f"{path}: {bad} of {len(points)} points have NaN or infinite coordinates")
    return pcd


def _read_open3d(path: Path, suffix: str):
    """A file of a format Open3D reads (one of ``_OPEN3D_SUFFIXES``), checked before and after Open3D reads it
    (see :func:`read_point_cloud`)."""
    import open3d as o3d

    size, declared, doubles = path.stat().st_size, None, {}
    with open(path, "rb") as f:
        if suffix == ".ply":
            expected, declared = _check_ply(path, f, size)
        elif suffix == ".pcd":
            expected, declared, doubles = _check_pcd(path, f, size)
        else:
            expected = _check_text(path, f, suffix)
    pcd = o3d.io.read_point_cloud(str(path), format="auto")
    points = np.asarray(pcd.points)
    if len(points) != expected:
        detail = _first_unread_line(path, suffix) if suffix in _LINE_NUMBERS else ""
        raise ValueError(f"{path}: {len(points)} points could be read where the file holds {expected}{detail}")
    for key, values in doubles.items():  # binary doubles, which Open3D reads as zeros
        setattr(pcd, key, o3d.utility.Vector3dVector(values))
    points = np.asarray(pcd.points)
    if declared is not None and not np.array_equal(points, declared, equal_nan=True):
        wrong = np.flatnonzero(~((points == declared) | (np.isnan(points) & np.isnan(declared))).all(axis=1))
        raise ValueError(f"{path}: Open3D read {len(wrong)} of {len(points)} points otherwise than the file declares "
                         f"them (point {wrong[0]}: {points[wrong[0]].tolist()} for {declared[wrong[0]].tolist()}); "
                         "a corrupted file")
    return pcd
