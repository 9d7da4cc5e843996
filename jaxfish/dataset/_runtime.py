"""Process settings for bulk runs (edge code: they change the C allocator, the CPU affinity or the
lifetime of whole processes)."""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import os
import signal
import sys
import tempfile
import threading
import time
import warnings
from collections.abc import Sequence
from pathlib import Path

# glibc mallopt parameters (malloc.h).
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD, _M_ARENA_MAX = -1, -2, -3, -8
MMAP_THRESHOLD_BYTES = 32 * 2**20
"""glibc's largest mmap threshold on 64-bit systems (``DEFAULT_MMAP_THRESHOLD_MAX``)."""
MALLOC_ARENAS = 2
"""The most heaps (glibc arenas) `tune_allocator` lets the threads of a process allocate from
(glibc's default: eight per core)."""
_LOCK = threading.Lock()
_TUNED: bool | None = None


def tune_allocator() -> bool:
    """Make glibc's ``malloc`` keep the memory of freed large arrays in the process heap: blocks up
    to 32 MB come from the heap instead of fresh ``mmap`` regions, the heap is not trimmed, and the
    threads share at most `MALLOC_ARENAS` heaps.

    Why: a sample's ground truth allocates and frees hundreds of image-sized buffers; served by
    fresh mappings, every one of them page-faults and is zeroed by the kernel again, and kept in
    the heap they are reused. The cost: freed memory is not returned to the system until the
    process ends, so a process peaks higher. Each heap keeps its own high-water mark, so the
    threads that decode, compute and write a sample share a few heaps rather than each growing one
    (glibc's default); threads that allocated before the call keep the heap they have. The
    dataset builder applies it in the processes that build samples unless
    ``BuildOptions(tune_allocator=False)``; it suits any script that computes ground truth in a
    loop (``scripts/bench_groundtruth.py`` applies it).
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
    ok &= mallopt(_M_ARENA_MAX, MALLOC_ARENAS)
    return bool(ok)


def openexr_in_calling_thread() -> None:
    """Have OpenImageIO read and write OpenEXR files in the thread that calls it (its
    ``exr_threads`` attribute set to -1: OpenEXR starts no thread pool of its own).

    Why: the builder writes a sample's files on its own threads (``BuildOptions.write_threads``)
    and decodes a capture on its decode threads; OpenEXR's pool would only hand the same work to
    other threads, at a cost in CPU time (the same bytes either way). The builder applies it in
    the processes that build samples. Measured effect: ``docs/performance.md``. Process-wide and
    idempotent."""
    import OpenImageIO as oiio

    oiio.attribute("exr_threads", -1)


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


PREALLOCATE_ENV = "XLA_PYTHON_CLIENT_PREALLOCATE"
"""JAX's environment variable for GPU memory: unset or true, a process takes 75 % of the GPU's memory
when its GPU backend starts; ``false``, it allocates as it needs."""


ARENA_MAX_ENV = "MALLOC_ARENA_MAX"
"""glibc's environment variable for the most heaps a process's threads allocate from; read as the
process starts, before any thread has a heap."""


def allocator_env() -> dict[str, str]:
    """The environment `local_cluster`'s process workers get so that their threads share at most
    `MALLOC_ARENAS` heaps from the start, as `tune_allocator` caps them in a building process
    (which tunes only after its own threads have started): ``{ARENA_MAX_ENV: "2"}``, or nothing
    where this process's environment sets `ARENA_MAX_ENV` itself (the workers inherit that choice)."""
    return {} if ARENA_MAX_ENV in os.environ else {ARENA_MAX_ENV: str(MALLOC_ARENAS)}


def accelerator_sharing_env() -> dict[str, str]:
    """The environment `local_cluster`'s process workers get so that they, and the process that
    started them, can share one GPU: ``{PREALLOCATE_ENV: "false"}`` (each allocates GPU memory as it
    needs it; with JAX's default the first process to start takes 75 % of it and each later one
    settles, after failed allocations, for a share of what is left), or nothing where this
    process's environment sets `PREALLOCATE_ENV` itself (the workers inherit that choice). No
    effect without a GPU."""
    return {} if PREALLOCATE_ENV in os.environ else {PREALLOCATE_ENV: "false"}


