"""ISA-L deflate with placed states (`jaxfish.io._deflate`): the stray hash of ISA-L's level-1/2
body is CRC-32C of the state's address bits, where the state lies decides the parse, and placed
states give one byte stream per input whatever the thread."""

from __future__ import annotations

import subprocess
import sys
import threading
import zlib

import numpy as np
import pytest
from isal import isal_zlib

from jaxfish.io import _deflate, _png

placed_states = pytest.mark.skipif(not _deflate.DETERMINISTIC, reason="ISA-L states are placed on Linux x86-64 only")


def crc32c_bits(data: bytes, crc: int) -> int:
    """CRC-32C bit by bit (reflected Castagnoli polynomial), from ``crc``, no final inversion."""
    for byte in data:
        for i in range(8):
            crc = (crc >> 1) ^ (0x82F63B78 if (crc ^ (byte >> i)) & 1 else 0)
    return crc


def test_the_stray_hash_is_crc32c_of_the_word_from_zero():
    assert crc32c_bits(b"123456789", 0xFFFFFFFF) ^ 0xFFFFFFFF == 0xE3069283  # the standard check value
    words = np.random.default_rng(0).integers(0, 2**32, 300, dtype=np.uint64).astype(np.uint32)
    assert [int(h) for h in _deflate.stray_hash(words)] == [crc32c_bits(int(w).to_bytes(4, "little"), 0) for w in words]
    assert int(_deflate.stray_hash(np.uint32(0))) == 0  # why STRAY_HASH is odd: four zero bytes hash to 0
    assert _deflate.STRAY_HASH % 2 == 1 and _deflate.STRAY_HASH < 1 << _deflate.HASH_BITS


def test_candidate_addresses_qualify_in_order():
    found = [a for _, a in zip(range(3), _deflate.candidate_addresses(), strict=False)]
    assert found == sorted(found) and len(set(found)) == 3
    for a in found:
        assert a % (1 << 16) == 0 and a < 1 << 47 and _deflate.qualifies(a)
        assert int(_deflate.stray_hash(np.uint32(a >> 16))) & 0xFFFF == _deflate.STRAY_HASH
    assert not _deflate.qualifies(found[0] + (1 << 16))  # the next 64 KiB window hashes elsewhere


def place_first(addresses):
    """A state at the first of ``addresses`` that no other mapping holds."""
    for a in addresses:
        try:
            return _deflate.place(a)
        except OSError:
            continue
    raise AssertionError("no free address")


def recurring_third_position() -> np.ndarray:
    """Bytes whose 3rd to 10th recur after a zero run: ISA-L finds the repeat from the hash of the
    third position, the one its level-1/2 body takes from the state's address."""
    return np.frombuffer(b"\x07\x09ABCDEFGH" + bytes(100) + b"ABCDEFGH" + bytes(20), np.uint8)


@placed_states
def test_where_the_state_lies_decides_the_parse_and_placed_states_agree():
    data = recurring_third_position()
    third = int(_deflate.stray_hash(np.uint32(int.from_bytes(data[2:6].tobytes(), "little"))))
    # Own windows, far from the module's pool: the state that hashes the third position right,
    # and two that qualify.
    right = place_first(_deflate.candidate_addresses(0x3800_0000, stray=third & 0xFFFF))
    qualifying = _deflate.candidate_addresses(0x3A00_0000)
    states = [right, place_first(qualifying), place_first(qualifying)]
    try:
        for level in (1, 2):
            out_right, out_q1, out_q2 = (_deflate.deflate_with(s, data, level) for s in states)
            for out in (out_right, out_q1, out_q2):
                assert zlib.decompress(out) == data.tobytes()
            assert out_right != out_q1, "ISA-L no longer hashes the third position from the state's address"
            assert out_q1 == out_q2 == _deflate.compress(data, level)
    finally:
        for s in states:
            _deflate._LIBRARY.munmap(s.address, _deflate.STATE_BYTES)


