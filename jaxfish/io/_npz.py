"""Deterministic ``.npz`` files: ``np.savez``'s layout (one stored ``{name}.npy`` per array, zip64
headers) with fixed zip timestamps, written straight from the arrays' buffers or from chunks."""

from __future__ import annotations

import io
import os
import zipfile
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from ._atomic import atomic_path, write_sliced

ZIP_DATE_TIME = (1980, 1, 1, 0, 0, 0)
"""The timestamp of every member `write_npz` writes (zip's earliest)."""


class NpzMember:
    """One array of an ``.npz`` given as its ``dtype``, ``shape`` and a function returning its
    C-order bytes in chunks (bytes-like objects whose sizes add up to the array's), so that a
    large derived array is written without ever being held whole."""

    def __init__(self, dtype: np.dtype, shape: tuple[int, ...], chunks: Callable[[], Iterable]):
        self.dtype, self.shape, self.chunks = np.dtype(dtype), tuple(int(n) for n in shape), chunks


def _npy_header(dtype: np.dtype, shape: tuple[int, ...]) -> bytes | None:
    """The ``.npy`` header `np.lib.format.write_array` writes for a C-order array (version 1.0),
    or None when it needs a later version (a long header, non-Latin-1 field names)."""
    if dtype.hasobject:
        raise ValueError("Object arrays cannot be saved when allow_pickle=False")
    buf = io.BytesIO()
    header = {"descr": np.lib.format.dtype_to_descr(dtype), "fortran_order": False, "shape": shape}
    try:
        np.lib.format.write_array_header_1_0(buf, header)
    except (ValueError, UnicodeEncodeError):
        return None
    return buf.getvalue()


def write_npz(path: str | os.PathLike, **arrays: np.ndarray | NpzMember) -> Path:
    """``np.savez``-compatible ``.npz`` with fixed zip timestamps (1980-01-01), so the same arrays
    always give the same bytes (``np.savez`` stamps the current time); atomic, no pickle. A member
    may be an `NpzMember` (its bytes produced chunk by chunk); an array's bytes are written from
    its buffer (the bytes ``np.savez`` writes)."""
    path = Path(path)
    with atomic_path(path) as tmp, zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED) as zf:
        for name, member in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=ZIP_DATE_TIME)
            info.compress_type = zipfile.ZIP_STORED
            with zf.open(info, "w", force_zip64=True) as fh:
                _write_member(fh, member)
    return path


def _write_member(fh, member: np.ndarray | NpzMember) -> None:
    if isinstance(member, NpzMember):
        header = _npy_header(member.dtype, member.shape)
        if header is None:
            raise ValueError(f"write_npz: the .npy header of a {member.dtype} {member.shape} member needs version 2 or 3")
        fh.write(header)
        size = 0
        for chunk in member.chunks():
            fh.write(chunk)
            size += memoryview(chunk).nbytes
        if size != member.dtype.itemsize * int(np.prod(member.shape)):
            raise ValueError(f"write_npz: a {member.dtype} {member.shape} member's chunks hold {size} bytes")
        return
    write_npy_into(fh, member)


def npy_layout(file: io.BufferedIOBase) -> tuple[np.dtype, tuple[int, ...], int] | None:
    """The dtype, shape and data offset of the ``.npy`` file open at its start (a binary file),
    its header checked against the file's size: a header claiming more data than the file holds
    (a truncated or corrupt file) raises ``ValueError`` stating both sizes. None for a header this
    check does not read (version 3.0: NumPy's, for non-Latin-1 field names), a Fortran-order or an
    object array. Leaves the file's position anywhere. Other faults raise ``np.load``'s
    ``ValueError`` or ``EOFError``."""
    start = file.tell()
    version = np.lib.format.read_magic(file)
    if version == (1, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_1_0(file)
    elif version == (2, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_2_0(file)
    else:
        return None
    data = file.tell()
    if dtype.hasobject:
        return None
    need = int(np.prod(shape, dtype=object)) * dtype.itemsize  # Python ints: no overflow
    held = file.seek(0, os.SEEK_END) - data
    if held < need:
        raise ValueError(f"truncated .npy: its header declares a {dtype} array of shape {shape}, "
                         f"{need} bytes of data, and the file holds {held}")
    if fortran and len(shape) > 1:
        return None
    return dtype, tuple(shape), data - start


def load_npy(file: str | os.PathLike | io.BufferedIOBase) -> np.ndarray:
    """``np.load`` of a ``.npy`` file (a path, or a binary file open at its start) without pickles,
    its header checked against the file's size first (`npy_layout`): a header claiming more data
    than the file holds (a truncated or corrupt file) raises ``ValueError`` stating both sizes,
    where ``np.load`` would first allocate the claimed array (a ``MemoryError`` for a huge claim).
    Other faults raise ``np.load``'s ``ValueError``, ``OSError`` or ``EOFError``. The check reads
    headers of versions 1.0 and 2.0; a version 3.0 header (NumPy's, for non-Latin-1 field names) is
    left to ``np.load``."""
    if not hasattr(file, "read"):
        with open(file, "rb") as fh:
            return load_npy(fh)
    start = file.tell()
    npy_layout(file)
    file.seek(start)
    return np.load(file, allow_pickle=False)


def write_npy(path: str | os.PathLike, arr: np.ndarray) -> Path:
    """Write ``arr`` as ``.npy`` atomically: the bytes ``np.save(..., allow_pickle=False)`` writes
    (`write_npy_into`)."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        write_npy_into(fh, arr)
    return Path(path)


def write_npy_into(fh, arr: np.ndarray) -> None:
    """The bytes ``np.save(fh, arr, allow_pickle=False)`` writes, its data from the array's buffer
    in slices (`write_sliced`) when the array is C-contiguous and its header version 1.0."""
    arr = np.asanyarray(arr)
    header = _npy_header(arr.dtype, arr.shape) if arr.flags.c_contiguous and type(arr) is np.ndarray else None
    if header is None:  # Fortran order, a later header version, a subclass: NumPy's own writer
        np.lib.format.write_array(fh, arr, allow_pickle=False)
        return
    fh.write(header)
    if arr.size:
        write_sliced(fh, arr)
