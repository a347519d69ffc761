"""The C kernels of o3dvis.nn.native against the torch ops they stand in for."""

import os

import numpy as np
import pytest
import torch

from o3dvis import clib
from o3dvis.nn import native
from o3dvis.nn.cues import ViewProjection, point_surfels

from .conftest import _CAMERA, _DIRECTION, _points, _views, needs_kernels

@pytest.mark.skipif(not native.has_gather_conv(), reason="no AVX-512 bfloat16 kernels here")
@pytest.mark.parametrize("blocks", [1, 2])
def test_the_unet_in_one_call_answers_as_its_layers_one_by_one(monkeypatch, blocks):
    """The down-samplings, encoder, up-samplings and decoder in one call of C (native.unet): the
    features of the layers' steps called one by one, to the bit; made anew when a weight changes."""
    import copy

    from o3dvis.nn import unet
    from o3dvis.nn.conv import products_in
    from o3dvis.nn.network import NetworkConfig, VisibilityNetwork

    torch.manual_seed(1)
    network = VisibilityNetwork(NetworkConfig(noise_cues=True, blocks=blocks)).eval()
    alone = copy.deepcopy(network)
    points = _points(3000)
    calls, run = [], native.unet
    monkeypatch.setattr(native, "unet", lambda *args, **kw: calls.append(1) or run(*args, **kw))
    with torch.no_grad(), products_in(torch.bfloat16):
        fused = network.encode(points)
        assert calls == [1]
        with monkeypatch.context() as m:
            m.setattr(unet._NativeBody, "of", classmethod(lambda cls, *steps: None))
            assert torch.equal(alone.encode(points), fused) and calls == [1]
            alone.unet.enc[1][0].a.conv.weight.mul_(1.5)
            network.unet.enc[1][0].a.conv.weight.mul_(1.5)
            changed = alone.encode(points)
        assert not torch.equal(changed, fused)
        assert torch.equal(network.encode(points), changed) and calls == [1, 1]


@pytest.mark.skipif(not native.has_gather_conv(), reason="no AVX-512 bfloat16 kernels here")
def test_unet_checks_that_its_table_holds_together():
    """native.unet on a table of two up-samplings: the answers of native.upsample; a table whose
    buffers, channels, kinds or shapes do not fit, or with a null address (a convolution without its
    lists), raises before anything runs; a row out of range raises from the layer that reads it."""
    g = torch.Generator().manual_seed(3)
    x = torch.randn(3, 4, generator=g)
    w1, s1 = torch.randn(4, 8 * 16, generator=g), torch.randn(16, generator=g)
    w2, s2 = torch.randn(16, 8 * 16, generator=g), torch.randn(16, generator=g)
    rows1 = torch.tensor([0, 5, 9, 17, 23])
    rows2 = torch.tensor([1, 2, 8, 30, 39])
    first = native.upsample(x, rows1, w1, s1, True)
    expected = native.upsample(first, rows2, w2, s2, True, addend=first)

    def table(**change) -> torch.Tensor:
        fields = {"kind": 1, "input": [0, 1], "residual": -1, "addend": [-1, 1], "channels": [4, 16], "outputs": 16,
                  "taps": 1, "relu": 1, "weight": [w1.data_ptr(), w2.data_ptr()],
                  "shift": [s1.data_ptr(), s2.data_ptr()], "rows": 5, "index": [rows1.data_ptr(), rows2.data_ptr()],
                  "offsets": 0, "entries": 0, "listed": 0}
        fields.update(change)
        return torch.tensor([[v[i] if isinstance(v, list) else v for v in fields.values()] for i in range(2)])

    assert table().shape == (2, native.UNET_FIELDS)
    assert torch.equal(native.unet(table(), x, torch.empty(5, 16)), expected)
    for change in [{"input": [0, 2]}, {"channels": [4, 8]}, {"addend": [-1, 0]}, {"kind": [1, 2]},
                   {"kind": [0, 1]}, {"rows": [4, 5]}]:
        with pytest.raises(ValueError, match="does not hold together"):
            native.unet(table(**change), x, torch.empty(5, 16))
    with pytest.raises(ValueError, match="layer 1 failed"):
        native.unet(table(index=[rows1.data_ptr(), (rows2 + 40).data_ptr()]), x, torch.empty(5, 16))
    with pytest.raises(ValueError, match="out must be"):
        native.unet(table(), x, torch.empty(4, 16))


