"""Large CPU buffers advised onto transparent huge pages (o3dvis.nn.memory)."""

import sys
from pathlib import Path

import pytest
import torch

from o3dvis.nn.memory import empty_huge

_THP = Path("/sys/kernel/mm/transparent_hugepage/enabled")


def _huge_kib(address: int) -> int | None:
    """AnonHugePages (KiB) of the mapping of this process that holds ``address``, from /proc/self/smaps."""
    inside = False
    for line in Path("/proc/self/smaps").read_text().splitlines():
        head = line.split()[0]
        if "-" in head and not head.endswith(":"):
            lo, hi = (int(x, 16) for x in head.split("-"))
            inside = lo <= address < hi
        elif inside and head == "AnonHugePages:":
            return int(line.split()[1])
    return None


def test_small_and_large_buffers_are_plain_tensors():
    for shape, dtype in (((3, 5), torch.float32), ((27, 1 << 20), torch.float32), ((1 << 22,), torch.int64)):
        t = empty_huge(shape, dtype)
        assert t.shape == shape and t.dtype == dtype and t.is_contiguous() and t.device.type == "cpu"
        t.fill_(1)
        assert int(t.sum()) == t.numel()


@pytest.mark.skipif(not sys.platform.startswith("linux") or not _THP.exists()
                    or "[never]" in _THP.read_text(), reason="no transparent huge pages here")
def test_a_large_buffer_sits_on_huge_pages():
    """Written once, a 64 MiB buffer is backed by huge pages (some of it at least: the kernel
    falls back to small pages where it finds no free 2 MiB block; unadvised, none of it is)."""
    t = empty_huge((16 << 20,))
    t.fill_(1.0)
    huge = _huge_kib(t.data_ptr() + t.numel() * 2)  # the middle of the buffer
    assert huge is not None and huge >= 2 << 10
