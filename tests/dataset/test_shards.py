"""Shards: N `build_dataset(..., shard=(I, N))` runs (or `jaxfish synth --shard`) into one folder and
a merge give the bytes of one run; the merge refuses what is not the complete split of one build;
the SLURM job array chooses the shard; shard locks and clean-ups keep to their shard."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from jaxfish.cli._demo import demo_config, demo_rig
from jaxfish.dataset import (
    DatasetError,
    Shard,
    build_dataset,
    merge_shards,
    parse_shard,
    slurm_shard,
    synthesize_capture,
)
from jaxfish.io import CaptureError
from jaxfish.io._folder import folder_lock, shard_lock
from tests.helpers import assert_same_tree
from tests.hostile.corpus import run_cli

from .small_capture import SCALE, SEED

FRAMES = 3
"""Frames of this module's capture: enough for 3 shards."""


@pytest.fixture(scope="module")
def capture3(tmp_path_factory):
    """The small capture's settings with `FRAMES` frames, rendered as one run."""
    root = tmp_path_factory.mktemp("shards") / "capture"
    return synthesize_capture(root, demo_rig(SCALE), frames=FRAMES, seed=SEED, config=demo_config(SCALE))


@pytest.fixture(scope="module")
def whole(capture3, tmp_path_factory):
    """One whole build of `capture3`."""
    out = tmp_path_factory.mktemp("shards_whole") / "dataset"
    assert build_dataset(capture3, out).ok
    return out


@pytest.fixture(scope="module")
def two_shards(capture3, tmp_path_factory):
    """`capture3` built as shards 0/2 and 1/2, not merged."""
    out = tmp_path_factory.mktemp("shards_two") / "dataset"
    for i in range(2):
        assert build_dataset(capture3, out, shard=(i, 2)).ok
    return out


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def test_the_rule_gives_the_kth_sorted_frame_to_shard_k_mod_n():
    assert Shard(1, 3).select([7, 0, 3, 3, 5, 9, 1]) == [1, 7]
    assert [Shard(i, 2).select(range(5)) for i in range(2)] == [[0, 2, 4], [1, 3]]
    assert Shard(2, 3).select([4, 8]) == []  # more shards than frames: an empty shard
    assert parse_shard(" 2/5 ") == Shard(2, 5) and str(Shard(2, 5)) == "2/5" and Shard(2, 5).name == "2-of-5"
    for bad in ("3/2", "0/0", "a/b", "1", "1/2/3", "-1/2", "", "1/ 2x"):
        with pytest.raises(DatasetError, match="--shard"):
            parse_shard(bad)
    for bad in ((2, 2), (0, 0), (-1, 3), (True, 2), ("0", 2)):
        with pytest.raises(DatasetError, match="shard"):
            Shard(*bad)


@pytest.mark.parametrize("count", [1, 2, 3])
def test_n_shard_builds_and_a_merge_equal_one_build_byte_for_byte(capture3, whole, tmp_path, count):
    out = tmp_path / "dataset"
    for i in reversed(range(count)):  # any order
        report = build_dataset(capture3, out, shard=(i, count))
        assert report.ok and report.samples == [f"{f:05d}" for f in range(i, FRAMES, count)], report.summary()
        assert not (out / "dataset.json").exists() and not (out / "calibration_data").exists()
        record = json.loads((out / ".shards" / f"{i}-of-{count}.json").read_text())
        assert record["shard"] == [i, count] and record["samples"] == report.samples
        assert record["requested"] == [f"{f:05d}" for f in range(FRAMES)]
    assert merge_shards(out).items == tuple(f"{f:05d}" for f in range(FRAMES))
    assert_same_tree(whole, out)  # markers, dataset.json and every file; the shard records are gone


def test_a_shard_build_resumes_and_a_whole_build_over_shards_supersedes_their_records(capture3, whole, two_shards,
                                                                                     tmp_path):
    out = _copy(two_shards, tmp_path / "dataset")
    again = build_dataset(capture3, out, shard=(1, 2))
    assert again.ok and again.skipped == ["00001"] and not again.built
    assert build_dataset(capture3, out).skipped == ["00000", "00001", "00002"]
    assert_same_tree(whole, out)


