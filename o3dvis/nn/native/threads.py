"""How many threads a kernel's work is shared out among: the calling thread and the helpers of
the kernels' crew (``o3dvis/nn/csrc/threads.c``)."""

from __future__ import annotations

import torch

from ...threads import usable_cores

# the most threads a kernel's work is shared out among: the caller's and the CREW_MAX helpers of the crew
MAX_THREADS = 65

SHARED_WORK = 1 << 24
"""Multiply-adds of a kernel call from which it shares its blocks with helper threads by default
(see :func:`kernel_threads`)."""


def kernel_threads(threads: int | None = None, work: int | None = None) -> int:
    """The threads a kernel's work is shared out among: the calling thread and up to ``threads - 1``
    helpers of the kernels' crew, kept for the process's life and asleep between kernels (work is
    claimed block by block, so a helper that starts late takes less of it).

    Args:
        threads: a count in [1, :data:`MAX_THREADS`]; None: torch's intra-op thread count of the
            calling thread (what :func:`o3dvis.threads.torch_threads` sets), at most the cores
            this process may use, and one for a call of less ``work`` than :data:`SHARED_WORK`.
        work: the call's multiply-adds, where known.

    Raises:
        ValueError: a count out of range.
    """
    if threads is None:
        if work is not None and work < SHARED_WORK:
            return 1
        return max(1, min(torch.get_num_threads(), usable_cores(), MAX_THREADS))
    if isinstance(threads, bool) or not isinstance(threads, int) or not 1 <= threads <= MAX_THREADS:
        raise ValueError(f"threads must be an int in [1, {MAX_THREADS}], got {threads!r}")
    return threads
