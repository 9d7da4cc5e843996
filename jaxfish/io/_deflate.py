"""Deterministic ISA-L deflate: the same input gives the same zlib stream in every thread and process.

ISA-L's level-1 and level-2 compressor (``igzip_icf_body_h1_gr_bt.asm``, the x86-64 bodies that
python-isal's ``isal_zlib.compress`` runs) hashes the stream's third input byte from a register
that still holds the address of the ``isal_zstream`` state instead of the input (in
``.write_first_byte``: ``shr tmp2, 16`` with ``tmp2`` never loaded from the data). That one hash
decides where the third position is recorded and which earlier position it is matched against, so
the LZ77 parse of a stream's first bytes, and therefore the compressed bytes, depends on where the
state lies in memory: python-isal keeps it on the calling thread's stack, so another thread or
another process occasionally writes other (equally valid) bytes for the same pixels.

`compress` runs the same ISA-L functions (``isal_deflate_init`` / ``isal_deflate``, exported by
python-isal's extension module) on a state that jaxfish places itself, at an address whose bits
16-47 hash to `STRAY_HASH` under every ISA-L hash mask (`qualifies`): one parse, one byte stream
per input, level and ISA-L version. Every other parameter is
``isal_zlib.compress``'s: a zlib wrapper, a 32 KiB window, the default level buffer of the level,
the whole input in one call.

Where states cannot be placed (not Linux on x86-64, or python-isal's module without exported ISA-L
symbols) `DETERMINISTIC` is False and `compress` is ``isal_zlib.compress`` itself, as it is once
`_PLACE_TRIES` candidate addresses in a row could not be mapped."""

from __future__ import annotations

import ctypes
import functools
import os
import platform
import sys
import threading
from collections.abc import Iterator

import numpy as np

try:
    from isal import isal_zlib as _isal_zlib
except ImportError:  # pragma: no cover - isal is a dependency
    _isal_zlib = None

LEVEL_BUF_BYTES = {1: 4096 + 2 * 8192 + 4 * 65536, 2: 4096 + 2 * 32768 + 4 * 65536,
                   3: 4096 + 4 * 4096 + 2 * 32768 + 4 * 65536}
"""ISA-L's default level buffer of each level (``ISAL_DEF_LVL<n>_DEFAULT``, what ``isal_zlib.compress``
allocates). Its size sets the deflate block size, so it is part of what fixes the bytes."""
STATE_BYTES = 1 << 18
"""Bytes reserved for one ``isal_zstream`` (about 82 KiB in ISA-L 2.3x: a history buffer of twice
the 32 KiB window and the level-0 hash heads make most of it)."""
HASH_BITS = 16
"""Low bits of the stray hash that every placed state shares: ISA-L masks it to at most 15 bits
(levels 2-3), to fewer for inputs under 16 KiB."""
STRAY_HASH = 0x9E37
"""The low `HASH_BITS` of the stray hash of every placed state. Odd, so that no mask maps it to 0
(the hash of four zero bytes, the most common word in filtered image rows); with it the builds
recorded in ``tests/dataset/manifests`` keep their bytes."""

_ZLIB_FLAG = 3  # IGZIP_ZLIB
_FULL_FLUSH = 2
_WINDOW_BITS = 15
_PROT_RW = 0x1 | 0x2
_MAP_FLAGS = 0x02 | 0x20 | 0x100000  # MAP_PRIVATE | MAP_ANONYMOUS | MAP_FIXED_NOREPLACE (Linux)
_MAX_INPUT = 2**32 - 2**26  # larger inputs (and their output bound) would overflow ISA-L's 32-bit counts: unplaced
_PLACE_TRIES = 16  # candidate addresses tried for one new state before the unplaced fallback
_SEARCH_FROM = 0x3000_0000  # bits 16-47 of the first candidate address: 0x3000_0000_0000, far from the usual mappings


