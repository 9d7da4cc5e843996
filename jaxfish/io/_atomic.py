"""Atomic file writing: nothing half-written is ever left at the destination path."""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ._folder import temporary_prefix


def _process_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


FILE_MODE = 0o666 & ~_process_umask()
"""Permission bits of every file written here: what ``open(path, "w")`` would give (0o666 minus
the umask, read once at import). `tempfile.mkstemp` creates its file 0o600, which would leave a
shared dataset unreadable to other users."""


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, *, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it is renamed onto ``path``
    (``os.replace``, atomic on POSIX) with the permissions of a plain ``open`` (`FILE_MODE`), on
    error it is removed. An `OSError` writing the temporary file (a full disk, a quota) is raised
    again naming ``path``. The temporary name is ``.jaxfish-{run}-{stem}.{random}.part{suffix}``
    (`jaxfish.io._folder`: a killed run's temporaries are recognised and removed by the next run,
    and no other file is); it keeps the destination's extension (or ``suffix``) so writers that
    dispatch on it work."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    suffix = path.suffix if suffix is None else suffix
    try:
        fd, tmp = tempfile.mkstemp(prefix=temporary_prefix(path), suffix=f".part{suffix}", dir=path.parent)
    except OSError as e:
        raise type(e)(e.errno, f"{path}: cannot write here ({e.strerror})") from None
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        try:
            yield tmp_path
        except OSError as e:  # writing the temporary file (e.g. ENOSPC): name the destination
            if e.errno is None or e.filename not in (None, str(tmp_path)):
                raise  # another file's error (a source the writer reads) names that file already
            raise type(e)(e.errno, f"{path}: cannot write ({e.strerror})") from None
        os.chmod(tmp_path, FILE_MODE)
        try:
            os.replace(tmp_path, path)
        except OSError as e:  # name the destination, not the temporary file
            raise type(e)(e.errno, f"{path}: cannot write ({e.strerror})") from None
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


WRITE_SLICE_BYTES = 1 << 20
"""Largest ``write`` call `write_sliced` makes. The kernel may back one large write with large
page-cache folios, each a block of free memory that a virtual machine may have handed back to its
host and must fault in again; writes of 1 MiB take the pages freed most recently. Figures in
docs/performance.md."""


def write_sliced(fh, data) -> None:
    """Write the bytes of ``data`` (bytes-like, or a C-contiguous NumPy array) to the binary file
    ``fh`` in slices of at most `WRITE_SLICE_BYTES`, without copying them."""
    view = memoryview(data.reshape(-1).view(np.uint8) if isinstance(data, np.ndarray) else data).cast("B")
    for start in range(0, view.nbytes, WRITE_SLICE_BYTES):
        fh.write(view[start:start + WRITE_SLICE_BYTES])


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write bytes to ``path`` atomically (`write_sliced`)."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        write_sliced(fh, data)
    return Path(path)


def atomic_copy_file(source: str | os.PathLike, path: str | os.PathLike) -> Path:
    """Copy the bytes of the file ``source`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        shutil.copyfile(source, tmp)
    return Path(path)


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write UTF-8 text to ``path`` atomically."""
    return atomic_write_bytes(path, text.encode("utf-8"))
