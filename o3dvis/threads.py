"""How many CPU threads o3dvis runs on, and running many small torch tasks side by side.

o3dvis uses two kinds of threads: torch's intra-op threads (an OpenMP team that
splits each op, used while encoding a cloud; the C kernels share the blocks of a
convolution, a view or a sort with as many threads of their own, see
:func:`o3dvis.nn.native.kernel_threads`) and its own worker threads (views or
chunks of points answered side by side, each worker on one torch thread). One
task uses one kind at a time, so the threads it runs on are what
:func:`plan_threads` gives, never more than the cores this process may use; a
block whose parallel work is the workers' runs inside :func:`workers_only`.

The policy (``"auto"``, the default) for a task of ``work`` points or rows:

- one thread below ``min_work`` (a split op then costs more than it saves);
- one thread while tasks have been waiting for a CPU in more than a tenth of
  the last ten seconds (:func:`cpu_pressure`, Linux);
- otherwise torch's thread count (:func:`torch.get_num_threads`), at most the
  cores of the process's CPU affinity (and of its cgroup CPU quota), minus the
  cores that other processes keep busy right now (their runnable tasks, read
  from ``/proc/loadavg`` on Linux, without this process's own).

The load rules matter: an OpenMP team waits at the end of every op for its
slowest thread, and a thread that shares its core with a busy process is
descheduled for whole time slices, so two threads on two busy cores run many
times slower than one, while one thread on a free machine is at most as many
times slower as there are threads. Hence two signals: the runnable tasks of
right now catch a load that has just started, the pressure of the last seconds
one that pauses now and then. Each is read again after 50 ms at most. :func:`set_num_threads` (or
``O3DVIS_NUM_THREADS`` in the environment) fixes the count instead, whatever
the load and the size; in a forked child (a DataLoader worker), at most torch's
count there.
"""

from __future__ import annotations

import contextlib
import math
import os
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent import futures
from concurrent.futures import ThreadPoolExecutor

import torch

__all__ = ["set_num_threads", "get_num_threads", "usable_cores", "busy_cores", "plan_threads", "torch_threads",
           "workers_only", "threaded_map", "side_by_side", "cpu_pressure", "ENV_VAR", "MAX_PRESSURE",
           "PARALLEL_ROWS"]

ENV_VAR = "O3DVIS_NUM_THREADS"
"""Environment variable fixing the thread count (a positive int; ``auto`` or unset: the policy)."""

MAX_PRESSURE = 0.1
"""Above this :func:`cpu_pressure`, the automatic policy runs on one thread."""

_fixed: int | None = None  # set by set_num_threads; None: the environment variable, else automatic


def _count(value, source: str) -> int | None:
    """A thread count from ``value``: None (or ``"auto"``) for the policy, else a positive int."""
    if value is None or (isinstance(value, str) and value.strip().lower() in ("", "auto")):
        return None
    if isinstance(value, int) and not isinstance(value, bool):
        count = value
    elif isinstance(value, str) and value.strip().isdecimal():  # not isdigit: "²" is a digit int() refuses
        count = int(value)
    else:
        count = 0
    if count < 1:
        raise ValueError(f"{source} must be a positive int or 'auto', got {value!r}")
    return count


def set_num_threads(count: int | str | None) -> None:
    """Fixes the CPU threads o3dvis runs on, or goes back to the automatic policy.

    Args:
        count: a positive int (at most :func:`usable_cores` are used, and in a forked child at
            most its torch thread count), or None or ``"auto"`` for the policy of this
            module (then ``O3DVIS_NUM_THREADS`` applies again, when set).

    Raises:
        ValueError: ``count`` is not a positive int, None or ``"auto"``.
    """
    global _fixed
    _fixed = _count(count, "count")


def get_num_threads() -> int | None:
    """The fixed thread count (:func:`set_num_threads`, else ``O3DVIS_NUM_THREADS``); None: automatic.

    Raises:
        ValueError: ``O3DVIS_NUM_THREADS`` holds something else than a positive int or ``auto``.
    """
    return _fixed if _fixed is not None else _count(os.environ.get(ENV_VAR), ENV_VAR)


def _quota() -> int | None:
    """Cores of the cgroup (v2) CPU quota of this process, None without one."""
    try:
        with open("/sys/fs/cgroup/cpu.max") as f:
            quota, period = f.read().split()[:2]
        return None if quota == "max" else max(1, math.ceil(int(quota) / int(period)))
    except (OSError, ValueError):
        return None


