"""Per-view cues (``o3dvis.nn.cues``): depth residuals that flag hidden points, the same in chunks and
under autograd, patch tables, point surfels and their footprints."""

import math

import pytest
import torch

from o3dvis.nn import view_cues
from o3dvis.nn.cues import ViewProjection, point_surfels


def test_view_cues_flag_the_far_side_of_a_sphere():
    torch.manual_seed(0)
    p = torch.nn.functional.normalize(torch.randn(20000, 3), dim=1)
    cam = torch.tensor([3.0, 0.0, 0.0])
    dirs, cues = view_cues(p, cam)
    assert cues.shape == (20000, 36)
    torch.testing.assert_close(dirs, torch.nn.functional.normalize(p - cam, dim=1))
    visible = (p * (cam - p)).sum(1) > 0
    # residual to the own pixel (patch centre, index 4) at scale 2 (columns 9..17):
    # small in front, large behind, where the front surface covers every pixel
    own = cues[:, 9 + 4]
    assert own[visible].median() < 0.5 and own[~visible].median() > 2.0
    # the finest buffer has holes: many hidden points are alone in their pixel there
    assert (cues[~visible, 4] == 0).float().mean() > 0.2
    # an empty neighbour pixel is marked as such: the corners of the image are empty
    assert (cues == -5.0).any()


def test_view_cues_same_in_chunks_and_with_or_without_autograd(torch_ops):
    torch.manual_seed(0)
    p = torch.nn.functional.normalize(torch.randn(5000, 3), dim=1) * torch.rand(5000, 1)
    cam = torch.tensor([2.0, 1.0, -0.5], requires_grad=True)
    view = ViewProjection(p, cam)
    full = view.cues()
    assert full.shape == (5000, 36)
    full.sum().backward()  # the autograd path is differentiable end to end
    assert torch.isfinite(cam.grad).all()
    with torch.inference_mode():  # the in-place path
        fast = ViewProjection(p, cam.detach())
        chunks = torch.cat([fast.cues(slice(a, a + 1234)) for a in range(0, 5000, 1234)])
    torch.testing.assert_close(chunks, full.detach(), atol=1e-5, rtol=0)
    # an empty neighbour pixel gives exactly the empty cue on both paths (the in-place path maps it
    # to a residual beyond the clamp, whose asinh is that cue, so that no NaN reaches the asinh)
    empty = full.detach() == -5.0
    assert empty.any() and torch.equal(chunks == -5.0, empty)


def test_patch_table_rows_are_the_3x3_depth_neighbourhoods_of_the_pixels():
    torch.manual_seed(3)
    p = torch.nn.functional.normalize(torch.randn(700, 3), dim=1)
    view = ViewProjection(p, torch.tensor([0.5, 3.0, 1.0]))
    res = 27  # finest side: ceil(sqrt(700))
    pixel = view.pixels[:, 0]
    zbuf = torch.full(((res + 2) ** 2,), float("inf"))
    iu, iv = pixel // res, pixel % res
    zbuf = zbuf.scatter_reduce(0, (iu + 1) * (res + 2) + iv + 1, view.depth, "amin").view(res + 2, res + 2)
    zbuf[torch.isinf(zbuf)] = float("nan")  # empty or off the image
    for k in range(9):
        du, dv = divmod(k, 3)
        torch.testing.assert_close(view.patches[pixel, k], zbuf[iu + du, iv + dv], equal_nan=True)


def _grid_plane(side: int, z: float, extent: float = 0.9) -> torch.Tensor:
    """A side x side grid of points on the plane at ``z``, ``2 extent / (side - 1)`` apart."""
    t = torch.linspace(-extent, extent, side)
    u, v = torch.meshgrid(t, t, indexing="ij")
    return torch.stack([u.flatten(), v.flatten(), torch.full((side * side,), z)], dim=1)


@pytest.mark.parametrize("side", [40, 120])
def test_point_surfels_of_a_grid(side):
    """Cell counts give the distance between neighbours of a plane's grid within a factor of 1.5,
    and a plane twice as dense gets half the spacing (one plane alone: the cube holds it); the
    cells' planes give the plane's normal, up to its sign."""
    points = _grid_plane(side, 0.1)
    surfels = point_surfels(points)
    spacing, normals = surfels[:, 0], surfels[:, 1:]
    true = 1.8 / (side - 1)
    assert surfels.shape == (side * side, 4)
    assert true / 1.5 < spacing.median() < true * 1.5
    assert point_surfels(_grid_plane(2 * side, 0.1))[:, 0].median() < 0.7 * spacing.median()
    inner = points[:, :2].abs().amax(dim=1) < 0.75  # border cells may hold one row of points: no plane
    torch.testing.assert_close(normals[inner, 2].abs(), torch.ones(int(inner.sum())), atol=1e-4, rtol=0)
    order = torch.randperm(len(points), generator=torch.Generator().manual_seed(0))  # unsorted: sorted inside
    shuffled = point_surfels(points[order])
    torch.testing.assert_close(shuffled[:, 0], spacing[order])
    torch.testing.assert_close((shuffled[:, 1:] * normals[order]).sum(dim=1).abs(), torch.ones(len(points)))


