"""`jaxfish.io.load_npy`: ``np.load`` of a ``.npy`` file whose header is checked against the file's
size first, so that a header claiming more data than the file holds is refused before anything is
allocated."""

from __future__ import annotations

import io
import re

import numpy as np
import pytest

from jaxfish.io import DVS_EVENT_DTYPE, load_npy


def _arrays() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    events = np.zeros(5, DVS_EVENT_DTYPE)
    events["x"], events["t"] = [1, 2, 3, 4, 5], [10, 20, 30, 40, 50]
    return {
        "float32": rng.normal(size=(7, 4)).astype(np.float32),
        "fortran": np.asfortranarray(rng.normal(size=(3, 5))),
        "scalar": np.asarray(3.5),
        "empty": np.zeros((0, 4), np.float32),
        "events": events,
        "big-endian": rng.integers(0, 9, 6).astype(">u2"),
    }


@pytest.mark.parametrize("name", list(_arrays()))
def test_reads_what_np_load_reads(tmp_path, name):
    a = _arrays()[name]
    path = tmp_path / "a.npy"
    np.save(path, a, allow_pickle=False)
    for got in (load_npy(path), load_npy(str(path)), load_npy(io.BytesIO(path.read_bytes()))):
        assert got.dtype == a.dtype and got.shape == a.shape and np.array_equal(got, a)
        assert got.flags.f_contiguous == np.load(path).flags.f_contiguous


def test_reads_version_2_headers(tmp_path):
    a = np.arange(12, dtype=np.int16).reshape(3, 4)
    buf = io.BytesIO()
    np.lib.format.write_array(buf, a, version=(2, 0))
    path = tmp_path / "v2.npy"
    path.write_bytes(buf.getvalue())
    assert np.array_equal(load_npy(path), a)


def _claiming(shape: tuple[int, ...], data: bytes, descr: str = "<f4") -> bytes:
    head = io.BytesIO()
    np.lib.format.write_array_header_1_0(head, {"descr": descr, "fortran_order": False, "shape": shape})
    return head.getvalue() + data


@pytest.mark.parametrize("shape", [(10**12,), (2**40, 2**40), (4, 3)])
def test_a_header_claiming_more_than_the_file_holds_is_refused(tmp_path, shape):
    """A huge claim would make ``np.load`` allocate it (``MemoryError``); a small one reads short."""
    path = tmp_path / "huge.npy"
    path.write_bytes(_claiming(shape, bytes(40)))
    need = int(np.prod(shape, dtype=object)) * 4
    expected = re.escape(f"shape {shape}, {need} bytes of data, and the file holds 40")
    with pytest.raises(ValueError, match=rf"truncated \.npy: .* {expected}"):
        load_npy(path)
    with pytest.raises(ValueError, match="truncated"):
        load_npy(io.BytesIO(path.read_bytes()))


def test_extra_bytes_after_the_data_read_as_np_load_reads_them(tmp_path):
    path = tmp_path / "extra.npy"
    path.write_bytes(_claiming((2, 2), np.arange(4, dtype="<f4").tobytes() + b"trailing"))
    assert np.array_equal(load_npy(path), np.load(path))


def test_other_faults_raise_np_load_errors(tmp_path):
    path = tmp_path / "x.npy"
    path.write_bytes(b"PK\x03\x04 not a .npy at all")
    with pytest.raises(ValueError):
        load_npy(path)
    path.write_bytes(b"\x93NUMPY")
    with pytest.raises((ValueError, EOFError)):
        load_npy(path)
    path.write_bytes(_claiming((2,), bytes(8), descr="|O"))
    with pytest.raises(ValueError):  # object arrays: no pickles
        load_npy(path)
    with pytest.raises(OSError):
        load_npy(tmp_path / "missing.npy")
