"""Errors while an atomic write is under way name the destination file, and leave nothing behind."""

from __future__ import annotations

import errno
import os

import numpy as np
import pytest

from jaxfish.io._atomic import atomic_path, atomic_write_bytes


def test_a_full_disk_names_the_destination_and_leaves_nothing(tmp_path, monkeypatch):
    dest = tmp_path / "out" / "lidar.npy"
    with pytest.raises(OSError) as e, atomic_path(dest) as part, open(part, "wb") as fh:
        np.save(fh, np.zeros(3))
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))  # what a write to a full disk raises
    assert e.value.errno == errno.ENOSPC and f"{dest}: cannot write (No space left on device)" in str(e.value)
    assert list((tmp_path / "out").iterdir()) == []

    def full(fh, data):
        raise OSError(errno.EDQUOT, os.strerror(errno.EDQUOT), fh.name)  # names the temporary file

    monkeypatch.setattr("jaxfish.io._atomic.write_sliced", full)
    with pytest.raises(OSError, match=rf"{dest.with_name('x.json')}: cannot write \(Disk quota exceeded\)"):
        atomic_write_bytes(dest.with_name("x.json"), b"{}")
    assert list((tmp_path / "out").iterdir()) == []


def test_another_files_error_keeps_its_own_name(tmp_path):
    dest = tmp_path / "copy.bin"
    with pytest.raises(FileNotFoundError) as e, atomic_path(dest) as part:
        part.write_bytes(open(tmp_path / "source.bin", "rb").read())
    assert e.value.filename == str(tmp_path / "source.bin") and not dest.exists()
    assert list(tmp_path.iterdir()) == []
