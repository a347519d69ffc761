"""What the tests of the C kernels share: each variant this CPU runs, and one view built both ways."""

import pytest
import torch

from o3dvis import clib
from o3dvis.nn import native
from o3dvis.nn.cues import ViewProjection

_CAMERA = torch.tensor([2.0, 1.0, -0.5])
_DIRECTION = torch.tensor([-0.3, 0.2, 1.0])
# the comparisons need the kernels; test_every_variant_this_cpu_runs_is_built fails where they should be and are not
needs_kernels = pytest.mark.skipif(not native.available(), reason="C kernels turned off (O3DVIS_NATIVE=0)")


@pytest.fixture(params=clib.runnable_variants())
def variant(request, monkeypatch) -> str:
    """Each variant of the kernels that this CPU runs, in turn, in place of the widest."""
    library = clib.load("o3dvis.nn._kernels", native._library.SIGNATURES, request.param)
    if library is None or library.variant != request.param:
        pytest.skip(f"the {request.param} kernels are not built")
    monkeypatch.setattr(native._library, "LIBRARY", library)
    return request.param


def _points(n: int = 6000, seed: int = 0) -> torch.Tensor:
    """A bumpy sphere with a point inside: surfaces that hide each other, empty pixels around."""
    g = torch.Generator().manual_seed(seed)
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=1)
    r = 0.8 + 0.1 * torch.sin(5 * d[:, :1]) * torch.cos(3 * d[:, 1:2])
    r[: n // 10] *= 0.5
    return d * r


def _views(points: torch.Tensor, **view) -> tuple[ViewProjection, ViewProjection]:
    """The same view built by the C kernels and by torch ops."""
    with torch.inference_mode():
        fast = ViewProjection(points, **view)
    with torch.no_grad(), pytest.MonkeyPatch.context() as mp:
        mp.setattr(native, "usable", lambda *tensors: False)
        slow = ViewProjection(points, **view)
    assert fast.native and not slow.native
    return fast, slow