def test_the_merge_refuses_a_missing_shard_another_split_a_corrupt_record_or_an_incomplete_sample(
        capture3, two_shards, tmp_path, capsys):
    def refused(name: str, edit, *says: str) -> None:
        out = _copy(two_shards, tmp_path / name)
        edit(out)
        before = sorted(p.relative_to(out).as_posix() for p in out.rglob("*"))
        code, _, err = run_cli(["merge", str(out)], capsys)
        assert code == 2 and "Traceback" not in err, err
        for text in says:
            assert text in err, err
        assert not (out / "dataset.json").exists()
        assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*")) == before  # nothing written

    shards = lambda out: out / ".shards"  # noqa: E731
    refused("missing", lambda out: (shards(out) / "1-of-2.json").unlink(), "shard(s) 1/2 missing", "--shard 1/2")
    refused("other_split", lambda out: shutil.copyfile(shards(out) / "0-of-2.json", shards(out) / "0-of-3.json"),
            "0-of-3.json", "field 'shard'")

    def other_n(out: Path) -> None:  # a real record of a 3-way split beside the 2-way one
        build_dataset(capture3, out, shard=(2, 3))
    refused("other_n", other_n, "different splits", "of 2: 0-of-2.json, 1-of-2.json", "of 3: 2-of-3.json")
    refused("corrupt", lambda out: (shards(out) / "0-of-2.json").write_text("{not json"), "0-of-2.json",
            "not a readable shard record")

    def other_options(out: Path) -> None:
        rec = shards(out) / "1-of-2.json"
        doc = json.loads(rec.read_text())
        doc["options"]["png_level"] = 9
        rec.write_text(json.dumps(doc))
    refused("other_options", other_options, "1-of-2.json", "field 'options' differs")

    def wrong_samples(out: Path) -> None:
        rec = shards(out) / "1-of-2.json"
        doc = json.loads(rec.read_text())
        doc["samples"] = ["00002"]
        rec.write_text(json.dumps(doc))
    refused("wrong_samples", wrong_samples, "field 'samples' is not shard 1/2")
    refused("incomplete", lambda out: (out / ".done" / "00002.json").unlink(), "00002", "0-of-2.json", "not complete")
    refused("file_gone", lambda out: (out / "rgb_images" / "00001_FV.png").unlink(), "00001", "not complete")

    def changed(out: Path) -> None:
        (out / "rgb_images" / "00001_FV.png").write_bytes(b"x")
    out = _copy(two_shards, tmp_path / "changed")
    changed(out)
    with pytest.raises(DatasetError, match="00001_FV.png: its blake3 digest differs"):
        merge_shards(out, verify=True)
    code, _, err = run_cli(["merge", str(tmp_path / "nowhere")], capsys)
    assert code == 2 and "not a folder" in err


def test_markers_record_blake3_digests_and_the_merge_verifies_older_sha256_markers(two_shards, tmp_path):
    """A marker lists its files' BLAKE3 digests (field ``digest``: ``blake3``); ``verify`` checks a
    marker without that field (an older build's) by SHA-256, and refuses an unknown algorithm."""
    import hashlib

    import blake3

    out = _copy(two_shards, tmp_path / "dataset")
    marker = out / ".done" / "00001.json"
    doc = json.loads(marker.read_text())
    assert doc["digest"] == "blake3" and doc["files"]
    for rel, digest in doc["files"].items():
        assert blake3.blake3((out / rel).read_bytes()).hexdigest() == digest, rel
    old = {k: v for k, v in doc.items() if k != "digest"}
    old["files"] = {rel: hashlib.sha256((out / rel).read_bytes()).hexdigest() for rel in doc["files"]}
    marker.write_text(json.dumps(old))
    merge_shards(_copy(out, tmp_path / "older"), verify=True)  # the SHA-256 marker verifies
    (out / "rgb_images" / "00001_FV.png").write_bytes(b"x")
    with pytest.raises(DatasetError, match="00001_FV.png: its sha256 digest differs"):
        merge_shards(out, verify=True)
    marker.write_text(json.dumps(doc | {"digest": "md5"}))
    with pytest.raises(DatasetError, match=r"00001.json: field 'digest' is 'md5', not one of blake3, sha256"):
        merge_shards(out, verify=True)


def test_the_merge_refuses_a_capture_the_shards_were_not_built_from(capture3, two_shards, tmp_path):
    other = _copy(capture3, tmp_path / "other")
    doc = json.loads((other / "sensors.json").read_text())
    doc["imu"]["note"] = "another rig"
    (other / "sensors.json").write_text(json.dumps(doc))
    out = _copy(two_shards, tmp_path / "dataset")
    with pytest.raises(DatasetError, match="differs from the one the shards were built from"):
        merge_shards(out, source=other)


