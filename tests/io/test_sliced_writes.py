"""Files written from buffers in memory go out in slices of at most `WRITE_SLICE_BYTES`, with the
bytes NumPy's and the plain writers give."""

from __future__ import annotations

import io

import numpy as np
import pytest

from jaxfish.io import atomic_write_bytes, write_depth_npy, write_events_npy, write_flo
from jaxfish.io._atomic import WRITE_SLICE_BYTES, write_sliced
from jaxfish.io._carla import DVS_EVENT_DTYPE
from jaxfish.io._npz import write_npy_into


class _Recorder(io.RawIOBase):
    def __init__(self):
        self.sizes, self.data = [], bytearray()

    def writable(self):
        return True

    def write(self, b):
        n = memoryview(b).nbytes
        self.sizes.append(n)
        self.data += bytes(b)
        return n


@pytest.mark.parametrize("size", [0, 1, WRITE_SLICE_BYTES, WRITE_SLICE_BYTES + 1, 3 * WRITE_SLICE_BYTES - 7])
def test_write_sliced_writes_every_byte_in_bounded_slices(size):
    data = np.random.default_rng(size).integers(0, 256, size, dtype=np.uint8)
    for given in (data.tobytes(), data, data.reshape(-1, 1)):
        rec = _Recorder()
        write_sliced(rec, given)
        assert bytes(rec.data) == data.tobytes()
        assert all(0 < n <= WRITE_SLICE_BYTES for n in rec.sizes)
        assert len(rec.sizes) == -(-size // WRITE_SLICE_BYTES)


def _npy_bytes(arr) -> bytes:
    buf = io.BytesIO()
    np.save(buf, arr, allow_pickle=False)
    return buf.getvalue()


def test_write_npy_into_gives_np_save_bytes():
    rng = np.random.default_rng(0)
    ev = np.empty(300_000, DVS_EVENT_DTYPE)  # 3.9 MB: several slices
    ev["x"], ev["y"], ev["t"], ev["pol"] = rng.integers(0, 1280, ev.size), rng.integers(0, 966, ev.size), \
        np.arange(ev.size) * 7, rng.integers(0, 2, ev.size)
    depth = rng.random((700, 900), dtype=np.float32)
    for arr in (ev, depth, np.asfortranarray(depth), depth[:, ::2], np.zeros((0, 3), np.float32), np.ones((), np.float64)):
        rec = _Recorder()
        write_npy_into(rec, arr)
        assert bytes(rec.data) == _npy_bytes(arr)


def test_file_writers_keep_their_bytes(tmp_path):
    rng = np.random.default_rng(1)
    depth = rng.random((966, 1280), dtype=np.float32)
    ev = np.zeros(100_000, DVS_EVENT_DTYPE)
    ev["t"] = np.arange(ev.size)
    write_depth_npy(tmp_path / "d.npy", depth)
    write_depth_npy(tmp_path / "f.npy", np.asfortranarray(depth))
    write_events_npy(tmp_path / "e.npy", ev)
    assert (tmp_path / "d.npy").read_bytes() == _npy_bytes(depth)
    assert (tmp_path / "f.npy").read_bytes() == _npy_bytes(np.asfortranarray(depth))
    assert (tmp_path / "e.npy").read_bytes() == _npy_bytes(ev)
    flow = rng.random((966, 1280, 2), dtype=np.float32)
    write_flo(tmp_path / "x.flo", flow)
    want = np.float32(202021.25).tobytes() + np.array([1280, 966], "<i4").tobytes() + flow.astype("<f4").tobytes()
    assert (tmp_path / "x.flo").read_bytes() == want
    blob = rng.integers(0, 256, 5 * WRITE_SLICE_BYTES // 2, dtype=np.uint8).tobytes()
    atomic_write_bytes(tmp_path / "b.bin", blob)
    assert (tmp_path / "b.bin").read_bytes() == blob