class _Stream(ctypes.Structure):
    """The public head of ISA-L's ``struct isal_zstream`` (``igzip_lib.h``); the internal state
    follows it inside the `STATE_BYTES` reserved."""

    _fields_ = [("next_in", ctypes.c_void_p), ("avail_in", ctypes.c_uint32), ("total_in", ctypes.c_uint32),
                ("next_out", ctypes.c_void_p), ("avail_out", ctypes.c_uint32), ("total_out", ctypes.c_uint32),
                ("hufftables", ctypes.c_void_p), ("level", ctypes.c_uint32), ("level_buf_size", ctypes.c_uint32),
                ("level_buf", ctypes.c_void_p), ("end_of_stream", ctypes.c_uint16), ("flush", ctypes.c_uint16),
                ("gzip_flag", ctypes.c_uint16), ("hist_bits", ctypes.c_uint16)]


@functools.cache
def _crc32c_table() -> np.ndarray:
    table = np.arange(256, dtype=np.uint32)
    for _ in range(8):
        table = np.where(table & 1, (table >> 1) ^ np.uint32(0x82F63B78), table >> 1).astype(np.uint32)
    return table


def stray_hash(words) -> np.ndarray:
    """The hash ISA-L's ``compute_hash`` gives 32-bit ``words`` (uint32, any shape): the x86
    ``crc32`` instruction from 0, i.e. CRC-32C of the four little-endian bytes without the
    initial and final inversion. ISA-L masks it to the hash table's size."""
    table = _crc32c_table()
    crc = np.zeros(np.shape(words), np.uint32)
    w = np.asarray(words, np.uint32)
    for byte in range(4):
        crc = table[(crc ^ (w >> np.uint32(8 * byte))) & np.uint32(0xFF)] ^ (crc >> np.uint32(8))
    return crc


def _low_stray_hash(words) -> np.ndarray:
    """The low `HASH_BITS` of the stray hash of states whose address bits 16-47 are ``words``."""
    return stray_hash(words) & np.uint32((1 << HASH_BITS) - 1)


def qualifies(address: int) -> bool:
    """Whether a state at ``address`` gives the stray hash `STRAY_HASH` under every mask ISA-L uses."""
    return int(_low_stray_hash(np.uint32((address >> 16) & 0xFFFFFFFF))) == STRAY_HASH


def candidate_addresses(start: int = _SEARCH_FROM, stray: int = STRAY_HASH) -> Iterator[int]:
    """The 64 KiB-aligned addresses from ``start << 16`` up whose state gives the stray hash
    ``stray`` in its low `HASH_BITS` (by default those that `qualifies` accepts), in order: about
    one in every 4 GiB of address space (bits 16-47 give 2**32 words)."""
    block = 1 << HASH_BITS
    while start + block <= 1 << 31:  # user space ends below 2**47 on x86-64
        words = np.arange(start, start + block, dtype=np.uint32)
        yield from (int(w) << 16 for w in words[_low_stray_hash(words) == stray])
        start += block


class _Placed:
    """One ISA-L state at a qualifying address, with its level buffer."""

    def __init__(self, address: int):
        self.address = address
        self.stream = _Stream.from_address(address)
        self.level_buf = np.empty(max(LEVEL_BUF_BYTES.values()), np.uint8)
        self.out = np.empty(0, np.uint8)  # output space, kept: fresh pages would fault in every call

    def output(self, size: int) -> np.ndarray:
        """At least ``size`` bytes of output space (the kept buffer, grown when too small)."""
        if self.out.size < size:
            self.out = np.empty(size, np.uint8)
        return self.out


class _Library:
    """python-isal's extension module opened as a C library, and the placed states (a free list:
    one state per concurrent caller)."""

    def __init__(self):
        lib = ctypes.CDLL(_isal_zlib.__file__)
        self.init, self.deflate = lib.isal_deflate_init, lib.isal_deflate
        self.init.argtypes = self.deflate.argtypes = [ctypes.c_void_p]
        self.init.restype, self.deflate.restype = None, ctypes.c_int
        libc = ctypes.CDLL(None)
        self.mmap = libc.mmap
        self.mmap.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int, ctypes.c_int, ctypes.c_int, ctypes.c_long]
        self.mmap.restype = ctypes.c_void_p
        self.munmap = libc.munmap
        self.munmap.argtypes, self.munmap.restype = [ctypes.c_void_p, ctypes.c_size_t], ctypes.c_int
        self.lock = threading.Lock()
        self.free: list[_Placed] = []
        self.candidates = candidate_addresses()

    def place_at(self, address: int) -> _Placed:
        got = self.mmap(address, STATE_BYTES, _PROT_RW, _MAP_FLAGS, -1, 0)
        if got == address:
            return _Placed(address)
        if got not in (None, ctypes.c_void_p(-1).value):
            self.munmap(got, STATE_BYTES)  # an old kernel took the address as a hint only
        raise OSError(f"cannot place an ISA-L state at {address:#x}")

    def _place(self) -> _Placed:
        for _, address in zip(range(_PLACE_TRIES), self.candidates, strict=False):
            try:
                return self.place_at(address)
            except OSError:
                continue
        self.candidates = iter(())  # where that many fail, mappings are refused: stop trying
        raise OSError("no free address for an ISA-L state among the candidates")

    def take(self) -> _Placed | None:
        """A free placed state, a new one, or None where no candidate address is free."""
        with self.lock:
            if self.free:
                return self.free.pop()
            try:
                return self._place()
            except OSError:
                return None

    def give(self, placed: _Placed) -> None:
        with self.lock:
            self.free.append(placed)