def share_accelerator() -> bool:
    """Apply `accelerator_sharing_env` to this process, for a build on local process workers.
    Only possible while JAX has not started its backends here (the variable is read then); a
    value already in the environment is kept. Returns whether this process now allocates GPU
    memory as it needs it (always true of processes without a GPU, which have nothing to share)."""
    if PREALLOCATE_ENV in os.environ:
        return os.environ[PREALLOCATE_ENV].strip().lower() in ("false", "0")
    try:
        from jax._src import xla_bridge

        started = xla_bridge.backends_are_initialized()
    except (ImportError, AttributeError):  # pragma: no cover - another JAX: set it, read or not
        started = False
    if started:
        return not any(d.platform == "gpu" for d in xla_bridge.devices())
    os.environ[PREALLOCATE_ENV] = "false"
    return True


CORE_SHARES_ENV = "JAXFISH_CORE_SHARES"
"""Environment variable of `local_cluster`'s workers: every worker's share of the cores
(``"0,1;2,3"``: worker ``i`` takes the ``i``-th group), taken by `dask_setup` at the worker's start."""


def encode_shares(shares: Sequence[Sequence[int]]) -> str:
    """`core_shares` as the value of `CORE_SHARES_ENV`."""
    return ";".join(",".join(str(int(c)) for c in share) for share in shares)


def _share_of(name, value: str) -> tuple[int, ...] | None:
    """The share of the worker named ``name`` (`local_cluster` names them 0..N-1) in a
    `CORE_SHARES_ENV` value; None when it names none."""
    try:
        shares = [tuple(int(c) for c in group.split(",")) for group in value.split(";")]
        index = int(name)
    except (TypeError, ValueError):
        return None
    return shares[index] if 0 <= index < len(shares) and shares[index] else None


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
    ends its workers. A worker whose environment holds `CORE_SHARES_ENV` first pins itself to its
    share of the cores (by its name), before JAX starts: XLA's thread pools, the decode threads
    and the write threads of that worker then fit its share. Does nothing in a worker without
    `BUILD_PID_ENV` or in the building process itself (thread workers)."""
    pid = os.environ.get(BUILD_PID_ENV, "")
    if not (pid.isascii() and pid.isdigit()) or int(pid) == os.getpid():
        return
    share = _share_of(getattr(worker, "name", None), os.environ.get(CORE_SHARES_ENV, ""))
    if share is not None and hasattr(os, "sched_setaffinity"):
        # Before JAX starts its CPU client in this process: XLA sizes its thread pools from the
        # affinity it finds then (one intra-op thread per core of the share).
        with contextlib.suppress(OSError):  # a core this machine no longer lets us use
            _pin_process(share)
    die_with_parent(int(pid))
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)


# ------------------------------------------------------------------ compiled programs shared on disk
COMPILE_CACHE_ENV = "JAXFISH_COMPILE_CACHE"
"""Environment variable naming the default compile-cache folder (`default_compile_cache`); an empty
value turns the default cache off."""
MIN_COMPILE_SECONDS = 0.0
"""Programs that took at least this long to compile are written to the compile cache: all of them
(JAX's default, 1 s, would leave most of a build's programs out, and which ones would depend on how
busy the machine is; loading a small program costs less than compiling it)."""


class CompileCacheWarning(UserWarning):
    """The compile cache cannot be used (its folder is not a writable folder): the build goes on and
    compiles its programs in every process."""


def default_compile_cache() -> Path | None:
    """The compile-cache folder a build uses by default: ``$JAXFISH_COMPILE_CACHE`` when set (None
    when set to an empty string: no cache), else ``$XDG_CACHE_HOME/jaxfish/xla`` (``~/.cache``
    when ``XDG_CACHE_HOME`` is unset). Each process resolves it for itself: a remote worker finds
    its own user's folder."""
    env = os.environ.get(COMPILE_CACHE_ENV)
    if env is not None:
        return Path(env).expanduser() if env.strip() else None
    base = os.environ.get("XDG_CACHE_HOME", "").strip()
    return (Path(base) if base else Path.home() / ".cache") / "jaxfish" / "xla"


def compile_cache_folder(setting) -> Path | None:
    """The folder of a ``compile_cache`` setting (`jaxfish.dataset.BuildOptions`): True ->
    `default_compile_cache`, False / None -> None (off), a path -> that folder."""
    if setting is True:
        return default_compile_cache()
    if setting is False or setting is None:
        return None
    return Path(os.fspath(setting)).expanduser()


