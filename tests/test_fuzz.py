"""Property-based fuzzing of the visibility API with hypothesis (a tiny random network, small clouds).

Clouds are drawn on a dyadic grid (integers times a power of two) in several shapes: scattered,
with repeated points, flat, on a line, clustered; as numpy/torch arrays or Open3D clouds, in
float32 or float64, at scales from 2^-36 to 2^24. Properties:

* any cloud with cameras outside its bounding box gets a (V, N) bool answer, probabilities in
  [0, 1], and the drop-in functions agree with it; a camera inside gets one too, a camera on a
  point a ValueError;
* the answer does not depend on the order of the points (up to float summation order);
* moving cloud and camera together, or scaling both by a power of two, changes nothing, bit for
  bit (on a dyadic grid these maps are exact in float64, so any difference is a real dependence);
* repeated points get the same answer; the same call twice gives the same bits;
* the HPR baselines answer on the same clouds, repeated points alike, the nearest point visible;
* the C Delaunay triangulation of the clouds seen along an axis is exactly Delaunay (checked in
  integers), or empty where the points are fewer than three distinct or on one line;
* the CLI's point cloud reader gives the points of any PLY/PCD/XYZ/PTS file Open3D wrote, and
  refuses the same file cut short, with an overstated count, or replaced by random bytes;
* it reads exactly the values written, or refuses with a ValueError, any PLY/PCD whose header is
  drawn around what Open3D writes (x, y, z, normals, colours dropped, repeated, reordered, of any
  type, lists or counts) and any file Open3D wrote with one header byte replaced, never letting
  Open3D's reader crash on one; ``o3dvis visible`` on these files exits 2 with one line naming the
  file, or writes points of the file.

CI runs about 1 430 cases derandomized (the same every run); benchmarks/fuzz_long.py runs the
same properties with fresh random cases for longer (``O3DVIS_FUZZ_SCALE``, ``O3DVIS_FUZZ_RANDOM``).
"""

from __future__ import annotations

import os
from collections import Counter
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import open3d as o3d
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

import o3dvis
from o3dvis.nn import NetworkConfig, VisibilityNetwork

from conftest import lzf_literal

SCALE = float(os.environ.get("O3DVIS_FUZZ_SCALE", "1"))
RANDOM = os.environ.get("O3DVIS_FUZZ_RANDOM") == "1"
COUNTS: Counter = Counter()
"""Examples run per property (read by benchmarks/fuzz_long.py)."""

UNIT = 6  # coordinates are integers times 2 ** (exponent - UNIT)
_KINDS = ("scattered", "repeated", "flat", "line", "clustered")