def _open() -> _Library | None:
    if _isal_zlib is None or sys.platform != "linux" or platform.machine() not in ("x86_64", "AMD64"):
        return None
    try:
        return _Library()
    except (OSError, AttributeError):  # no such library or no exported ISA-L symbols
        return None


_LIBRARY = _open()
if _LIBRARY is not None and hasattr(os, "register_at_fork"):
    # A child forked while another thread held the lock would wait for it forever; its states are
    # its own copies (private mappings), free to reuse.
    os.register_at_fork(after_in_child=lambda: setattr(_LIBRARY, "lock", threading.Lock()))
DETERMINISTIC = _LIBRARY is not None
"""Whether `compress` places ISA-L's state itself (the bytes then depend on the input only)."""


def compress(data, level: int) -> bytes:
    """The zlib stream of ``data`` (a C-contiguous buffer) at ISA-L ``level`` 1-3: the format and
    parameters of ``isal_zlib.compress(data, level)``, from a state at a qualifying address
    (module docstring)."""
    if level not in LEVEL_BUF_BYTES:
        raise ValueError(f"ISA-L compresses at levels 1-3, got {level}")
    src = np.ascontiguousarray(data).reshape(-1).view(np.uint8) if isinstance(data, np.ndarray) else np.frombuffer(data, np.uint8)
    if _LIBRARY is None or src.size > _MAX_INPUT:
        return _isal_zlib.compress(src, level)
    placed = _LIBRARY.take()
    if placed is None:  # no state could be placed: unplaced, as python-isal
        return _isal_zlib.compress(src, level)
    try:
        return deflate_with(placed, src, level)
    finally:
        _LIBRARY.give(placed)


def place(address: int) -> _Placed:
    """A fresh ISA-L state at ``address`` (64 KiB-aligned, unmapped), for `deflate_with`. Raises
    OSError where it cannot be placed there or `DETERMINISTIC` is False."""
    if _LIBRARY is None:
        raise OSError("ISA-L states cannot be placed here (see jaxfish.io._deflate)")
    return _LIBRARY.place_at(address)


def deflate_with(placed: _Placed, src: np.ndarray, level: int) -> bytes:
    """The zlib stream of the uint8 vector ``src`` (at most `_MAX_INPUT` bytes) at ISA-L
    ``level``, compressed in one call on the state ``placed`` (not shared with another thread
    meanwhile)."""
    n = src.size
    # Room for every block stored (5 bytes a 65,535-byte block), the wrapper and a dynamic header.
    out = placed.output(n + 5 * (n // 65535 + 1) + 4096)
    z = placed.stream
    _LIBRARY.init(placed.address)
    z.level, z.level_buf, z.level_buf_size = level, placed.level_buf.ctypes.data, LEVEL_BUF_BYTES[level]
    z.hist_bits, z.gzip_flag = _WINDOW_BITS, _ZLIB_FLAG
    z.next_in, z.avail_in = src.ctypes.data, n
    z.flush, z.end_of_stream = _FULL_FLUSH, 1
    z.next_out, z.avail_out = out.ctypes.data, out.size
    err = _LIBRARY.deflate(placed.address)
    if err != 0 or z.avail_in != 0 or z.avail_out == 0:
        raise RuntimeError(f"ISA-L deflate failed (error {err}, {n} input bytes, {z.avail_in} left)")
    return out[:out.size - z.avail_out].tobytes()
