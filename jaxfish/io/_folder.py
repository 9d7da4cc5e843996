"""Output folders that jaxfish owns: the names of its temporary files, their removal after a killed
run, and the lock that keeps two runs from writing into one folder at the same time.

Every file jaxfish writes goes through `jaxfish.io.atomic_path`, whose temporary file is named
``.jaxfish-{run}-{stem}.{random}.part{suffix}`` beside its destination: ``run`` identifies the
writing process (`RUN_ID`), ``random`` is `tempfile.mkstemp`'s. `remove_temporaries` deletes only
names of that form, never another file whose name merely contains ``.part``.
"""

from __future__ import annotations

import contextlib
import os
import re
import secrets
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path

TEMPORARY_PREFIX = ".jaxfish-"
"""First characters of every temporary file name jaxfish writes."""

_TEMPORARY = re.compile(r"\.jaxfish-[0-9a-f]{8}-(.*)\.[a-z0-9_]{8}\.part(\.[^/]*)?", re.S)


def _new_run_id() -> str:
    return secrets.token_hex(4)


RUN_ID = _new_run_id()
"""This process's run id (8 hex digits) in the names of its temporary files."""


def _renew_run_id() -> None:  # a forked child is another run
    global RUN_ID
    RUN_ID = _new_run_id()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_renew_run_id)


def temporary_prefix(path: str | os.PathLike) -> str:
    """``mkstemp`` prefix of the temporary file written for ``path``: ``.jaxfish-{RUN_ID}-{stem}.``
    (the stem cut to 64 characters, so that a long destination name keeps its temporary's name
    within the file system's limit)."""
    return f"{TEMPORARY_PREFIX}{RUN_ID}-{Path(path).stem[:64]}."


def is_temporary(name: str, *, run: str | None = None) -> bool:
    """Whether the file name ``name`` is a temporary file of jaxfish's `atomic_path` (of run ``run``
    only, when given)."""
    if not _TEMPORARY.fullmatch(name):
        return False
    return run is None or name.startswith(f"{TEMPORARY_PREFIX}{run}-")


def temporary_destination(name: str) -> str | None:
    """The destination stem a temporary file of `atomic_path` was written for (``.jaxfish-{run}-
    {stem}.{random}.part{suffix}`` -> ``stem``, cut to 64 characters as `temporary_prefix` cuts
    it), or None when ``name`` is not such a temporary."""
    m = _TEMPORARY.fullmatch(name)
    return m.group(1) if m else None


def remove_temporaries(root: str | os.PathLike, *, run: str | None = None,
                       owned: Callable[[Path], bool] | None = None) -> int:
    """Delete the temporary files of jaxfish's `atomic_path` (those of run ``run`` only, when given)
    anywhere under the folder ``root`` (symbolic links to folders are not followed); returns how
    many. Without ``run`` it also deletes a live run's temporaries: call it while holding the
    folder's `folder_lock`. ``owned``: delete only the temporaries whose destination
    ``folder / stem`` (relative to ``root``, `temporary_destination`) it accepts (a shard's own,
    under its `shard_lock`)."""
    n = 0
    root = Path(root)
    if not root.is_dir():
        return 0
    for dirpath, _dirs, files in os.walk(root):
        for name in files:
            if not is_temporary(name, run=run):
                continue
            if owned is not None:
                rel = Path(os.path.relpath(dirpath, root)) / str(temporary_destination(name))
                if not owned(Path(*rel.parts[1:]) if rel.parts[0] == "." else rel):
                    continue
            with contextlib.suppress(FileNotFoundError):
                os.unlink(os.path.join(dirpath, name))
                n += 1
    return n


def _busy(folder: Path, what: str) -> str:
    return f"{folder}: another jaxfish {what} is writing into this folder; wait until it ends or use another folder"


@contextlib.contextmanager
def folder_lock(folder: str | os.PathLike, error: type[Exception], what: str, *, shared: bool = False,
                busy: str | None = None) -> Iterator[None]:
    """Hold an exclusive lock on the existing folder ``folder`` for the duration of the block
    (``flock`` on the folder itself: no lock file is written, and the operating system releases it
    when the process dies, even by ``kill -9``). When another process (or another open of the folder
    in this process) holds it, raises ``error`` naming the folder and ``what`` is running there
    (``busy``: another message). ``shared``: a shared lock instead, which other shared holders
    (the shards of one build, `shard_lock`) keep together and an exclusive holder excludes.
    Where the file system cannot lock (some network file systems) or the platform has no ``flock``,
    it warns and runs unlocked."""
    folder = Path(folder)
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        warnings.warn(f"{folder}: cannot lock the folder on this platform; run one {what} at a time", stacklevel=3)
        yield
        return
    fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0) | getattr(os, "O_CLOEXEC", 0))
    try:
        try:
            fcntl.flock(fd, (fcntl.LOCK_SH if shared else fcntl.LOCK_EX) | fcntl.LOCK_NB)
        except BlockingIOError:
            raise error(busy or _busy(folder, what)) from None
        except OSError as e:  # pragma: no cover - depends on the file system
            warnings.warn(f"{folder}: cannot lock the folder ({e.strerror}); run one {what} at a time", stacklevel=3)
        yield
    finally:
        os.close(fd)  # releases the lock


