"""Noise cues (``o3dvis.nn.noise``): they grow with noise, ignore order and block size, match the
torch eigenvalues and quantiles, and are per cloud in a batch."""

import pytest
import torch

from o3dvis.nn import (NetworkConfig, VisibilityNetwork, morton_order, native, noise_cues, normalize_points,
                       octree as octree_module)


def _noisy_sphere(n, noise, seed=0):
    g = torch.Generator().manual_seed(seed)
    p = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=1)
    return normalize_points(p + noise * torch.randn(n, 3, generator=g, dtype=torch.float64))[0]


def test_noise_cues_grow_with_noise_and_ignore_order():
    cues = torch.stack([noise_cues(_noisy_sphere(40_000, s)) for s in (0.0, 0.003, 0.01)])
    assert (cues[1:] > cues[:-1]).all(), cues
    assert cues[0].max() < 0.05  # a smooth surface is thin and flat at this density
    p = _noisy_sphere(40_000, 0.003)
    torch.testing.assert_close(noise_cues(p[torch.randperm(len(p))]), noise_cues(p), atol=1e-6, rtol=0)
    # points already in Morton order (as a VisibilityField stores them) need no sort: the same cues
    torch.testing.assert_close(noise_cues(p[morton_order(p)], ordered=True), noise_cues(p), atol=1e-6, rtol=0)
    shuffled = noise_cues(p[torch.randperm(len(p))], ordered=True)  # the flag is believed: runs of far points
    assert shuffled[1] > 2 * noise_cues(p)[1]


def test_noise_cues_do_not_depend_on_the_block_size(monkeypatch):
    """The torch ops sum the cell moments over blocks of rows: blocks of 1 000 give the one-block sums."""
    import o3dvis.nn.noise as noise

    monkeypatch.setattr(noise.native, "available", lambda: False)
    p = _noisy_sphere(40_000, 0.003)
    whole = noise_cues(p)
    monkeypatch.setattr(noise, "_BLOCK", 1_000)
    torch.testing.assert_close(noise_cues(p), whole, atol=1e-6, rtol=0)


def _cell_thickness_by_torch(p: torch.Tensor) -> torch.Tensor:
    """Each full cell's thickness term as the C kernel computes it (offsets and their products in
    float32, sums in float64), by torch ops, with eigvalsh: in the cells' order."""
    import o3dvis.nn.noise as noise

    res = 1 << noise._LEVEL
    c = octree_module.grid_cells(p, noise._LEVEL)
    cell = (c[:, 0] * res + c[:, 1]) * res + c[:, 2]
    q = p - ((c + 0.5) * (2 / res) - 1)
    products = torch.stack([q[:, i] * q[:, j] for i, j in noise._PAIRS] + list(q.unbind(1)), dim=1).double()
    m = torch.zeros(res ** 3, 9, dtype=torch.float64).index_add_(0, cell, products)
    count = torch.bincount(cell, minlength=res ** 3)
    full = torch.nonzero(count >= noise._MIN_COUNT).squeeze(1)
    m, n = m[full].T, count[full].double()
    cov = m.new_zeros(len(full), 3, 3)
    for k, (i, j) in enumerate(noise._PAIRS):
        cov[:, i, j] = m[k] / n - (m[6 + i] / n) * (m[6 + j] / n)
    return noise._eigenvalues(cov)[:, 0].sqrt() * n.sqrt() * (res / 2)