@pytest.mark.skipif(os.environ.get("O3DVIS_NATIVE", "1") != "1", reason="a variant or none asked for")
def test_every_variant_this_cpu_runs_is_built():
    """The package's build made them all (CI builds where there is a C compiler), and the widest
    is the one loaded."""
    for variant in clib.runnable_variants():
        library = clib.load("o3dvis.nn._kernels", native._library.SIGNATURES, variant)
        assert getattr(library, "variant", None) == variant, (
            f"the {variant} kernels are not built: in a source checkout run `pip install -e .` or "
            "`python setup.py build_ext --inplace`")
    assert native.variant() == clib.runnable_variants()[-1]


@needs_kernels
@pytest.mark.parametrize("view", [{"camera": _CAMERA}, {"direction": _DIRECTION}])
@pytest.mark.parametrize("footprints", [False, True])
def test_projection_equals_the_torch_one(view, footprints, variant):
    """The same buffers and cues (with ``footprints``, the splatted buffers too, which the torch
    ops build after the kernel's projection, along the same pixel rays)."""
    points = _points()
    if footprints:
        view = {**view, "surfels": point_surfels(points)}
    fast, slow = _views(points, **view)
    assert len(fast.sides) == (7 if footprints else 4)
    torch.testing.assert_close(fast.depth, slow.depth, atol=1e-6, rtol=1e-6)
    torch.testing.assert_close(fast.dirs, slow.dirs, atol=1e-6, rtol=0)
    assert fast.corners.dtype == torch.int32 and fast.inv_footprint is None  # the scales made on demand
    patches, pixels = fast._tables()
    torch.testing.assert_close(fast.inv_footprint, slow.inv_footprint, atol=0, rtol=1e-5)
    assert patches.shape == slow.patches.shape
    # a point on a pixel border may fall on either side by float32 rounding (the mean view
    # direction is summed in double, atan2 is a polynomial): a few in ten thousand at most
    same = (pixels == slow.pixels).all(dim=1)
    assert same.float().mean() > 0.999
    with torch.inference_mode():  # depths an ulp apart, times up to ~200 / pixel footprint (the splats'
        # planes along rays of frames a float32 rounding apart: up to 1e-3)
        torch.testing.assert_close(fast.cues()[same], slow.cues()[same], atol=1e-3 if footprints else 1e-4, rtol=0)
        assert (fast.cues() == -5.0).any()  # empty neighbours are marked