def usable_cores() -> int:
    """The CPU cores this process may run on: its affinity, capped by its cgroup CPU quota. Read at
    most :data:`_READING_AGE` seconds ago."""
    return _recent("usable_cores", _usable_cores)


def _usable_cores() -> int:
    """:func:`usable_cores`, read now."""
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cores = os.cpu_count() or 1
    quota = _quota()
    return max(1, min(cores, quota) if quota else cores)


def _own_running() -> int:
    """This process's threads that are running or runnable now (Linux; 1 elsewhere)."""
    try:
        tasks = os.listdir("/proc/self/task")
    except OSError:
        return 1
    running = 0
    for tid in tasks:
        try:
            with open(f"/proc/self/task/{tid}/stat", "rb") as f:
                stat = f.read()
        except OSError:  # the thread ended meanwhile
            continue
        running += stat[stat.rfind(b")") + 2:][:1] == b"R"
    return max(1, running)


_READING_AGE = 0.05
"""Seconds a reading of the load (:func:`busy_cores`, :func:`cpu_pressure`) or of the usable cores
is used again: they read some ten files of ``/proc`` and ``/sys`` in about 100 µs, a small cloud's
call plans twice, and a load that matters lasts longer than this."""

_readings: dict[str, tuple[float, object]] = {}


def _recent(name: str, read: Callable[[], object]) -> object:
    """``read()``, or what it gave under ``name`` less than :data:`_READING_AGE` seconds ago."""
    now = time.monotonic()
    kept = _readings.get(name)
    if kept is None or not 0 <= now - kept[0] < _READING_AGE:
        kept = _readings[name] = (now, read())
    return kept[1]


def busy_cores() -> int:
    """How many of this process's :func:`usable_cores` other processes keep busy right now.

    The runnable tasks of the machine (``/proc/loadavg``) without this process's
    own, scaled to the share of the machine's CPUs this process may use; 0 where
    ``/proc/loadavg`` does not exist. Read at most :data:`_READING_AGE` seconds ago.
    """
    return _recent("busy_cores", _busy_cores)


def _busy_cores() -> int:
    """:func:`busy_cores`, read now."""
    try:
        with open("/proc/loadavg", "rb") as f:
            running = int(f.read().split()[3].split(b"/")[0])
    except (OSError, ValueError, IndexError):
        return 0
    others, cores = max(0, running - _own_running()), usable_cores()
    return min(cores, round(others * cores / max(cores, os.cpu_count() or 1)))


def cpu_pressure() -> float | None:
    """The share of the last ten seconds in which some task waited for a CPU (Linux pressure stall
    information: of this process's cgroup where it has its own, else of the machine), in [0, 1];
    None where unknown. Read at most :data:`_READING_AGE` seconds ago."""
    return _recent("cpu_pressure", _cpu_pressure)


def _cpu_pressure() -> float | None:
    """:func:`cpu_pressure`, read now."""
    for path in ("/sys/fs/cgroup/cpu.pressure", "/proc/pressure/cpu"):
        try:
            with open(path, "rb") as f:
                some = f.readline().split()
            return float(some[1].split(b"=")[1]) / 100
        except (OSError, ValueError, IndexError):
            continue
    return None


def plan_threads(work: int, min_work: int) -> int:
    """The threads a CPU task of ``work`` points (or rows) runs on (see the module's policy).

    Args:
        work: the size of the task.
        min_work: below this size one thread does it (ignored with a fixed count).

    Returns:
        A count in [1, :func:`usable_cores`].
    """
    fixed = get_num_threads()
    cores = usable_cores()
    limit = min(getattr(_OWN, "limit", None) or torch.get_num_threads(), cores)
    if fixed is not None:  # in a forked child, at most its own count: see _after_fork_in_child
        return min(fixed, limit if _forked else cores)
    if limit <= 1 or work < min_work or (cpu_pressure() or 0.0) > MAX_PRESSURE:
        return 1
    return max(1, min(limit, cores - busy_cores()))


@contextlib.contextmanager
def torch_threads(count: int) -> Iterator[None]:
    """Runs the block with ``count`` torch intra-op threads on the calling thread, then restores its count."""
    before = torch.get_num_threads()
    if count == before:
        yield
        return
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(before)