def inputs() -> list[np.ndarray]:
    rng = np.random.default_rng(1)
    noisy = np.cumsum(rng.integers(-3, 4, (64, 385)), axis=1).astype(np.uint8)
    labels = np.repeat(np.repeat(rng.integers(0, 4, (8, 12), dtype=np.uint8), 6, 0), 32, 1)
    return [np.zeros(0, np.uint8), np.array([5], np.uint8), recurring_third_position(), noisy, labels,
            rng.integers(0, 256, 200_000, dtype=np.uint8), np.zeros(70_000, np.uint8)]


@pytest.mark.parametrize("level", [1, 2, 3])
def test_compress_is_a_zlib_stream_with_isal_zlib_parameters(level):
    for data in inputs():
        out = _deflate.compress(data, level)
        assert zlib.decompress(out) == data.tobytes()
        assert out[:2] == isal_zlib.compress(data, level)[:2]  # the same zlib header (window, level)
    data = inputs()[3]
    assert _deflate.compress(data.tobytes(), level) == _deflate.compress(data, level)  # bytes or array
    assert _deflate.compress(np.asfortranarray(data), level) == _deflate.compress(data, level)  # any layout, C order


def test_compress_rejects_levels_outside_one_to_three():
    for level in (0, 4):
        with pytest.raises(ValueError, match="levels 1-3"):
            _deflate.compress(b"abc", level)


@placed_states
def test_threads_compress_to_the_same_bytes():
    data = inputs()
    expected = {(i, level): _deflate.compress(d, level) for i, d in enumerate(data) for level in (1, 2)}
    seen: list[dict] = []

    def work():
        seen.append({(i, level): _deflate.compress(d, level) for _ in range(3)
                     for i, d in enumerate(data) for level in (1, 2)})

    threads = [threading.Thread(target=work) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(seen) == 4 and all(s == expected for s in seen)
    rgb = np.random.default_rng(2).integers(0, 256, (40, 50, 3), dtype=np.uint8)
    pngs = []
    threads = [threading.Thread(target=lambda: pngs.append(_png.encode_png(rgb))) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(set(pngs)) == 1 and pngs[0] == _png.encode_png(rgb)


def test_without_placed_states_compress_is_isal_zlib(monkeypatch):
    calls = []

    class Unplaced:
        @staticmethod
        def compress(data, level):
            calls.append((bytes(data), level))
            return isal_zlib.compress(data, level)

    monkeypatch.setattr(_deflate, "_LIBRARY", None)
    monkeypatch.setattr(_deflate, "_isal_zlib", Unplaced)
    data = inputs()[3]
    assert zlib.decompress(_deflate.compress(data, 2)) == data.tobytes()
    assert calls == [(data.tobytes(), 2)]
    with pytest.raises(OSError, match="cannot be placed"):
        _deflate.place(0x3C00_0000 << 16)


FORK_CHILD = """
import os, signal
import numpy as np
from jaxfish.io import _deflate

data = (np.arange(100_000) // 7).astype(np.uint8)
expected = _deflate.compress(data, 1)
with _deflate._LIBRARY.lock:  # as if another thread were taking a state at the fork
    pid = os.fork()
    if pid == 0:
        signal.alarm(30)  # a child waiting on the inherited lock ends instead of hanging
        os._exit(0 if _deflate.compress(data, 1) == expected else 3)
_, status = os.waitpid(pid, 0)
raise SystemExit(os.waitstatus_to_exitcode(status))
"""


@placed_states
def test_a_child_forked_while_a_thread_holds_the_pool_compresses():
    # In a fresh interpreter: this one may run JAX, whose threads make forking it unsafe.
    done = subprocess.run([sys.executable, "-c", FORK_CHILD], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr


@placed_states
def test_where_no_state_can_be_placed_compress_falls_back_after_a_few_tries(monkeypatch):
    library = _deflate._Library()
    tries = []

    def refuse(address):
        tries.append(address)
        raise OSError("refused")

    monkeypatch.setattr(library, "place_at", refuse)
    monkeypatch.setattr(_deflate, "_LIBRARY", library)
    data = inputs()[3]
    assert zlib.decompress(_deflate.compress(data, 1)) == data.tobytes()
    assert len(tries) == _deflate._PLACE_TRIES
    assert library.take() is None and len(tries) == _deflate._PLACE_TRIES  # no more tries