def compile_cache_problem(folder: str | os.PathLike) -> str | None:
    """Why ``folder`` cannot hold the compile cache (it is not a folder, cannot be created, or a file
    cannot be written into it), or None when it can. Creates the folder."""
    path = Path(folder)
    try:
        path.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".jaxfish-probe-", dir=path)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        return f"{path}: cannot be used as the compile cache ({e.strerror or type(e).__name__})"
    return None


_CACHE_SET: list[str | None] = [None]  # the folder use_compile_cache configured in this process
_WARNED: set[str] = set()


def use_compile_cache(setting=True) -> Path | None:
    """Configure JAX's persistent compilation cache in this process for a ``compile_cache``
    setting (`compile_cache_folder`): programs compiled from now on are written to the folder, and
    a program another process (a dask worker, an earlier build) compiled is loaded from it instead
    of compiled again. A loaded program is the compiled program itself: the outputs' bytes are the
    same (``tests/dataset/test_compile_cache.py``). Idempotent; returns the folder in use, None
    when off.

    Entries are written atomically (a temporary file renamed into place), so that processes may
    write the same entry at the same time and a process killed while writing leaves no partial
    entry; an entry that cannot be read back (corrupt) is removed and its program compiled again.
    A folder that cannot be used (`compile_cache_problem`) warns (`CompileCacheWarning`) and turns
    the cache off. The default setting (True) leaves a cache folder the process's own JAX
    configuration already names (``JAX_COMPILATION_CACHE_DIR``) in place.

    The cache key holds the program, the JAX and XLA versions and the compile options, not the
    CPU model: share one folder only between machines of the same CPU type."""
    import jax

    folder = compile_cache_folder(setting)
    current = jax.config.jax_compilation_cache_dir
    if setting is True and current and current != _CACHE_SET[0]:
        return Path(current)  # the process's own choice
    if folder is not None:
        problem = compile_cache_problem(folder)
        if problem is not None:
            if problem not in _WARNED:  # once per process and folder, not once per sample
                _WARNED.add(problem)
                warnings.warn(f"{problem}; building without it (every process compiles its programs)",
                              CompileCacheWarning, stacklevel=2)
            folder = None
    wanted = None if folder is None else str(folder.resolve())
    with _LOCK:
        if wanted == _CACHE_SET[0] and current == wanted:
            return folder
        _configure_jax_cache(wanted)
        _CACHE_SET[0] = wanted
    return None if wanted is None else Path(wanted)


def _configure_jax_cache(folder: str | None) -> None:
    import jax
    from jax.experimental.compilation_cache import compilation_cache as public

    public.reset_cache()
    jax.config.update("jax_compilation_cache_dir", folder)
    if folder is None:
        return
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_SECONDS)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    try:  # JAX's own file cache writes entries in place; ours renames them into place
        from jax._src import compilation_cache as internal

        with internal._cache_initialized_mutex:
            internal._cache = _AtomicFileCache(folder, internal.decompress_executable)
            internal._cache_initialized = True
    except (ImportError, AttributeError):  # pragma: no cover - another JAX: its own file cache
        pass


class _AtomicFileCache:
    """JAX's file cache layout (``{key}-cache`` files, JAX's compression), written through a
    temporary file renamed into place, and checked when read (an entry that does not decompress is
    removed and reported as missing)."""

    _SUFFIX = "-cache"

    def __init__(self, folder: str, decompress):
        self._path = Path(folder)
        self._decompress = decompress

    def get(self, key: str) -> bytes | None:
        path = self._path / f"{key}{self._SUFFIX}"
        try:
            value = path.read_bytes()
        except OSError:  # missing (or unreadable): compile
            return None
        try:
            self._decompress(value)
        except Exception:  # noqa: BLE001 - truncated or corrupt: whatever the codec raises
            with contextlib.suppress(OSError):
                path.unlink()
            warnings.warn(f"{path}: corrupt compile-cache entry removed (its program is compiled again)",
                          CompileCacheWarning, stacklevel=2)
            return None
        return value

    def put(self, key: str, value: bytes) -> None:
        path = self._path / f"{key}{self._SUFFIX}"
        if path.exists():
            return
        fd, tmp = tempfile.mkstemp(prefix=f".{key[:16]}-", suffix=".tmp", dir=self._path)
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(value)
            os.replace(tmp, path)  # atomic: a reader sees no entry or the whole entry
        except BaseException:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
            raise

    def clear(self) -> None:
        for p in self._path.glob(f"*{self._SUFFIX}"):
            with contextlib.suppress(OSError):
                p.unlink()