@pytest.mark.skipif(not native.available(), reason="the C kernels are not built")
def test_native_patch_terms_match_the_torch_eigenvalues(monkeypatch):
    """The cells' thickness and the runs' flatness by C (sums along the Morton curve, eigenvalues in
    closed form) against eigvalsh on the same sums by torch ops: equal to a few ulps of the largest
    eigenvalue, on noisy patches and on degenerate ones (a plane, a line, one point, a cube's
    corners of equal eigenvalues, a sheet 1e-6 thick); the cues from unordered points are those
    of the ordered ones, and close to the torch path's (sums in float32)."""
    import o3dvis.nn.noise as noise

    p = _noisy_sphere(30_000, 0.003).float()
    p[:5] = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [-1.0, 1.0, 0.0], [0.5, -0.5, 1.0]])
    ordered = p[morton_order(p)].contiguous()
    got = native.cell_thickness(ordered, noise._LEVEL, noise._MIN_COUNT)
    expected = _cell_thickness_by_torch(p)
    assert len(got) == len(expected) > 100
    torch.testing.assert_close(got.sort().values, expected.sort().values, rtol=1e-6, atol=1e-9)
    g = torch.Generator().manual_seed(1)
    flat = torch.rand(16, 3, generator=g)
    patches = [ordered[:16], flat * torch.tensor([1.0, 1.0, 0.0]), flat * torch.tensor([1.0, 0.0, 0.0]),
               torch.zeros(16, 3), torch.tensor([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0)
                                                 for z in (-1.0, 1.0)] * 2),
               flat * torch.tensor([1.0, 1.0, 1e-6])]
    runs = torch.cat(patches).contiguous()
    got = native.run_flatness(runs, torch.arange(0, len(runs), 16), 16)
    x = runs.double().view(-1, 16, 3)
    x = x - x.mean(dim=1, keepdim=True)
    eig = noise._eigenvalues(torch.einsum("rki,rkj->rij", x, x))
    want = (eig[:, 0] / eig[:, 1].clamp_min(torch.finfo(torch.float64).tiny)).sqrt()
    torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-7)
    assert got[4] == 1.0 and got[3] == 0.0 and got[2] == 0.0
    assert torch.equal(noise_cues(p), noise_cues(ordered, ordered=True))
    monkeypatch.setattr(noise.native, "available", lambda: False)
    torch.testing.assert_close(noise_cues(ordered, ordered=True), noise_cues(p), atol=1e-5, rtol=1e-3)
    monkeypatch.undo()
    with pytest.raises(ValueError, match="runs of 16 points"):
        native.run_flatness(runs, torch.tensor([len(runs) - 8]), 16)
    with pytest.raises(ValueError, match="level"):
        native.cell_thickness(ordered, 11, 8)
    with pytest.raises(ValueError, match="points"):
        native.cell_thickness(ordered.double(), 5, 8)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_noise_cues_lower_quartile_is_torch_quantile_to_the_bit(dtype):
    """The cues' lower quartile by two selections equals torch.quantile's sort and interpolation,
    value for value, with ties, at ranks between two values and on them, and NaN where one is."""
    from o3dvis.nn.noise import _quartile

    g = torch.Generator().manual_seed(3)
    for n in [*range(1, 40), 1001, 2048, 5000]:
        values = torch.rand(n, generator=g, dtype=dtype) ** 3
        values[::5] = values[0]
        assert torch.equal(_quartile(values), torch.quantile(values, 0.25)), n
    values[7] = float("nan")
    assert _quartile(values).isnan() and torch.quantile(values, 0.25).isnan()


def test_noise_cues_of_clouds_too_small_to_measure_are_zero():
    assert torch.equal(noise_cues(_noisy_sphere(10, 0.01)), torch.zeros(2, dtype=torch.float64))


def test_noise_cues_are_per_cloud_in_a_batch():
    torch.manual_seed(0)
    net = VisibilityNetwork(NetworkConfig(depth=6, noise_cues=True)).double().eval()
    clouds = [_noisy_sphere(3000, 0.0, seed=1), _noisy_sphere(5000, 0.01, seed=2)]
    batch = torch.cat([torch.full((len(c),), i) for i, c in enumerate(clouds)])
    with torch.no_grad():
        together = net.encode(torch.cat(clouds), batch, batch_size=2)
        alone = torch.cat([net.encode(c) for c in clouds])
    torch.testing.assert_close(together, alone)
