"""Folders jaxfish writes: its temporaries are recognisable (and only they are cleaned), a folder is
locked while written, and `synthesize_capture` writes only into a new, empty or jaxfish capture."""

from __future__ import annotations

import json
import subprocess
import sys

import jax.numpy as jnp
import pytest

import jaxfish as jf
from jaxfish.dataset import synthesize_capture
from jaxfish.io import CaptureError, atomic_path, atomic_write_text
from jaxfish.io._folder import RUN_ID, folder_lock, is_temporary, remove_temporaries
from jaxfish.scene import CaptureConfig

STALE = ".jaxfish-0badc0de-rgb_curr.k2x_9aqz.part.png"
"""A temporary file name of another (killed) run."""
USER_FILES = ("notes/.thesis.part1.tex", "rec.mcap", ".00000_FV.abcd1234.part.png", "x.part", ".jaxfish-notes.txt")
"""Names a user may give files: some hold '.part' or jaxfish's prefix, none is a jaxfish temporary."""


def test_atomic_writes_name_their_temporaries_by_the_scheme_the_cleaner_knows(tmp_path):
    with atomic_path(tmp_path / "sub" / "00000_FV.png") as tmp:
        assert tmp.parent == tmp_path / "sub" and tmp.name.startswith(f".jaxfish-{RUN_ID}-00000_FV.")
        assert tmp.name.endswith(".part.png") and is_temporary(tmp.name) and is_temporary(tmp.name, run=RUN_ID)
        assert not is_temporary(tmp.name, run="0badc0de")
        assert remove_temporaries(tmp_path, run="0badc0de") == 0 and tmp.exists()
        tmp.write_bytes(b"x")
    assert [p.name for p in (tmp_path / "sub").iterdir()] == ["00000_FV.png"]
    with atomic_path(tmp_path / ("n" * 250 + ".json")) as tmp:  # a long name keeps a valid temporary name
        assert is_temporary(tmp.name) and len(tmp.name) < 120
    assert is_temporary(STALE) and not is_temporary(STALE, run=RUN_ID)
    for name in USER_FILES:
        assert not is_temporary(name.rsplit("/", 1)[-1]), name


def test_remove_temporaries_removes_only_jaxfish_temporaries(tmp_path):
    for rel in USER_FILES + (f"a/b/{STALE}", STALE):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(rel)
    outside = tmp_path.parent / f"{tmp_path.name}_outside"
    outside.mkdir()
    (outside / STALE).write_text("not under the folder")
    (tmp_path / "link").symlink_to(outside, target_is_directory=True)
    assert remove_temporaries(tmp_path) == 2
    assert sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*") if p.is_file()) == sorted(USER_FILES)
    assert (outside / STALE).exists()  # symbolic links are not followed
    assert remove_temporaries(tmp_path / "missing") == 0


_HOLD = """
import fcntl, os, sys
fd = os.open(sys.argv[1], os.O_RDONLY)
fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
print("locked", flush=True)
sys.stdin.read()  # until the test closes the pipe
"""


def hold_lock(folder):
    """Another process holding ``folder``'s lock until its stdin is closed (waits for its 'locked')."""
    proc = subprocess.Popen([sys.executable, "-c", _HOLD, str(folder)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            text=True)
    assert proc.stdout.readline().strip() == "locked"
    return proc


def release(proc) -> None:
    """End a `hold_lock` process (it exits when its stdin closes)."""
    proc.stdin.close()
    proc.wait()
    proc.stdout.close()


def test_folder_lock_refuses_a_second_writer_in_this_or_another_process(tmp_path):
    with folder_lock(tmp_path, CaptureError, "test"):
        with pytest.raises(CaptureError, match="another jaxfish test is writing into this folder"):
            with folder_lock(tmp_path, CaptureError, "test"):
                pass
    with folder_lock(tmp_path, CaptureError, "test"):  # released on exit
        pass
    proc = hold_lock(tmp_path)
    try:
        with pytest.raises(CaptureError, match=str(tmp_path)):
            with folder_lock(tmp_path, CaptureError, "test"):
                pass
    finally:
        release(proc)
    with folder_lock(tmp_path, CaptureError, "test"):  # released when the process ends
        pass


SMALL = CaptureConfig(face_size=8, bev_size=8, front_width=8, front_height=6, dvs_substeps=1, lidar_channels=2,
                      lidar_points_per_channel=8, radar_points=4)


@pytest.fixture(scope="module")
def rig():
    return {"RV": jf.default_rig()["RV"].resize(16, 12).astype(jnp.float32)}


def test_synth_rerun_removes_a_killed_runs_temporaries_and_keeps_user_files(rig, tmp_path):
    out = tmp_path / "cap"
    synthesize_capture(out, rig, frames=1, seed=1, config=SMALL)
    stale = [out / STALE, out / "frames/000000/cameras/RV/left" / STALE]  # what kill -9 leaves
    for p in stale:
        p.write_bytes(b"half a png")
    for rel in USER_FILES:
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        (out / rel).write_text(rel)
    synthesize_capture(out, rig, frames=1, seed=2, config=SMALL)
    assert not any(p.exists() for p in stale)
    assert all((out / rel).read_text() == rel for rel in USER_FILES)
    assert json.loads((out / "capture.json").read_text())["seed"] == 2


def test_synth_writes_only_into_a_new_empty_or_capture_folder(rig, tmp_path):
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "rec.mcap").write_bytes(b"recording")
    with pytest.raises(CaptureError, match="not empty and not a jaxfish capture"):
        synthesize_capture(foreign, rig, frames=1, config=SMALL)
    assert sorted(p.name for p in foreign.iterdir()) == ["rec.mcap"]
    (tmp_path / "file").write_text("x")
    with pytest.raises(CaptureError, match="not a folder"):
        synthesize_capture(tmp_path / "file", rig, frames=1, config=SMALL)
    other = tmp_path / "other"
    atomic_write_text(other / "capture.json", json.dumps({"format": "someone-elses"}))
    with pytest.raises(CaptureError, match="capture.json of format 'jaxfish-capture'"):
        synthesize_capture(other, rig, frames=1, config=SMALL)
    empty = tmp_path / "empty"
    empty.mkdir()
    synthesize_capture(empty, rig, frames=1, config=SMALL)
    assert (empty / "capture.json").is_file()


def test_synth_refuses_a_locked_capture_folder(rig, tmp_path):
    out = tmp_path / "cap"
    out.mkdir()
    proc = hold_lock(out)
    try:
        with pytest.raises(CaptureError, match="another jaxfish capture writer"):
            synthesize_capture(out, rig, frames=1, config=SMALL)
    finally:
        release(proc)
    assert not any(out.iterdir())