def _settings(examples: int):
    return settings(max_examples=max(1, round(examples * SCALE)), deadline=None, derandomize=not RANDOM,
                    database=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


@lru_cache(maxsize=None)
def tiny_model() -> o3dvis.NeuralVisibility:
    """A randomly initialised small network (the properties hold for any weights), reading the
    footprint-splatted buffers too, as the scene model does."""
    torch.manual_seed(0)
    network = VisibilityNetwork(NetworkConfig(depth=5, channels=(8, 8, 8, 8), feature_channels=8,
                                              num_frequencies=2, hidden=(16,), footprints=True))
    return o3dvis.NeuralVisibility(network)


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@st.composite
def grid_clouds(draw, max_points: int = 40) -> tuple[np.ndarray, int]:
    """``(units, exponent)``: (N, 3) int64 grid coordinates of one of the shapes, and a scale exponent."""
    n = draw(st.integers(1, max_points))
    kind = draw(st.sampled_from(_KINDS))
    units = draw(arrays(np.int64, (n, 3), elements=st.integers(-4096, 4096)))
    if kind == "repeated":
        units = units[np.arange(n) % draw(st.integers(1, n))]
    elif kind == "flat":
        units[:, draw(st.integers(0, 2))] = units[0, 0]
    elif kind == "line":
        direction = draw(arrays(np.int64, 3, elements=st.integers(-40, 40)))
        units = units[:1] // 4 + np.arange(n)[:, None] * direction
    elif kind == "clustered":
        units[: n // 2] //= 256
    return units, draw(st.integers(-30, 30))


@st.composite
def outside_cameras(draw, units: np.ndarray, count: int) -> np.ndarray:
    """(V, 3) grid cameras outside the bounding box of ``units``: off one face by at least one unit."""
    cameras = draw(arrays(np.int64, (count, 3), elements=st.integers(-8192, 8192)))
    lo, hi = units.min(axis=0), units.max(axis=0)
    for camera in cameras:
        axis, gap = draw(st.integers(0, 2)), draw(st.integers(1, 8192))
        camera[axis] = hi[axis] + gap if draw(st.booleans()) else lo[axis] - gap
    return cameras


def _world(units: np.ndarray, exponent: int) -> np.ndarray:
    return units * 2.0 ** (exponent - UNIT)


def _as_input(points: np.ndarray, form: str, dtype):
    points = points.astype(dtype)
    if form == "torch":
        return torch.from_numpy(points)
    if form == "open3d":
        return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    if form == "open3d-tensor":
        return o3d.t.geometry.PointCloud(o3d.core.Tensor(points))
    return points


def _probabilities(points, cameras) -> torch.Tensor:
    return tiny_model().encode(points).probabilities(cameras)


@given(grid_clouds(), st.data())
@_settings(200)
def test_any_cloud_gets_a_well_formed_answer(cloud, data):
    COUNTS["well-formed answer"] += 1
    units, exponent = cloud
    views = data.draw(st.integers(1, 3))
    cameras = _world(data.draw(outside_cameras(units, views)), exponent)
    form = data.draw(st.sampled_from(["numpy", "torch", "open3d", "open3d-tensor"]))
    dtype = data.draw(st.sampled_from([np.float64, np.float32]))
    pcd = _as_input(_world(units, exponent), form, dtype)
    n = len(units)
    camera_form = data.draw(st.sampled_from(["numpy", "list", "torch", "open3d"]))
    given_cameras = {"numpy": cameras, "list": cameras.tolist(), "torch": torch.from_numpy(cameras),
                     "open3d": o3d.core.Tensor(cameras)}[camera_form]
    field = tiny_model().encode(pcd)
    mask = field.query(given_cameras)
    probs = field.probabilities(given_cameras)
    assert isinstance(mask, np.ndarray) and mask.dtype == bool and mask.shape == (views, n)
    assert isinstance(probs, torch.Tensor) and probs.shape == (views, n) and probs.dtype == torch.float32
    assert bool(((probs >= 0) & (probs <= 1)).all())
    np.testing.assert_array_equal(mask, probs.numpy() > 0.5)
    if form.startswith("open3d"):
        mesh, pt_map = o3dvis.hidden_point_removal_neural(pcd, cameras[0], model=tiny_model())
        index = np.asarray(pt_map if isinstance(pt_map, list) else pt_map.numpy())
        np.testing.assert_array_equal(index, np.flatnonzero(mask[0]))
        selected = o3dvis.select_visible(pcd, cameras[0], model=tiny_model())
        count = len(selected.points) if form == "open3d" else len(selected.point.positions)
        assert count == mask[0].sum()
    fraction = data.draw(arrays(np.int64, 3, elements=st.integers(0, 2**20))) / 2**20
    lo, hi = _world(units.min(axis=0), exponent), _world(units.max(axis=0), exponent)
    inside = lo + (hi - lo) * fraction
    world = _world(units, exponent)
    if np.linalg.norm(world - inside, axis=1).min() > 1e-6 * (hi - lo).max():  # off the points: answered
        probs = field.probabilities(inside)
        assert probs.shape == (1, n) and bool(((probs >= 0) & (probs <= 1)).all())
    on = world[data.draw(st.integers(0, n - 1))]
    with pytest.raises(ValueError, match="on a point"):
        field.query(on)


@given(grid_clouds(), st.data())
@_settings(150)
def test_answer_does_not_depend_on_point_order(cloud, data):
    COUNTS["point order"] += 1
    units, exponent = cloud
    cameras = _world(data.draw(outside_cameras(units, 2)), exponent)
    order = np.asarray(data.draw(st.permutations(range(len(units)))), dtype=np.int64)
    points = _world(units, exponent)
    a = _probabilities(points, cameras)[:, order]
    b = _probabilities(points[order], cameras)
    torch.testing.assert_close(b, a, atol=1e-4, rtol=0)  # features sum points in another order
    decided = (a - 0.5).abs() > 1e-3
    assert torch.equal((a > 0.5)[decided], (b > 0.5)[decided])


@given(grid_clouds(), st.data())
@_settings(200)
def test_moving_or_scaling_cloud_and_camera_together_changes_nothing(cloud, data):
    COUNTS["translation and scale"] += 1
    units, exponent = cloud
    cameras = data.draw(outside_cameras(units, 2))
    shift = data.draw(arrays(np.int64, 3, elements=st.integers(-2**26, 2**26)))
    factor = data.draw(st.integers(-8, 8))
    a = _probabilities(_world(units, exponent), _world(cameras, exponent))
    b = _probabilities(_world(units + shift, exponent), _world(cameras + shift, exponent))
    c = _probabilities(_world(units, exponent + factor), _world(cameras, exponent + factor))
    assert torch.equal(a, b), f"moved by {_world(shift, exponent)}: max difference {(a - b).abs().max():.3g}"
    assert torch.equal(a, c), f"scaled by 2^{factor}: max difference {(a - c).abs().max():.3g}"


@given(grid_clouds(), st.data())
@_settings(150)
def test_repeated_points_share_an_answer_and_calls_repeat_exactly(cloud, data):
    COUNTS["repeats and determinism"] += 1
    units, exponent = cloud
    copies = np.asarray(data.draw(st.lists(st.integers(0, len(units) - 1), min_size=1, max_size=10)))
    units = np.concatenate([units, units[copies]])
    points, cameras = _world(units, exponent), _world(data.draw(outside_cameras(units, 2)), exponent)
    probs = _probabilities(points, cameras)
    same = (units[:, None] == units[None]).all(axis=2)
    first = same.argmax(axis=1)
    # equal rows may round differently in the MLP's blocked matrix products: not bit for bit
    torch.testing.assert_close(probs, probs[:, first], atol=1e-6, rtol=0)
    again = o3dvis.NeuralVisibility(tiny_model().network).encode(points.copy())
    assert torch.equal(again.probabilities(cameras.copy()), probs)
    np.testing.assert_array_equal(again.query(cameras), probs.numpy() > 0.5)


@given(grid_clouds(max_points=60), st.data())
@_settings(300)
def test_hpr_baselines_answer_any_cloud(cloud, data):
    COUNTS["HPR baselines"] += 1
    units, exponent = cloud
    points = _world(units, exponent)
    cameras = _world(data.draw(outside_cameras(units, data.draw(st.integers(1, 3)))), exponent)
    distance = np.linalg.norm(points[None] - cameras[:, None], axis=2)
    nearest = distance == distance.min(axis=1, keepdims=True)
    same = (units[:, None] == units[None]).all(axis=2).argmax(axis=1)
    # HPR's flip needs a radius beyond every point (a smaller one silently inverts far points)
    for mask in (o3dvis.hidden_point_removal_mask(points, cameras, 100.0 * distance.max()),
                 o3dvis.exponential_hpr_mask(points, cameras, -0.01)):
        assert mask.dtype == bool and mask.shape == (len(cameras), len(points))
        np.testing.assert_array_equal(mask, mask[:, same])
        assert mask[nearest].all(), "the point nearest to a camera is hidden"
    with pytest.raises(ValueError, match="coincides"):
        o3dvis.hidden_point_removal_mask(points, points[data.draw(st.integers(0, len(points) - 1))], 1.0)


@pytest.mark.skipif(os.environ.get("O3DVIS_NATIVE") == "0", reason="C kernels turned off (O3DVIS_NATIVE=0)")
@given(grid_clouds(max_points=60), st.data())
@_settings(300)
def test_delaunay_triangulates_any_plane_cloud(cloud, data):
    """The C Delaunay (o3dvis/apps/delaunay.c) on the clouds above seen along an axis: repeated
    points, lines, clusters, any scale; exactly Delaunay, or no triangle where none can be."""
    from conftest import _check_triangulation

    from o3dvis.apps.delaunay import delaunay_triangles

    COUNTS["Delaunay"] += 1
    units, exponent = cloud
    units = np.delete(units, data.draw(st.integers(0, 2)), axis=1)
    triangles = delaunay_triangles(_world(units, exponent))
    assert triangles.dtype == np.int64 and triangles.shape[1:] == (3,)
    distinct = np.unique(units, axis=0)
    if len(distinct) < 3 or np.linalg.matrix_rank(distinct - distinct[0]) < 2:
        assert len(triangles) == 0
    else:
        _check_triangulation(units.astype(float), triangles)


_FILE_FORMATS = {"ply": (".ply", {}), "ply-ascii": (".ply", {"write_ascii": True}), "pcd": (".pcd", {}),
                 "pcd-ascii": (".pcd", {"write_ascii": True}), "pcd-compressed": (".pcd", {"compressed": True}),
                 "xyz": (".xyz", {}), "xyzn": (".xyzn", {}), "xyzrgb": (".xyzrgb", {}), "pts": (".pts", {})}
_TEXT_FORMATS = {"ply-ascii", "pcd-ascii", "xyz", "xyzn", "xyzrgb", "pts"}


@given(grid_clouds(), st.data())
@_settings(150)
def test_point_cloud_files_are_read_exactly_or_refused(cloud, data):
    """The CLI's reader (o3dvis.io.read_point_cloud) on files Open3D wrote, then cut at any byte,
    given a header that overstates the count, or replaced by random bytes: the points written,
    or a ValueError; a cut text file may lose digits of its last number, and one without a header
    (XYZ) its last lines, which nothing in it declares."""
    import tempfile
    from pathlib import Path

    from o3dvis.io import read_point_cloud

    COUNTS["point cloud files"] += 1
    units, exponent = cloud
    points = _world(units, exponent)
    fmt = data.draw(st.sampled_from(sorted(_FILE_FORMATS)))
    suffix, options = _FILE_FORMATS[fmt]
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd.normals = o3d.utility.Vector3dVector(np.tile([0.0, 0.0, 1.0], (len(points), 1)))
    pcd.colors = o3d.utility.Vector3dVector(np.full((len(points), 3), 0.5))
    mutation = data.draw(st.sampled_from(["none", "cut", "more points declared", "random bytes"]))
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / f"cloud{suffix}"
        assert o3d.io.write_point_cloud(str(path), pcd, **options)
        written = np.asarray(o3d.io.read_point_cloud(str(path)).points)
        content = path.read_bytes()
        if mutation == "cut":
            content = content[:data.draw(st.integers(0, len(content) - 1))]
        elif mutation == "more points declared":
            declared = {".ply": b"element vertex ", ".pcd": b"POINTS ", ".pts": b""}.get(suffix)
            if declared is None:  # no header: a line of two numbers
                content += b"1 2\n"
            else:
                head = content.index(declared) + len(declared)
                end = head + len(content[head:].split()[0])
                content = content[:head] + str(len(points) + data.draw(st.integers(1, 10**9))).encode() + content[end:]
        elif mutation == "random bytes":
            content = data.draw(st.binary(max_size=400))
        path.write_bytes(content)
        try:
            read = np.asarray(read_point_cloud(path).points)
        except ValueError:
            assert mutation != "none", "a file Open3D wrote was refused"
            return
    assert np.isfinite(read).all()
    if mutation == "random bytes":
        return
    assert mutation in ("none", "cut"), f"a file declaring more points than it holds was read ({fmt})"
    if mutation == "cut" and fmt.startswith("xyz"):  # no header: a cut at a line end leaves a shorter cloud
        written = written[:len(read)]
    assert read.shape == written.shape, f"{len(read)} points read of {len(written)} ({fmt}, {mutation})"
    last = len(read) - 1 if mutation == "cut" and fmt in _TEXT_FORMATS else len(read)
    np.testing.assert_array_equal(read[:last], written[:last])


_PLY_VALUES = {"char": "i1", "uchar": "u1", "short": "<i2", "ushort": "<u2", "int": "<i4", "uint": "<u4",
               "float": "<f4", "double": "<f8"}
_PCD_VALUES = [("F", 4), ("F", 8), ("F", 2), ("I", 1), ("I", 2), ("I", 4), ("I", 8), ("U", 1), ("U", 2), ("U", 4),
               ("U", 8)]
_HEADER_FORMATS = ("ply-binary", "ply-ascii", "pcd-binary", "pcd-ascii", "pcd-compressed")


@dataclass
class _Declared:
    """A PLY property or PCD field as a drawn header declares it: its type as the header spells it, the numpy
    type of its values, and a PCD field's COUNT or 0 for a PLY list (of one value, after its uchar length)."""

    name: str
    header: str
    dtype: str
    count: int = 1


def _declare(name: str, fmt: str, kind) -> _Declared:
    if fmt.startswith("ply"):
        return _Declared(name, kind, _PLY_VALUES[kind])
    letter, size = kind
    return _Declared(name, f"{letter} {size}", {"F": "<f", "I": "<i", "U": "<u"}[letter] + str(size))


def _cast(values: np.ndarray, dtype: str) -> np.ndarray:
    """``values`` as ``dtype`` holds them: integers rounded and clipped to its range."""
    if np.dtype(dtype).kind in "iu":
        info = np.iinfo(dtype)
        return np.clip(np.round(values), info.min, info.max).astype(dtype)
    with np.errstate(over="ignore"):
        return values.astype(dtype)


def _text(value) -> str:
    return repr(float(value)) if isinstance(value, np.floating) else str(int(value))


def _header_and_body(fmt: str, declared: list[_Declared], columns: list[np.ndarray], n: int) -> bytes:
    """A PLY or PCD file of ``n`` points declaring ``declared``, holding ``columns`` (one a declaration,
    already cast): a PLY list holds one value, a PCD field of COUNT c its value c times."""
    widths = [max(1, d.count) for d in declared]
    if fmt.startswith("ply"):
        props = "".join(f"property list uchar {d.header} {d.name}\n" if d.count == 0 else
                        f"property {d.header} {d.name}\n" for d in declared)
        kind = "ascii" if fmt == "ply-ascii" else "binary_little_endian"
        head = f"ply\nformat {kind} 1.0\nelement vertex {n}\n{props}end_header\n"
    else:
        kind = {"pcd-ascii": "ascii", "pcd-binary": "binary", "pcd-compressed": "binary_compressed"}[fmt]
        head = (f"VERSION 0.7\nFIELDS {' '.join(d.name for d in declared)}\n"
                f"SIZE {' '.join(d.header[2:] for d in declared)}\nTYPE {' '.join(d.header[0] for d in declared)}\n"
                f"COUNT {' '.join(str(w) for w in widths)}\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
                f"POINTS {n}\nDATA {kind}\n")
    if fmt.endswith("ascii"):
        rows = [" ".join(("1 " if d.count == 0 else "") + " ".join([_text(c[i])] * w)
                         for d, c, w in zip(declared, columns, widths)) for i in range(n)]
        return (head + "".join(row + "\n" for row in rows)).encode()
    if fmt == "pcd-compressed":
        return head.encode() + lzf_literal(b"".join(np.repeat(c[:, None], w, axis=1).tobytes()
                                                    for c, w in zip(columns, widths)))
    layout = []
    for i, (d, width) in enumerate(zip(declared, widths)):
        layout += [(f"length{i}", "u1")] if d.count == 0 else []
        layout.append((f"value{i}", d.dtype, (width,)))
    table = np.zeros(n, layout)
    for i, (d, column, width) in enumerate(zip(declared, columns, widths)):
        table[f"value{i}"] = np.repeat(column[:, None], width, axis=1)
        if d.count == 0:
            table[f"length{i}"] = 1
    return head.encode() + table.tobytes()


@st.composite
def drawn_headers(draw) -> tuple[str, bytes, dict[str, np.ndarray], bool]:
    """A PLY or PCD file written here from a drawn header: x, y, z, maybe normals and colours, then maybe some
    declarations dropped, one repeated, their order shuffled, their types drawn from all PLY types or PCD
    (TYPE, SIZE) pairs, some made lists (PLY) or of COUNT 2 (PCD). Returns the suffix, the content, the values
    of each name as written (its first declaration, cast to its type), and whether the header is one Open3D
    writes itself."""
    units, exponent = draw(grid_clouds(max_points=20))
    fmt = draw(st.sampled_from(_HEADER_FORMATS))
    ply = fmt.startswith("ply")
    normals = ("nx", "ny", "nz") if ply else ("normal_x", "normal_y", "normal_z")
    colours = ("red", "green", "blue") if ply else ("rgb",)
    values = dict(zip("xyz", _world(units, exponent).T))
    values.update(zip(normals, units.T % 3 - 1.0))
    values.update(zip(colours, units.T % 256 * (1.0 if ply else 65793.0)))
    names = ["x", "y", "z", *(normals if draw(st.booleans()) else ()), *(colours if draw(st.booleans()) else ())]
    colour = ("uchar" if ply else ("U", 4))
    declared = [_declare(name, fmt, colour if name in ("red", "green", "blue", "rgb") else (
        "double" if ply else ("F", 4))) for name in names]
    original = [dict(vars(d)) for d in declared]
    changes = draw(st.sampled_from(["retype", "shuffle", "drop", "repeat", "list or count", "all", "none"]))
    if changes in ("drop", "all"):
        keep = draw(st.lists(st.booleans(), min_size=len(declared), max_size=len(declared)))
        declared = [d for d, k in zip(declared, keep) if k] or declared[:1]
    if changes in ("repeat", "all"):
        declared.append(_Declared(**vars(draw(st.sampled_from(declared)))))
    if changes in ("shuffle", "all"):
        declared = draw(st.permutations(declared))
    for d in declared:
        if changes in ("retype", "all") and draw(st.booleans()):
            kind = draw(st.sampled_from(sorted(_PLY_VALUES) if ply else _PCD_VALUES))
            d.header, d.dtype = _declare(d.name, fmt, kind).header, _declare(d.name, fmt, kind).dtype
    if changes in ("list or count", "all"):
        draw(st.sampled_from(declared)).count = 0 if ply else 2  # a PLY list, a PCD COUNT 2
    clean = [vars(d) for d in declared] == original
    columns = [_cast(values[d.name], d.dtype) for d in declared]
    content = _header_and_body(fmt, declared, columns, len(units))
    written = {}
    for d, column in zip(declared, columns):
        written.setdefault(d.name, column.astype(np.float64))
    return (".ply" if ply else ".pcd"), content, written, clean


def _read_as_written(path, written: dict[str, np.ndarray], ply: bool) -> bool:
    """Reads ``path`` with the CLI's reader: False when it raised a ValueError; else asserts that the points,
    and the normals and (PLY) colours where read, are exactly the values written, each set declared whole."""
    from o3dvis.io import read_point_cloud

    try:
        pcd = read_point_cloud(path)
    except ValueError:
        return False
    sets = {"points": ("x", "y", "z"), "normals": ("nx", "ny", "nz") if ply else ("normal_x", "normal_y", "normal_z")}
    if ply:
        sets["colors"] = ("red", "green", "blue")
    for what, names in sets.items():
        read = np.asarray(getattr(pcd, what))
        if what == "points" or len(read):
            assert all(name in written for name in names), f"{what} read from a file without all of {names}"
            expected = np.stack([written[name] for name in names], axis=1) / (255.0 if what == "colors" else 1.0)
            np.testing.assert_array_equal(read, expected, err_msg=f"{what} read otherwise than written")
    return True


@given(drawn_headers())
@_settings(120)
def test_point_cloud_headers_are_read_as_declared_or_refused(drawn):
    """The CLI's reader on PLY/PCD files (ASCII, binary, compressed) with headers drawn around what Open3D
    writes: x, y, z and normals or colours dropped, repeated, reordered, of any type, lists or counts. A file
    is refused with a ValueError, or its points (and normals, colours) are the values written; a file Open3D
    could write itself is read."""
    import tempfile
    from pathlib import Path

    COUNTS["drawn headers"] += 1
    suffix, content, written, clean = drawn
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / f"cloud{suffix}"
        path.write_bytes(content)
        read = _read_as_written(path, written, suffix == ".ply")
    assert read or not clean, "a file with a header as Open3D writes it was refused"


def _corrupted_file(data, folder) -> tuple[object, np.ndarray]:
    """A PLY or PCD file Open3D wrote (ASCII, binary or compressed; with normals, colours or neither) with one
    byte of its header replaced by any byte; returns its path and the points Open3D wrote."""
    from pathlib import Path

    units, exponent = data.draw(grid_clouds(max_points=20))
    fmt = data.draw(st.sampled_from(sorted(name for name in _FILE_FORMATS if name.startswith(("ply", "pcd")))))
    suffix, options = _FILE_FORMATS[fmt]
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(_world(units, exponent)))
    if data.draw(st.booleans()):
        pcd.normals = o3d.utility.Vector3dVector(units % 3 - 1.0)
    if data.draw(st.booleans()):
        pcd.colors = o3d.utility.Vector3dVector(units % 256 / 255.0)
    path = Path(folder) / f"cloud{suffix}"
    assert o3d.io.write_point_cloud(str(path), pcd, **options)
    written = np.asarray(o3d.io.read_point_cloud(str(path)).points)
    content = path.read_bytes()
    end = (content.index(b"end_header\n") + 11 if suffix == ".ply"
           else content.index(b"\n", content.index(b"\nDATA ") + 1))
    at = data.draw(st.integers(0, end - 1))
    path.write_bytes(content[:at] + bytes([data.draw(st.integers(0, 255))]) + content[at + 1:])
    return path, written


def _read_as_before(path, written: np.ndarray) -> bool:
    """Reads a file of :func:`_corrupted_file` with the CLI's reader: False when it raised a ValueError; else
    asserts that the points are those written, or, where the byte turned the TYPE letter of x, y or z of a
    PCD into I or U, those written as they then read (a binary float's bits as an integer, text as the same
    number)."""
    from o3dvis.io import read_point_cloud

    try:
        read = np.asarray(read_point_cloud(path).points)
    except ValueError:
        return False
    if not np.array_equal(read, written):
        lines = [line.split() for line in path.read_bytes().split(b"\nDATA")[0].decode("latin-1").splitlines()]
        header = {words[0]: words[1:] for words in lines if words}
        types = dict(zip(header.get("FIELDS", []), header.get("TYPE", [])))
        bits = {"F": "<f4", "I": "<i4", "U": "<u4"}
        expected = np.stack([written[:, i].astype(np.float32).view(bits.get(types.get(name), "<f4"))
                             for i, name in enumerate("xyz")], axis=1).astype(np.float64)
        np.testing.assert_array_equal(read, expected, err_msg="points read otherwise than written")
    return True


@given(st.data())
@_settings(120)
def test_point_cloud_files_with_a_corrupted_header_byte_are_read_as_written_or_refused(data):
    """The CLI's reader on files Open3D wrote with any byte of the header replaced: refused with a ValueError
    or read as written; Open3D's reader never runs on a header it would crash on."""
    import tempfile

    COUNTS["corrupted header byte"] += 1
    with tempfile.TemporaryDirectory() as folder:
        _read_as_before(*_corrupted_file(data, folder))


@given(st.data())
@_settings(40)
def test_cli_reads_fuzzed_files_or_refuses_them_in_one_line(data):
    """``o3dvis visible`` on the files of the two properties above: exit code 2 and one line naming the file
    where the reader refuses it, else the points it writes are points of the file, read as written."""
    import io
    import tempfile
    from contextlib import redirect_stderr, redirect_stdout
    from pathlib import Path

    from o3dvis.cli import main

    COUNTS["CLI reading"] += 1
    with tempfile.TemporaryDirectory() as folder:
        if data.draw(st.booleans()):
            suffix, content, written, _ = data.draw(drawn_headers())
            path = Path(folder) / f"cloud{suffix}"
            path.write_bytes(content)
            check = lambda: _read_as_written(path, written, suffix == ".ply")  # noqa: E731
        else:
            path, before = _corrupted_file(data, folder)
            check = lambda: _read_as_before(path, before)  # noqa: E731
        out, err = Path(folder) / "visible.ply", io.StringIO()
        with redirect_stderr(err), redirect_stdout(io.StringIO()):
            code = main(["visible", str(path), "--direction", "0,0,1", "--no-normals", "-o", str(out)])
        read = check()
        lines = err.getvalue().strip().splitlines()
        if code == 2:
            assert not read and lines and lines[-1].startswith("o3dvis visible: error: ") and str(path) in lines[-1]
            assert "Traceback" not in err.getvalue()
        else:
            assert read and code in (0, 1), f"exit code {code}: {lines[-1:]}"
            if code == 0:
                points = {tuple(p) for p in np.asarray(o3d.io.read_point_cloud(str(path)).points)}
                assert {tuple(p) for p in np.asarray(o3d.io.read_point_cloud(str(out)).points)} <= points