def _lock_file(path: Path, flags: int) -> int | None:
    """Open (creating) the lock file ``path`` and ``flock`` it with ``flags``; returns its
    descriptor, or None when it is held elsewhere (``LOCK_NB``). Other errors propagate."""
    import fcntl

    fd = os.open(path, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o644)
    try:
        fcntl.flock(fd, flags)
    except BlockingIOError:
        os.close(fd)
        return None
    except BaseException:
        os.close(fd)
        raise
    return fd


SHARD_LOCK_SUFFIX = ".lock"
"""Suffix of the lock files `shard_lock` keeps in its folder."""


@contextlib.contextmanager
def shard_lock(folder: str | os.PathLike, locks: str | os.PathLike, index: int, count: int,
               error: type[Exception], what: str) -> Iterator[None]:
    """Hold the locks of shard ``index`` of ``count`` writing into the existing folder ``folder``
    for the duration of the block; raises ``error`` (naming the folder) when they are held elsewhere.

    - a shared `folder_lock` on ``folder``: the shards of one run write side by side, while a whole
      run (the exclusive `folder_lock`) and a shard run exclude each other;
    - an exclusive lock on ``locks/{index}-of-{count}.lock``: two runs of the same shard exclude
      each other;
    - a shared lock on ``locks/of-{count}.lock``, taken only when no shard of another count holds
      its own (``locks/of-{other}.lock``): shards of different counts, whose samples overlap, never
      run together. ``locks/.lock`` serialises that check (held for a few system calls).

    The lock files (empty) stay in ``locks``; whoever finishes the shards (under the exclusive
    folder lock) removes the folder. Like `folder_lock`, the operating system releases every lock
    when the process dies; where the file system cannot lock, it warns and runs unlocked."""
    folder, locks = Path(folder), Path(locks)
    name = f"{int(index)}-of-{int(count)}"
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        warnings.warn(f"{folder}: cannot lock the folder on this platform; run one {what} per shard", stacklevel=3)
        yield
        return
    busy = (f"{folder}: a jaxfish {what} of the whole folder (or a merge) is writing into it; a shard cannot run "
            f"beside it: wait until it ends")
    with folder_lock(folder, error, what, shared=True, busy=busy):
        held: list[int] = []
        try:
            try:
                locks.mkdir(parents=True, exist_ok=True)
                mutex = _lock_file(locks / SHARD_LOCK_SUFFIX, fcntl.LOCK_EX)  # blocks for a few system calls at most
                try:
                    for other in sorted(locks.glob(f"of-*{SHARD_LOCK_SUFFIX}")):
                        if other.name == f"of-{int(count)}{SHARD_LOCK_SUFFIX}":
                            continue
                        fd = _lock_file(other, fcntl.LOCK_EX | fcntl.LOCK_NB)
                        if fd is None:
                            n = other.name.removeprefix("of-").removesuffix(SHARD_LOCK_SUFFIX)
                            raise error(f"{folder}: shards of another split (of {n}) are writing into this folder; "
                                        f"shard {index}/{count} would overlap their samples: wait until they end")
                        os.close(fd)
                    fd = _lock_file(locks / f"{name}{SHARD_LOCK_SUFFIX}", fcntl.LOCK_EX | fcntl.LOCK_NB)
                    if fd is None:
                        raise error(f"{folder}: another jaxfish {what} of shard {index}/{count} is writing into this "
                                    f"folder; wait until it ends")
                    held.append(fd)
                    group = _lock_file(locks / f"of-{int(count)}{SHARD_LOCK_SUFFIX}", fcntl.LOCK_SH)
                    held.append(group)
                finally:
                    if mutex is not None:  # pragma: no branch - a blocking lock is always granted
                        os.close(mutex)
            except OSError as e:  # pragma: no cover - depends on the file system
                if isinstance(e, error):
                    raise
                warnings.warn(f"{folder}: cannot lock shard {index}/{count} ({e.strerror}); run each shard once",
                              stacklevel=3)
            yield
        finally:
            for fd in held:
                if fd is not None:
                    os.close(fd)