def test_area_spacing_of_a_strip_that_crosses_its_cells_in_part():
    """Two rows of grid points 0.02 apart: too few in the cells of their own size, they take cells
    several rows wide, whose side over the square root of their count overstates the spacing about
    twice; the spread of the points gives it (within 10 %), in C as in torch."""
    u, v = torch.meshgrid(torch.arange(-0.5, 0.5, 0.02), torch.tensor([0.3, 0.32]), indexing="ij")
    points = torch.stack([u.flatten(), v.flatten(), torch.zeros(u.numel())], dim=1)
    points = torch.cat([points, torch.tensor([[-0.99, -0.99, -0.99], [0.99, 0.99, 0.99]])])  # the cube's corners
    expected = point_surfels(points, areas=True)
    with torch.inference_mode():  # the C kernel, where built
        kernel = point_surfels(points, areas=True)
    for surfels in (expected, kernel):
        assert surfels.shape == (len(points), 5)
        torch.testing.assert_close(surfels[:, :4], point_surfels(points))
        strip = surfels[:-2]
        assert strip[:, 0].min() > 1.5 * 0.02 and (strip[:, 4] - 0.02).abs().max() < 0.002
    torch.testing.assert_close(kernel[:, 4], expected[:, 4], rtol=1e-4, atol=1e-7)


def _slanted_plane(side: int, extent: float, slope: float) -> torch.Tensor:
    """A side x side grid of points on the plane z = 0.5 + slope * x."""
    points = _grid_plane(side, 0.5, extent)
    points[:, 2] += slope * points[:, 0]
    return points


@pytest.mark.parametrize("slope", [0.0, 1.5])
def test_footprints_close_the_holes_of_a_near_sparse_surface(slope, torch_ops):
    """A sparse plane close to the camera in front of a dense far plane: in the finest buffer the
    far plane shows through the gaps between the near points, so most far points see only their own
    depth around them; in the splatted finest buffer the near plane covers them. The splat is the
    near plane itself, so also when it is slanted its own points lie on it, not behind it. The
    buffers of the other scales stay as they were."""
    near, far = _slanted_plane(30, 0.3, slope), _grid_plane(150, -0.5, 0.3)
    points = torch.cat([near, far])
    camera = torch.tensor([0.0, 0.0, 0.9 + 0.3 * slope])
    plain = ViewProjection(points, camera).cues()
    view = ViewProjection(points, camera, surfels=point_surfels(points))
    cues = view.cues()
    assert plain.shape == (len(points), 36) and cues.shape == (len(points), 63)
    torch.testing.assert_close(cues[:, :36], plain)
    behind = far[:, 0].abs().lt(0.2) & far[:, 1].abs().lt(0.2)  # far points behind the near plane
    centre = 4  # the point's own pixel in the 3x3 patch
    own_plain, own_splat = plain[len(near):, centre][behind], cues[len(near):, 36 + centre][behind]
    assert (own_plain.abs() < 0.1).float().mean() > 0.5  # the far point is the nearest in its pixel
    assert (own_splat > 2.0).float().mean() > 0.95  # the near plane lies in front of it
    # a near point's own pixel holds its own plane, within 1.5 pixel footprints (a splat at the
    # point's own depth leaves 60 % of the slanted plane's points behind it by more)
    assert cues[:len(near), 36 + centre].abs().max() < math.asinh(1.5)


def test_view_cues_orthographic_direction():
    p = torch.nn.functional.normalize(torch.randn(5000, 3), dim=1)
    dirs, cues = view_cues(p, direction=torch.tensor([-1.0, 0.0, 0.0]))
    assert torch.equal(dirs, torch.tensor([-1.0, 0.0, 0.0]).expand(5000, 3))
    visible = p[:, 0] > 0
    own = cues[:, 9 + 4]
    assert own[visible].median() < 0.5 and own[~visible].median() > 2.0