_OWN = threading.local()  # limit: torch's thread count where workers_only runs, else absent


@contextlib.contextmanager
def workers_only() -> Iterator[None]:
    """Runs the block with one torch intra-op thread on the calling thread, while :func:`plan_threads`
    plans as with torch's count before it: for blocks whose parallel work runs on the library's
    own workers (:func:`threaded_map`). After each op it splits, torch's OpenMP team spins some
    milliseconds, on a core that the workers then share with it."""
    before = getattr(_OWN, "limit", None)
    _OWN.limit = before or torch.get_num_threads()
    try:
        with torch_threads(1):
            yield
    finally:
        _OWN.limit = before


_POOL: ThreadPoolExecutor | None = None  # the worker threads, made on first use and kept
_POOL_LOCK = threading.Lock()
_WORKER = threading.local()  # whether the current thread is running an item of threaded_map


def _worker_pool() -> ThreadPoolExecutor:
    """The threads :func:`threaded_map` runs on: kept between calls (starting threads cost a
    fraction of a millisecond a call), made anew in a forked child (which has none of them)."""
    global _POOL
    with _POOL_LOCK:
        if _POOL is None:
            _POOL = ThreadPoolExecutor(thread_name_prefix="o3dvis-views")
        return _POOL


_forked = False  # whether this process is the child of a fork


def _after_fork_in_child() -> None:
    """A forked child has none of its parent's threads: it makes its own workers, and a fixed count
    never raises torch's count above the child's own. Torch's OpenMP (GNU libgomp), in a child
    forked after its parent ran a team, takes the team's threads for still there: a team of more
    than one waits for them for ever, which is why DataLoader workers set one torch thread."""
    global _POOL, _POOL_LOCK, _forked
    _POOL, _POOL_LOCK, _forked = None, threading.Lock(), True


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_after_fork_in_child)


def threaded_map(fn: Callable, items: Iterable, workers: int) -> Iterator:
    """``map(fn, items)`` on ``workers`` threads, each running torch ops on one thread of its own.

    On a CPU, views answered side by side this way are faster than one view at a
    time with every op split over the threads: the per-view ops are many and small
    (a split op waits for its slowest part), and each thread's buffers stay in its
    own cache. Each item runs without autograd (grad mode is per thread). A
    worker takes its own thread count before setting it to 1, and the caller's
    count is put back when it is done: ``torch.set_num_threads`` also sets the
    count that threads new to torch start with. The threads are kept for the next
    call; an item that calls this again runs the inner items on its own thread.
    When an item fails, or the caller stops early, the items not yet started are
    dropped, and the call returns once the started ones are done.
    """
    items = list(items)
    if getattr(_WORKER, "active", False):  # already on a worker: no threads on top of the planned ones
        yield from map(fn, items)
        return
    caller = torch.get_num_threads()
    results: list = [None] * len(items)
    ready = [threading.Event() for _ in items]
    state, lock = {"next": 0, "stop": False}, threading.Lock()

    def take() -> int | None:
        with lock:
            if state["stop"] or state["next"] >= len(items):
                return None
            state["next"] += 1
            return state["next"] - 1

    def run() -> None:
        _WORKER.active = True
        torch.get_num_threads()  # this thread's count is settled now, not at its first parallel op
        torch.set_num_threads(1)
        try:
            while (i := take()) is not None:
                try:
                    with torch.inference_mode():
                        results[i] = (fn(items[i]), None)
                except BaseException as error:  # handed to the caller at its turn
                    results[i] = (None, error)
                ready[i].set()
        finally:
            torch.set_num_threads(caller)
            _WORKER.active = False

    pool = _worker_pool()
    runners = [pool.submit(run) for _ in range(min(workers, len(items)))]
    try:
        for i in range(len(items)):
            ready[i].wait()
            value, error = results[i]
            if error is not None:
                raise error
            yield value
    finally:
        with lock:
            state["stop"] = True
        futures.wait(runners)


PARALLEL_ROWS = 8192
"""Rows below which per-point work (plane fits, votes, neighbour searches) runs on one thread."""


def side_by_side(fn: Callable, items: list, workers: int) -> Iterator:
    """``map(fn, items)``: on ``workers`` threads, or on the caller's alone for one."""
    return map(fn, items) if workers == 1 else threaded_map(fn, items, workers)
