"""Process settings for bulk runs (edge code: they change the C allocator, the CPU affinity or the
lifetime of whole processes)."""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import os
import signal
import sys
import threading
import time
from collections.abc import Sequence

# glibc mallopt parameters (malloc.h).
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3
MMAP_THRESHOLD_BYTES = 32 * 2**20
"""glibc's largest mmap threshold on 64-bit systems (``DEFAULT_MMAP_THRESHOLD_MAX``)."""
_LOCK = threading.Lock()
_TUNED: bool | None = None


def tune_allocator() -> bool:
    """Make glibc's ``malloc`` keep the memory of freed large arrays in the process heap: blocks up
    to 32 MB come from the heap instead of fresh ``mmap`` regions, and the heap is not trimmed.

    Why: a sample's ground truth allocates and frees hundreds of image-sized buffers; served by
    fresh mappings, every one of them page-faults and is zeroed by the kernel again, and kept in
    the heap they are reused. The cost: freed memory is not returned to the system until the
    process ends, so a dataset build peaks higher, while most of its time is PNG and file I/O;
    `build_dataset` therefore applies it only with ``BuildOptions(tune_allocator=True)``. It suits
    scripts that compute ground truth in a loop (``scripts/bench_groundtruth.py`` applies it).
    Measured effect: ``docs/performance.md``.

    Idempotent and process-wide. Returns True when applied, False where the C library is not glibc
    (nothing changes)."""
    global _TUNED
    with _LOCK:
        if _TUNED is None:
            _TUNED = _apply()
        return _TUNED


def _apply() -> bool:
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    ok = mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)
    ok &= mallopt(_M_TRIM_THRESHOLD, 2**31 - 1)
    ok &= mallopt(_M_TOP_PAD, 64 * 2**20)
    return bool(ok)


def core_shares(workers: int, cores: Sequence[int]) -> list[tuple[int, ...]]:
    """One share of ``cores`` per worker: disjoint contiguous groups whose sizes differ by at most
    one when there are at least as many cores as workers, one core each round robin otherwise."""
    cores = list(cores)
    if workers < 1 or not cores:
        raise ValueError(f"core_shares: need at least one worker and one core, got {workers} and {cores}")
    if workers >= len(cores):
        return [(cores[i % len(cores)],) for i in range(workers)]
    bounds = [round(i * len(cores) / workers) for i in range(workers + 1)]
    return [tuple(cores[a:b]) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]


def share_cores(client) -> dict[str, tuple[int, ...]]:
    """Pin every worker process of ``client`` (a dask.distributed client of a cluster on this
    machine, e.g. `local_cluster`) to its own share of this process's cores (`core_shares`, in
    worker-name order). Returns ``{worker address: cores}``; ``{}`` where nothing was pinned (not
    Linux, or one worker sharing all cores).

    Why: each worker runs its own decode threads, write threads and XLA thread pool, all sized for
    the whole machine, so unpinned workers contend for every core (measured in
    ``docs/performance.md``). Don't call it for thread workers: they share one process."""
    if not hasattr(os, "sched_setaffinity"):  # pragma: no cover - not Linux
        return {}
    info = client.scheduler_info()["workers"]
    addresses = sorted(info, key=lambda a: str(info[a].get("name", a)))
    cores = sorted(os.sched_getaffinity(0))
    shares = core_shares(len(addresses), cores)
    if len(shares) == 1 and len(shares[0]) == len(cores):
        return {}
    for address, share in zip(addresses, shares, strict=True):
        client.run(_pin_process, share, workers=[address])
    return dict(zip(addresses, shares, strict=True))


def _pin_process(cores: tuple[int, ...]) -> None:
    """Set the CPU affinity of every thread of this process (threads started later inherit it)."""
    for tid in os.listdir("/proc/self/task"):
        with contextlib.suppress(OSError):  # a thread that has just ended
            os.sched_setaffinity(int(tid), cores)


# ------------------------------------------------------------------ local workers end with their build
BUILD_PID_ENV = "JAXFISH_BUILD_PID"
"""Environment variable naming the process whose local dask workers must not outlive it."""
_PR_SET_PDEATHSIG = 1  # linux/prctl.h
WATCHDOG_PERIOD_S = 0.5
"""How often `die_with_parent`'s watchdog thread looks at the parent process id."""


def _kill_self() -> None:
    os.kill(os.getpid(), signal.SIGKILL)


def _set_parent_death_signal(signum: int) -> bool:
    """``prctl(PR_SET_PDEATHSIG, signum)`` (Linux); False where unavailable."""
    if not sys.platform.startswith("linux"):  # pragma: no cover - not Linux
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        prctl = libc.prctl
    except (OSError, AttributeError):  # pragma: no cover - no C library prctl
        return False
    prctl.argtypes = [ctypes.c_int, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong]
    prctl.restype = ctypes.c_int
    return prctl(_PR_SET_PDEATHSIG, int(signum), 0, 0, 0) == 0


def die_with_parent(parent_pid: int) -> bool:
    """Make this process end (SIGKILL) as soon as its parent process ``parent_pid`` ends, however
    the parent ends (``kill -9`` included). If ``parent_pid`` is not this process's parent any more
    (it has already ended), this process ends now.

    On Linux the kernel sends the signal (``prctl(PR_SET_PDEATHSIG, SIGKILL)``): immediate, even
    while a C call holds the GIL. Everywhere, a daemon thread also compares ``os.getppid()`` with
    ``parent_pid`` every `WATCHDOG_PERIOD_S` seconds (a process whose parent ends is adopted by
    another). Returns True when the kernel-level signal is set."""
    armed = _set_parent_death_signal(signal.SIGKILL)
    if os.getppid() != parent_pid:  # the parent ended before the signal was set
        _kill_self()

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(WATCHDOG_PERIOD_S)
        _kill_self()

    threading.Thread(target=watch, name="jaxfish parent watchdog", daemon=True).start()
    return armed


def dask_setup(worker) -> None:
    """Dask worker preload (`jaxfish.dataset.local_cluster` names this module): a local worker
    process ends with the process that started the cluster (`die_with_parent`, whose id
    `BUILD_PID_ENV` holds; dask's nannies run in that process) and ignores SIGINT and SIGTERM, so
    that a Ctrl-C reaching the whole process group stops the build through its own process, which
    ends its workers. Does nothing in a worker without `BUILD_PID_ENV` or in the building process
    itself (thread workers)."""
    pid = os.environ.get(BUILD_PID_ENV, "")
    if not pid.isdigit() or int(pid) == os.getpid():
        return
    die_with_parent(int(pid))
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