def test_the_slurm_job_array_chooses_the_shard(capture3, tmp_path, monkeypatch, capsys):
    def env(task, count, low=None, step=None, high=None):
        e = {"SLURM_ARRAY_TASK_ID": task, "SLURM_ARRAY_TASK_COUNT": count}
        e |= {k: v for k, v in (("SLURM_ARRAY_TASK_MIN", low), ("SLURM_ARRAY_TASK_STEP", step),
                                ("SLURM_ARRAY_TASK_MAX", high)) if v is not None}
        return e

    assert slurm_shard({}) is None and slurm_shard({"SLURM_ARRAY_TASK_ID": "3"}) is None
    assert slurm_shard(env("2", "4")) == Shard(2, 4)  # --array=0-3
    assert slurm_shard(env("1", "4", "1", "1", "4")) == Shard(0, 4)  # --array=1-4
    assert slurm_shard(env("4", "4", "1", None, "4")) == Shard(3, 4)
    assert slurm_shard(env("14", "4", "10", "2", "16")) == Shard(2, 4)  # --array=10-16:2
    for bad, says in ((env("x", "4"), "SLURM_ARRAY_TASK_ID"), (env("1", "0"), "SLURM_ARRAY_TASK_COUNT"),
                      (env("1", "-2"), "SLURM_ARRAY_TASK_COUNT"), (env("5", "4"), "not one of"),
                      (env("0", "4", "1", "1", "4"), "not one of"), (env("11", "4", "10", "2", "16"), "not one of"),
                      (env("2", "3", "1", "1", "9"), "not a range"), (env("1", "2", "1", "0"), "SLURM_ARRAY_TASK_STEP")):
        with pytest.raises(DatasetError, match=says):
            slurm_shard(bad)
    for k, v in env("2", "2", "1", "1", "2").items():  # the second task of --array=1-2: shard 1/2
        monkeypatch.setenv(k, v)
    out = tmp_path / "dataset"
    code, stdout, err = run_cli(["build", str(capture3), str(out)], capsys)
    assert code == 0, err
    assert "shard 1/2: complete" in stdout and "jaxfish merge" in stdout
    assert sorted(p.name for p in (out / ".shards").glob("*.json")) == ["1-of-2.json"]
    assert sorted(p.stem for p in (out / ".done").glob("*.json")) == ["00001"] and not (out / "dataset.json").exists()
    code, _, err = run_cli(["build", str(capture3), str(out), "--shard", "0/2"], capsys)  # --shard wins
    assert code == 0, err
    code, _, err = run_cli(["build", str(capture3), str(tmp_path / "whole"), "--shard", "all"], capsys)
    assert code == 0 and (tmp_path / "whole" / "dataset.json").is_file() and not (tmp_path / "whole" / ".shards").exists()
    monkeypatch.setenv("SLURM_ARRAY_TASK_ID", "seven")
    code, _, err = run_cli(["build", str(capture3), str(tmp_path / "bad")], capsys)
    assert code == 2 and "SLURM_ARRAY_TASK_ID='seven'" in err and "--shard I/N" in err
    assert not (tmp_path / "bad").exists()


def test_shard_locks_exclude_a_whole_run_the_same_shard_and_another_split(tmp_path):
    locks = tmp_path / ".shards"
    with shard_lock(tmp_path, locks, 0, 2, DatasetError, "build"):
        with shard_lock(tmp_path, locks, 1, 2, DatasetError, "build"):  # the other shard of the split: side by side
            with pytest.raises(DatasetError, match="another jaxfish build of shard 1/2"):
                with shard_lock(tmp_path, locks, 1, 2, DatasetError, "build"):
                    pass
            with pytest.raises(DatasetError, match="another split"):
                with shard_lock(tmp_path, locks, 0, 3, DatasetError, "build"):
                    pass
            with pytest.raises(DatasetError, match="another jaxfish build is writing"):
                with folder_lock(tmp_path, DatasetError, "build"):
                    pass
    with folder_lock(tmp_path, DatasetError, "build"):
        with pytest.raises(DatasetError, match="of the whole folder"):
            with shard_lock(tmp_path, locks, 0, 2, DatasetError, "build"):
                pass
    with shard_lock(tmp_path, locks, 0, 3, DatasetError, "build"):  # all released: another split may run now
        pass