@needs_kernels
def test_surfels_equal_the_torch_ones():
    """One pass of C for the points' spacings and planes: the same cells, spacings and normals (up
    to their sign; sums in double where torch sums each cell's products about its first point)
    wherever the smallest eigenvalue of the cell's covariance is single: elsewhere (cells of one or
    two points, or of points on a line) any normal of the line is one."""
    from o3dvis.nn import cues
    from o3dvis.nn.cues import point_surfels

    least_axis = cues._least_axis

    def single(a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:  # NaN where the eigenvalue is not single
        axis, smallest = least_axis(a)
        values = torch.linalg.eigvalsh(a)
        return torch.where((values[:, 1] - values[:, 0] > 1e-6 * values[:, 2])[:, None], axis, torch.nan), smallest

    points = torch.cat([_points(), _points(3000) * 0.3 + 0.5])
    with torch.inference_mode():
        fast = point_surfels(points)
    with torch.no_grad(), pytest.MonkeyPatch.context() as mp:
        mp.setattr(native, "usable", lambda *tensors: False)
        mp.setattr(cues, "_least_axis", single)
        slow = point_surfels(points)
    torch.testing.assert_close(fast[:, 0], slow[:, 0])
    agree = (fast[:, 1:] * slow[:, 1:]).sum(dim=1).abs()
    defined = ~agree.isnan()
    assert defined.float().mean() > 0.95 and agree[defined].min() > 1 - 1e-6
    with pytest.raises(ValueError, match="levels must lie"):
        native.surfels(points, torch.zeros(len(points), dtype=torch.long), 7, 8, 8)
    with torch.inference_mode():
        view = ViewProjection(points, _CAMERA)
        args = (points, fast, view.depth, torch.zeros(len(points), dtype=torch.int8), view.sides, view.corners,
                torch.eye(3), 1.0, _CAMERA, 3.0, view.buffers[:-(view.sides[-1] + 2) ** 2].clone())
        with pytest.raises(ValueError, match="level must be"):
            native.plane_splat(*args[:3], args[3].long(), *args[4:])
        with pytest.raises(ValueError, match="out must be the contiguous float32 buffers"):
            native.plane_splat(*args[:-1], view.buffers.clone())  # the coarsest scale too
        native.plane_splat(*args)  # no point assigned a splat scale: the buffers stay as they were
        torch.testing.assert_close(args[-1], view.buffers[:len(args[-1])], equal_nan=True)


def _neighbourhoods(scale: float) -> tuple[np.ndarray, np.ndarray]:
    """(M x 16, 3) points in rows of 16 of every shape a patch takes (blobs, noisy planes, strips,
    near-lines, cigars, lines), rotated at random and scaled, and their (M, 3, 3) scatters."""
    rng = np.random.default_rng(3)
    extents = np.repeat([[1, 1, 1], [1, 1, 1e-3], [1, 0.3, 1e-6], [1, 1e-3, 1e-9], [1, 0.999, 0.998], [1, 1e-4, 1e-4],
                         [1, 0, 0]], 300, axis=0)
    rotation = np.linalg.qr(rng.normal(size=(len(extents), 3, 3)))[0]
    points = (rng.normal(size=(len(extents), 16, 3)) * extents[:, None] @ rotation) * scale
    centred = points - points.mean(axis=1, keepdims=True)
    return points, centred.transpose(0, 2, 1) @ centred


@needs_kernels
@pytest.mark.parametrize("scale", [1e-100, 1.0, 1e100])
def test_the_eigen_solver_of_the_kernels_answers_as_lapack(scale):
    """The one symmetric 3x3 solver of the kernels (linalg.c), through the plane fits and the noise
    cues' runs: on patches of every shape and scale, each eigenvector of a single smallest
    eigenvalue and each eigenvalue within rounding of numpy's eigh (LAPACK), however close the two
    smaller eigenvalues lie; a line (a middle eigenvalue under 1e-12 times the largest) has no plane."""
    points, scatters = _neighbourhoods(scale)
    values, vectors = np.linalg.eigh(scatters)
    rows = torch.arange(points.shape[0] * 16).view(-1, 16)
    normals, planar = native.fit_planes(torch.from_numpy(points.reshape(-1, 3)).contiguous(), rows, None)
    separated = values[:, 1] - values[:, 0] > 1e-8 * values[:, 2]
    cos = np.abs(np.einsum("ij,ij->i", normals.numpy(), vectors[:, :, 0]))
    assert separated.mean() > 0.7 and cos[separated].min() > 1 - 1e-12
    assert torch.equal(planar, torch.from_numpy(values[:, 1] > 1e-12 * values[:, 2]))
    assert not planar[-300:].any() and planar[:-300].all()
    if scale == 1.0:  # the runs' flatness, sqrt(smallest / middle): each eigenvalue to 1e-13 of the largest
        single = torch.from_numpy(points.reshape(-1, 3)).float()
        centred = single.double().view(-1, 16, 3) - single.double().view(-1, 16, 3).mean(dim=1, keepdim=True)
        exact = np.linalg.eigvalsh((centred.transpose(1, 2) @ centred).numpy())
        flatness = native.run_flatness(single, torch.arange(0, len(single), 16), 16).numpy()
        low, middle = np.maximum(exact[:, 0], 0), np.maximum(exact[:, 1], np.finfo(float).tiny)
        assert np.all(np.abs(flatness ** 2 * middle - low) <= 1e-13 * exact[:, 2] + 1e-13 * low)


@needs_kernels
def test_child_neighbours_check_their_inputs():
    from o3dvis.nn.octree import Octree, _PARENT_OCTANT, _PARENT_OFFSET

    tree = Octree(torch.rand(500, 3, generator=torch.Generator().manual_seed(1)) * 2 - 1, depth=4, full_depth=1)
    args = [tree.keys[2], tree.parent[2], tree.neighbours(1), tree.children[1], _PARENT_OFFSET, _PARENT_OCTANT]
    assert torch.equal(native.child_neighbours(*args), tree.neighbours(2))
    with pytest.raises(ValueError, match="above must be a contiguous"):
        native.child_neighbours(*args[:2], args[2].int(), *args[3:])
    with pytest.raises(ValueError, match=r"parent indices must lie in \[0, 8\)"):
        native.child_neighbours(args[0], args[1] + 8, *args[2:])
    with pytest.raises(ValueError, match=r"parent_offset in \[0, 27\)"):
        native.child_neighbours(*args[:4], args[4] + 27, args[5])


@needs_kernels
@pytest.mark.parametrize("depth, full_depth, n", [(7, 2, 5000), (4, 1, 300), (3, 2, 40), (6, 3, 1), (5, 2, 3)])
def test_the_octree_of_c_equals_the_torch_one(depth, full_depth, n, variant):
    """One cloud's octree in two passes of C: the keys, parents, children, child and octant rows and
    each point's leaf of the torch ops, points along the Morton curve or (torch ops) in any order;
    keys out of order or range are refused, for the torch ops to take."""
    from o3dvis.nn.octree import Octree, cell_keys, morton_order

    g = torch.Generator().manual_seed(depth * 100 + n)
    points = torch.cat([_points(n, seed=depth)[: n // 2], torch.rand(n - n // 2, 3, generator=g) * 2 - 1])
    points = points[morton_order(points)] if n else points
    fast = Octree(points, depth=depth, full_depth=full_depth)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(native, "available", lambda: False)
        slow = Octree(points, depth=depth, full_depth=full_depth)
    assert torch.equal(fast.point_leaf, slow.point_leaf)
    for level in range(depth + 1):
        assert torch.equal(fast.keys[level], slow.keys[level])
        assert torch.equal(fast.parent[level], slow.parent[level])
        assert torch.equal(fast.octant_rows(level), slow.octant_rows(level))
    for level in range(depth):
        assert torch.equal(fast.children[level], slow.children[level])
        assert torch.equal(fast.child_rows(level), slow.child_rows(level))
    for level in range(full_depth, depth + 1):
        assert torch.equal(fast.neighbours(level), slow.neighbours(level))
    if n > 2:
        keys = cell_keys(points, depth)
        assert native.octree_levels(keys.flip(0), depth, full_depth) is None
        assert native.octree_levels(keys + (8 ** depth - int(keys.min())), depth, full_depth) is None
        shuffled = Octree(points.flip(0), depth=depth, full_depth=full_depth)  # the torch ops sort
        assert torch.equal(shuffled.keys[depth], slow.keys[depth])


def test_morton_keys_equal_the_torch_ones():
    """One pass of C for the octree's keys: the same cells (outside the cube clamped to it, the
    float32 rounding of the cell's coordinate the same) and the same interleaving."""
    from o3dvis.nn.octree import cell_keys, grid_cells, morton_encode

    points = torch.rand(50_000, 3, generator=torch.Generator().manual_seed(2)) * 2.2 - 1.1
    points[:4] = torch.tensor([[-1.0, 1.0, 0.0], [0.99999994, -0.99999994, 1e-8], [1.5, -1.5, 0.5],
                               [-1.0000001, 0.5, 0.25]])
    for depth in (1, 7, 10, 11, 12, 16, 21):
        expected = morton_encode(grid_cells(points, depth), depth)
        assert torch.equal(native.morton_keys(points, depth), expected), depth
        assert torch.equal(cell_keys(points, depth), expected), depth
    with pytest.raises(ValueError, match=r"depth must lie in \[1, 21\]"):
        native.morton_keys(points, 22)
    with pytest.raises(ValueError, match="points must be"):
        native.morton_keys(points.double(), 7)


@needs_kernels
@pytest.mark.parametrize("n", [1, 7, 8, 9, 50_001])
def test_the_unit_frame_in_c_equals_the_torch_ops(n):
    """Bounds, normalised float32 points and their Morton keys by two passes of C: equal to
    bounding_box, normalize_points, .float() and cell_keys by torch ops, point for point; the
    scatter matrix and the sums to rounding; the bounds NaN where an axis has one, as torch's."""
    from o3dvis.nn.frame import CloudFrame
    from o3dvis.nn.octree import MORTON_DEPTH, cell_keys, cube_frame, normalize_points

    g = torch.Generator().manual_seed(n)
    points = (torch.randn(n, 3, generator=g, dtype=torch.float64) * torch.tensor([3.0, 0.5, 2e3]) + 7).contiguous()
    if n > 8:
        points[1] = points[0]  # the box's corners and a point on each face
        points[2] = points.min(dim=0).values
        points[3] = points.max(dim=0).values
    lo, hi, total = native.bounds(points)
    assert torch.equal(lo, points.min(dim=0).values) and torch.equal(hi, points.max(dim=0).values)
    torch.testing.assert_close(total, points.sum(dim=0), rtol=1e-12, atol=1e-9)
    expected, center, scale = normalize_points(points)
    assert all(torch.equal(a, b) for a, b in zip((center, scale), cube_frame(lo, hi)))
    mean = expected.mean(dim=0)
    normalised, keys, scatter = native.normalize(points, center, float(scale), mean)
    assert torch.equal(normalised, expected.float())
    assert torch.equal(keys, cell_keys(expected.float(), MORTON_DEPTH))
    torch.testing.assert_close(scatter, (expected - mean).T @ (expected - mean), rtol=1e-9, atol=1e-12)
    unit, unit_keys, frame = CloudFrame.of(points)
    assert torch.equal(unit, expected.float() if n > 1 else torch.zeros(1, 3))  # one point: at the origin
    assert torch.equal(unit_keys, keys) if n > 1 else unit_keys is None
    assert (frame.hull is None) == (n > 3)  # up to 3 points: flat
    nan = points.clone()
    nan[n // 2, 1] = float("nan")
    for got, want in zip(native.bounds(nan)[:2], (nan.min(dim=0).values, nan.max(dim=0).values)):
        assert torch.equal(got.isnan(), want.isnan()) and torch.equal(got[[0, 2]], want[[0, 2]])
    with pytest.raises(ValueError, match="points must be"):
        native.bounds(points.float())


@needs_kernels
def test_the_unit_frame_of_flat_and_degenerate_clouds_is_the_torch_one():
    """A plane, a line and one point repeated: the flat hull (its float64 points made only then)
    and the normalised points as the torch path gives them."""
    from o3dvis.nn.frame import CloudFrame

    g = torch.Generator().manual_seed(5)
    plane = torch.randn(3000, 3, generator=g, dtype=torch.float64)
    plane[:, 2] = 0.25
    line = torch.randn(500, 1, generator=g, dtype=torch.float64) * torch.tensor([[1.0, 2.0, -1.0]])
    for points in (plane, line, torch.full((40, 3), 3.0, dtype=torch.float64)):
        got = CloudFrame.of(points)
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(native, "available", lambda: False)
            want = CloudFrame.of(points)
        assert torch.equal(got[0], want[0]) and got[1] is not None or len(points) == 40
        assert torch.equal(got[2].center, want[2].center) and torch.equal(got[2].scale, want[2].scale)
        assert got[2].hull is not None and want[2].hull is not None
        assert all(torch.equal(a, b) for a, b in zip(got[2].hull, want[2].hull))


@needs_kernels
@pytest.mark.parametrize("keys", ["ties", "wide", "one byte high", "cloud", "one", "equal", "none"])
def test_sort_keys_equals_a_stable_torch_sort(keys):
    """The radix sort of the Morton keys: the same sorted keys and the same permutation as a stable
    sort, ties (points in one cell) in their order, whichever bytes the keys differ in, on one
    thread or its buckets shared among several."""
    from o3dvis.nn.octree import MORTON_DEPTH, cell_keys, morton_sort

    g = torch.Generator().manual_seed(3)
    points = _points(30_000)
    keys = {"ties": lambda: torch.randint(0, 700, (20_000,), generator=g),
            "wide": lambda: torch.randint(0, 2**63 - 1, (20_000,), generator=g),
            "one byte high": lambda: torch.randint(0, 200, (5_000,), generator=g) << 48,
            "cloud": lambda: cell_keys(points, MORTON_DEPTH),
            "one": lambda: torch.tensor([2**63 - 1]),
            "equal": lambda: torch.full((300,), 12345),
            "none": lambda: torch.empty(0, dtype=torch.long)}[keys]()
    expected = torch.sort(keys, stable=True)
    for threads in (1, 3):
        got = native.sort_keys(keys, threads=threads)
        assert torch.equal(got[0], expected.values) and torch.equal(got[1], expected.indices)
        assert torch.equal(got[2][got[1]], torch.arange(len(keys)))
    assert torch.equal(morton_sort(points)[1], torch.sort(cell_keys(points, MORTON_DEPTH), stable=True).indices)
    with pytest.raises(ValueError, match="non-negative"):
        native.sort_keys(torch.tensor([4, -1, 2]))
    with pytest.raises(ValueError, match="keys must be"):
        native.sort_keys(keys.int())
    with pytest.raises(ValueError, match="threads must be"):
        native.sort_keys(keys, threads=0)


@needs_kernels
@pytest.mark.parametrize("normals", [False, True])
def test_leaf_means_equal_the_torch_ones(normals, monkeypatch):
    """The U-Net's input per leaf in one pass of C: bit for bit what index_add_ sums and divides,
    for two clouds in one octree, their points in no particular order."""
    from o3dvis.nn.network import VisibilityNetwork

    network = VisibilityNetwork()
    points = torch.cat([_points(3000), _points(2000, seed=1) * 0.5])[torch.randperm(5000)]
    batch = torch.cat([torch.zeros(3000, dtype=torch.long), torch.ones(2000, dtype=torch.long)])
    unit = torch.nn.functional.normalize(points + 0.1, dim=1) if normals else None
    noise = torch.rand(2, 2)
    with torch.no_grad():
        octree = network.octree(points, batch, 2)
        fast = network._signal(points, batch, octree, unit, noise)
        monkeypatch.setattr(native, "usable", lambda *tensors: False)
        slow = network._signal(points, batch, octree, unit, noise)
    assert torch.equal(fast, slow)
    leaf = octree.point_leaf
    with pytest.raises(ValueError, match="leaves must lie"):
        native.leaf_means(points, unit, leaf, 7, int(leaf.max()))
    with pytest.raises(ValueError, match="every leaf needs a point"):
        native.leaf_means(points, unit, leaf, 7, int(leaf.max()) + 2)
    with pytest.raises(ValueError, match="depth must lie"):
        native.leaf_means(points, unit, leaf, 0, int(leaf.max()) + 1)


@needs_kernels
@pytest.mark.parametrize("shape", [(16, 16, 27, 700), (32, 48, 27, 77), (8, 16, 8, 130), (96, 96, 27, 64),
                                   (48, 32, 27, 301), (64, 112, 27, 17), (6, 16, 27, 50), (40, 32, 8, 90),
                                   (32, 64, 27, 9), (64, 32, 8, 3)])
def test_gather_conv_equals_the_torch_ops(shape, variant):
    """A convolution over gathered rows, in each variant that has one (AMX tiles, or AVX-512
    bfloat16 dot products), against the torch ops of ConvBnRelu in inference: bfloat16 rows
    gathered (the input's length gathers zeros), one product rounded to bfloat16, the shift, the
    residual and the ReLU. The sums may run in another order than oneDNN's: a bfloat16 step apart
    at most, and rarely."""
    if not native.has_gather_conv():
        assert variant in ("base", "avx2")
        pytest.skip(f"the {variant} kernels have no gathered convolution")
    channels, outputs, taps, n = shape
    g = torch.Generator().manual_seed(4)
    x = torch.randn(3 * n, channels, generator=g)
    weight = torch.randn(taps * channels, outputs, generator=g) / taps
    shift, residual = torch.randn(outputs, generator=g), torch.randn(n, outputs, generator=g)
    index = torch.randint(0, len(x) + 1, (n, taps), generator=g)
    padded = torch.cat([x, x.new_zeros(1, channels)]).to(torch.bfloat16)
    product = (padded[index].flatten(1) @ weight.to(torch.bfloat16)).float() + shift
    packed = native.pack_conv(weight, taps)
    for got, expected in [(native.gather_conv(x, index, packed, taps, outputs, shift), product),
                          (native.gather_conv(x, index, packed, taps, outputs, shift, residual, relu=True),
                           torch.relu(residual + product))]:
        assert (got == expected).float().mean() > 0.999
        torch.testing.assert_close(got, expected, atol=0.01 * float(expected.abs().max()), rtol=0)
    with pytest.raises(ValueError, match="index must lie"):
        native.gather_conv(x, index.clamp(max=len(x)) + 1, packed, taps, outputs, shift)
    with pytest.raises(ValueError, match="packed must be"):
        native.gather_conv(x, index, packed[1:], taps, outputs, shift)


@needs_kernels
@pytest.mark.parametrize("missing", [0.0, 0.5, 0.9, 1.0])
def test_gather_conv_skips_the_missing_neighbours_exactly(missing, variant):
    """With most neighbours missing (a surface's nodes have about half of their 27), the products
    with the row of zeros are skipped: the sums of every product, value for value; the lists made
    once serve several convolutions over the same index; lists that are not the kernel's are refused."""
    if not native.has_gather_conv():
        pytest.skip(f"the {variant} kernels have no gathered convolution")
    g = torch.Generator().manual_seed(5)
    n, channels, outputs, taps = 300, 32, 48, 27
    x = torch.randn(n, channels, generator=g)
    index = torch.randint(0, n, (n, taps), generator=g)
    index[torch.rand(n, taps, generator=g) < missing] = n
    weight, shift = torch.randn(taps * channels, outputs, generator=g) / taps, torch.randn(outputs, generator=g)
    packed = native.pack_conv(weight, taps)
    padded = torch.cat([x, x.new_zeros(1, channels)]).to(torch.bfloat16)
    expected = torch.relu((padded[index].flatten(1) @ weight.to(torch.bfloat16)).float() + shift)
    entries = native.conv_entries(index, n)
    got = native.gather_conv(x, index, packed, taps, outputs, shift, relu=True, entries=entries)
    assert torch.equal(got, native.gather_conv(x, index, packed, taps, outputs, shift, relu=True))
    assert (got == expected).float().mean() > 0.999
    torch.testing.assert_close(got, expected, atol=0.01 * float(expected.abs().max()), rtol=0)
    other = torch.randn(n, channels, generator=g)
    assert torch.equal(native.gather_conv(other, index, packed, taps, outputs, shift, entries=entries),
                       native.gather_conv(other, index, packed, taps, outputs, shift))
    lists = -(-n // 64) * taps
    if len(entries) > lists + 1:
        for bad in (entries[lists + 1] + (n + 1 << 8), entries[lists + 1] | 255, -1):
            broken = entries.clone()
            broken[lists + 1] = bad
            with pytest.raises(ValueError, match="entries must be"):
                native.gather_conv(x, index, packed, taps, outputs, shift, entries=broken)
        with pytest.raises(ValueError, match="entries must be"):  # cut short
            native.gather_conv(x, index, packed, taps, outputs, shift, entries=entries[:-8])
    broken = entries.clone()
    broken[1] = broken[0] + 3  # a list that is no whole number of groups of 8
    with pytest.raises(ValueError, match="entries must be"):
        native.gather_conv(x, index, packed, taps, outputs, shift, entries=broken)


@pytest.mark.parametrize("use_normals", [False, True])
def test_the_unet_of_a_network_with_normals_is_one_call_of_the_kernels_too(monkeypatch, use_normals):
    """The normals model's U-Net takes 11 channels: the kernels, which read them in pairs, take a 12th of
    zeros (in the input and the weights) rather than leaving every layer to torch's bfloat16 products,
    whose memory grows with each new count of rows. Only the plan of the call is checked, on any CPU."""
    from o3dvis.nn.conv import products_in
    from o3dvis.nn.network import NetworkConfig, VisibilityNetwork

    monkeypatch.setattr(native, "available", lambda: True)
    monkeypatch.setattr(native, "has_gather_conv", lambda: True)
    network = VisibilityNetwork(NetworkConfig(noise_cues=True, use_normals=use_normals)).eval()
    channels = network.unet.skip_leaf.in_features
    assert channels == (11 if use_normals else 8)
    with torch.no_grad(), products_in(torch.bfloat16):
        body = network.unet._steps(torch.zeros(10, channels))[-1]
    assert body is not None, "the U-Net's layers left to torch ops"
    assert int(body.table[0, 4]) == body.weights[0].channels == (12 if use_normals else 8)


@pytest.mark.skipif(not native.has_gather_conv(), reason="no AVX-512 bfloat16 kernels here")
@pytest.mark.parametrize("use_normals", [False, True])
def test_the_unet_of_gathered_convolutions_answers_as_the_torch_ops(monkeypatch, use_normals):
    """The encoding with every gathered convolution (3x3x3 and down-sampling) in one pass of C:
    the features of the torch ops, but for sums that oneDNN orders otherwise (its order is the
    tiles' on a CPU with AMX, not on every CPU with AVX-512 bfloat16 alone: there a product a
    bfloat16 step apart in one layer moves every feature after it by a few such steps). With
    normals, the input's odd channel count is padded with zeros for the kernels."""
    from o3dvis.nn.conv import products_in
    from o3dvis.nn.network import NetworkConfig, VisibilityNetwork

    torch.manual_seed(0)
    network = VisibilityNetwork(NetworkConfig(noise_cues=True, use_normals=use_normals)).eval()
    points = _points(5000)
    normals = torch.nn.functional.normalize(torch.randn_like(points), dim=1) if use_normals else None
    calls, unet = [], native.unet
    monkeypatch.setattr(native, "unet", lambda table, *args, **kw: calls.append(table[:, 0].tolist()) or unet(
        table, *args, **kw))
    with torch.no_grad(), products_in(torch.bfloat16):
        fused = network.encode(points, normals=normals)
        assert [kinds.count(0) for kinds in calls] == [23]  # in one call: 5 down-samplings, 9 residual blocks of 2
        monkeypatch.setattr(native, "has_gather_conv", lambda: False)
        plain = network.encode(points, normals=normals)
    assert float((fused - plain).abs().mean()) < 4e-3 * float(plain.abs().mean())
    torch.testing.assert_close(fused, plain, atol=1e-2 * float(plain.abs().max()), rtol=0)


@needs_kernels
@pytest.mark.parametrize("shape", [(16, 32, 700), (32, 16, 301), (96, 64, 5), (48, 48, 130), (8, 24, 77)])
def test_upsample_equals_the_torch_ops(shape, variant):
    """An up-sampling for the nodes that exist only, against OctreeUpsample's product for all eight
    octants, gather, shift and ReLU: the same float32 sums, to their rounding (the kernel sums along
    the inputs in order, fused multiply-adds but in the baseline variant; the BLAS torch calls
    orders them as suits the CPU it finds, the same order on some and not on others)."""
    channels, outputs, parents = shape
    g = torch.Generator().manual_seed(6)
    x = torch.randn(parents, channels, generator=g).relu_()
    weight, shift = torch.randn(channels, 8 * outputs, generator=g) / channels, torch.randn(outputs, generator=g)
    rows = torch.sort(torch.randperm(8 * parents, generator=g)[: 3 * parents]).values
    product = (x @ weight).view(8 * parents, outputs).index_select(0, rows) + shift
    for relu, expected in [(False, product), (True, torch.relu(product))]:
        torch.testing.assert_close(native.upsample(x, rows, weight, shift, relu), expected, rtol=1e-5, atol=1e-5)
    # a residual before the ReLU and an addend after it: torch's adds, to the bit
    plain = native.upsample(x, rows, weight, shift, False)
    residual, addend = torch.randn(2, len(rows), outputs, generator=g)
    for relu, expected in [(False, plain + residual + addend), (True, torch.relu(plain + residual) + addend)]:
        assert torch.equal(native.upsample(x, rows, weight, shift, relu, residual=residual, addend=addend), expected)
    assert torch.equal(native.upsample(x, rows, weight, shift, True, addend=addend), torch.relu(plain) + addend)
    with pytest.raises(ValueError, match="rows must lie"):
        native.upsample(x, rows + 8 * parents - int(rows.min()), weight, shift, True)
    with pytest.raises(ValueError, match="weight must be"):
        native.upsample(x, rows, weight[:, 1:], shift, True)
    with pytest.raises(ValueError, match="addend must be"):
        native.upsample(x, rows, weight, shift, True, addend=addend[1:])


@needs_kernels
def test_the_unet_with_native_upsamplings_answers_as_the_torch_ops(monkeypatch):
    """The encoding with its up-samplings in one pass of C (only the octants that exist): the
    features of the products over all octants, value for value."""
    from o3dvis.nn import conv
    from o3dvis.nn.network import NetworkConfig, VisibilityNetwork

    torch.manual_seed(0)
    network = VisibilityNetwork(NetworkConfig(noise_cues=True)).eval()
    points = _points(5000)
    calls, upsample = [], native.upsample
    monkeypatch.setattr(native, "upsample", lambda *args, **kw: calls.append(1) or upsample(*args, **kw))
    with torch.no_grad(), conv.products_in(torch.float32):
        fused = network.encode(points)
        assert len(calls) == 5  # four decoder stages and the leaves
        native_step = conv.ConvBnRelu._native_step
        monkeypatch.setattr(conv.ConvBnRelu, "_native_step", lambda layer, *args: None if isinstance(
            layer.conv, conv.OctreeUpsample) else native_step(layer, *args))
        plain = network.encode(points)
    assert torch.equal(fused, plain)
