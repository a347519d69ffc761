"""Large CPU buffers on transparent huge pages.

A fresh buffer of hundreds of megabytes (the per-point features of a cloud of
millions of points) is faulted in by the kernel one 4 KiB page at a time on its
first write, which can cost more than the write itself. On Linux, where
transparent huge pages are enabled in ``madvise`` (or ``always``) mode, advising
the buffer onto them makes each fault bring in 2 MiB.
"""

from __future__ import annotations

import ctypes
import sys

import torch
from torch import Tensor

__all__ = ["empty_huge"]

_HUGE_PAGE = 1 << 21
_MADV_HUGEPAGE = 14  # Linux's asm-generic value (a system that reads it otherwise refuses the advice)
# smaller buffers are not worth a system call (and mostly reuse pages the allocator has faulted in)
_MIN_BYTES = 8 * _HUGE_PAGE
_LIBC = ctypes.CDLL(None, use_errno=True) if sys.platform.startswith("linux") else None


def empty_huge(shape: tuple[int, ...], dtype: torch.dtype = torch.float32,
               device: torch.device | str = "cpu") -> Tensor:
    """``torch.empty(shape)``, advised onto transparent huge pages when it is a large CPU buffer.

    The 2 MiB-aligned interior of the buffer is advised with ``madvise(MADV_HUGEPAGE)``
    before anything is written to it; where the system does not take the advice (another
    OS, huge pages off) the buffer is a plain one.

    Args:
        shape: the tensor's shape.
        dtype: its dtype.
        device: its device; only CPU buffers are advised.

    Returns:
        An uninitialised contiguous tensor.
    """
    out = torch.empty(shape, dtype=dtype, device=device)
    size = out.numel() * out.element_size()
    if _LIBC is not None and out.device.type == "cpu" and size >= _MIN_BYTES:
        start = out.data_ptr()
        first = -(-start // _HUGE_PAGE) * _HUGE_PAGE
        last = (start + size) // _HUGE_PAGE * _HUGE_PAGE
        _LIBC.madvise(ctypes.c_void_p(first), ctypes.c_size_t(last - first), _MADV_HUGEPAGE)
    return out