def test_a_shard_cleans_up_only_its_own_temporaries_and_samples(capture3, two_shards, tmp_path):
    out = _copy(two_shards, tmp_path / "dataset")
    ours = [out / "rgb_images" / ".jaxfish-0badc0de-00001_FV.k2x_9aqz.part.png",
            out / ".done" / ".jaxfish-0badc0de-00001.k2x_9aqz.part.json",
            out / ".shards" / ".jaxfish-0badc0de-1-of-2.k2x_9aqz.part.json"]
    theirs = [out / "rgb_images" / ".jaxfish-0badc0de-00000_FV.k2x_9aqz.part.png",
              out / "rgb_images" / ".jaxfish-0badc0de-00002_RV_prev.k2x_9aqz.part.png",
              out / ".jaxfish-0badc0de-dataset.k2x_9aqz.part.json",
              out / ".shards" / ".jaxfish-0badc0de-0-of-2.k2x_9aqz.part.json"]
    for p in ours + theirs:
        p.write_bytes(b"")
    (out / ".done" / "00000.json").unlink()  # shard 0's sample, incomplete: shard 1 leaves it alone
    report = build_dataset(capture3, out, shard=(1, 2))
    assert report.stale_removed == len(ours) and not any(p.exists() for p in ours)
    assert all(p.exists() for p in theirs) and (out / "rgb_images" / "00000_FV.png").exists()


def test_two_shard_builds_at_once_in_two_processes_write_one_dataset(capture3, whole, tmp_path):
    out = tmp_path / "dataset"
    code = ("import sys, jax; jax.config.update('jax_enable_x64', True); "  # as tests/conftest.py: the same bytes
            "jax.config.update('jax_numpy_dtype_promotion', 'strict'); "
            "from jaxfish.cli import main; sys.argv = ['jaxfish', *sys.argv[1:]]; main()")
    procs = [subprocess.Popen([sys.executable, "-c", code, "build", str(capture3), str(out), "--shard", f"{i}/2"],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in range(2)]
    results = [(p.communicate()[1], p.returncode) for p in procs]  # no timeout: a hang is the runner's to report
    for err, rc in results:
        assert rc == 0, err[-3000:]
    assert sorted(p.name for p in (out / ".shards").glob("*.json")) == ["0-of-2.json", "1-of-2.json"]
    merge_shards(out)
    assert_same_tree(whole, out)


@pytest.mark.parametrize("count", [2, 3])
def test_synth_shards_and_a_merge_equal_one_synth(capture3, tmp_path, count):
    root = tmp_path / "capture"
    for i in range(count):
        synthesize_capture(root, demo_rig(SCALE), frames=FRAMES, seed=SEED, config=demo_config(SCALE),
                           shard=(i, count))
        assert json.loads((root / "capture.json").read_text())["frames"] == []  # listed by the merge
    assert (report := merge_shards(root)).kind == "capture" and report.shards == count
    assert_same_tree(capture3, root)


def test_synth_shard_merge_refuses_a_missing_shard_or_a_changed_frame(capture3, tmp_path):
    root = tmp_path / "capture"
    for i in range(2):
        synthesize_capture(root, demo_rig(SCALE), frames=FRAMES, seed=SEED, config=demo_config(SCALE),
                           shard=(i, 2))
    saved = (root / ".shards" / "1-of-2.json").read_bytes()
    (root / ".shards" / "1-of-2.json").unlink()
    with pytest.raises(DatasetError, match="shard"):
        merge_shards(root)
    (root / ".shards" / "1-of-2.json").write_bytes(saved)
    (root / "frames" / "000002" / "ego.json").write_text("{}")
    with pytest.raises(DatasetError, match="000002: differs from what shard 0-of-2 wrote"):
        merge_shards(root)
    with pytest.raises(CaptureError, match="shard"):
        synthesize_capture(tmp_path / "bad", demo_rig(SCALE), frames=1, config=demo_config(SCALE), shard=(1, 1))


def test_embedded_scene_shards_merge_from_the_settings_their_records_hold(tmp_path):
    from jaxfish.dataset import EmbeddedSource

    def source():
        return EmbeddedSource(demo_rig(SCALE), frames=2, seed=SEED, config=demo_config(SCALE))

    assert build_dataset(source(), tmp_path / "whole").ok
    out = tmp_path / "dataset"
    for i in range(2):
        assert build_dataset(source(), out, shard=(i, 2)).ok
    record = json.loads((out / ".shards" / "0-of-2.json").read_text())
    assert record["origin"]["embedded"]["seed"] == SEED and record["origin"]["embedded"]["frames"] == 2
    merge_shards(out)  # no source given: the scene is made again from the record
    assert_same_tree(tmp_path / "whole", out)
