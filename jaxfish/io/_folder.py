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
from collections.abc import Iterator
from pathlib import Path

TEMPORARY_PREFIX = ".jaxfish-"
"""First characters of every temporary file name jaxfish writes."""

_TEMPORARY = re.compile(r"\.jaxfish-[0-9a-f]{8}-.*\.[a-z0-9_]{8}\.part(\.[^/]*)?", re.S)


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


def remove_temporaries(root: str | os.PathLike, *, run: str | None = None) -> int:
    """Delete the temporary files of jaxfish's `atomic_path` (those of run ``run`` only, when given)
    anywhere under the folder ``root`` (symbolic links to folders are not followed); returns how
    many. Without ``run`` it also deletes a live run's temporaries: call it while holding the
    folder's `folder_lock`."""
    n = 0
    root = Path(root)
    if not root.is_dir():
        return 0
    for dirpath, _dirs, files in os.walk(root):
        for name in files:
            if is_temporary(name, run=run):
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(os.path.join(dirpath, name))
                    n += 1
    return n


@contextlib.contextmanager
def folder_lock(folder: str | os.PathLike, error: type[Exception], what: str) -> Iterator[None]:
    """Hold an exclusive lock on the existing folder ``folder`` for the duration of the block
    (``flock`` on the folder itself: no lock file is written, and the operating system releases it
    when the process dies, even by ``kill -9``). When another process (or another open of the folder
    in this process) holds it, raises ``error`` naming the folder and ``what`` is running there.
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
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise error(f"{folder}: another jaxfish {what} is writing into this folder; wait until it ends "
                        f"or use another folder") from None
        except OSError as e:  # pragma: no cover - depends on the file system
            warnings.warn(f"{folder}: cannot lock the folder ({e.strerror}); run one {what} at a time", stacklevel=3)
        yield
    finally:
        os.close(fd)  # releases the lock
