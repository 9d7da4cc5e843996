"""``jaxfish demo``: render, build and draw contact sheets in one command (tiny scale for the test;
the same sizes as tests/dataset so the compiled functions are shared)."""

from __future__ import annotations

import json
import shutil

import numpy as np
from typer.testing import CliRunner

from jaxfish.cli import app
from jaxfish.dataset import CONTACT_COLUMNS, CONTACT_ROWS
from jaxfish.io import read_image
from tests.dataset.small_capture import small_capture_dir
from tests.hostile.corpus import run_cli


def test_demo_renders_builds_and_draws_contact_sheets(tmp_path):
    """The scene goes to the builder in memory: no capture is written."""
    out = tmp_path / "demo"
    args = ["demo", str(out), "--frames", "1", "--scale", "0.05", "--seed", "1"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert not (out / "capture").exists() and "rendered in memory" in result.output
    manifest = json.loads((out / "dataset" / "dataset.json").read_text())
    assert manifest["samples"] == ["00000"] and manifest["cameras"] == ["FV", "RV", "MVL", "MVR", "BEV"]
    sheet = read_image(out / "contact_sheets" / "00000.png")
    assert sheet.dtype == np.uint8 and sheet.shape[-1] == 3
    # 8 rows x 5 columns of 160 px high tiles (plus labels and gaps): every tile is drawn.
    assert len(CONTACT_ROWS) == 8 and [c for _, c in CONTACT_COLUMNS] == ["FV", "RV", "BEV", "MVL", "MVR"]
    assert sheet.shape[0] > 8 * 160 and sheet.shape[1] > 5 * 160
    # The RGB-at-t tile of FV is the dataset's image, resized: its mean colour matches.
    rgb = read_image(out / "dataset" / "rgb_images" / "00000_FV.png").astype(float)
    assert np.std(sheet.astype(float)) > 10 and rgb.mean() > 5
    again = CliRunner().invoke(app, args)  # resumes: nothing re-rendered or rebuilt
    assert again.exit_code == 0, again.output
    assert "0 built, 1 already complete" in again.output
    # Another seed over the demo's own output: rendered and rebuilt in place, the user's files kept.
    users = [out / "dataset" / "notes" / ".thesis.part1.tex", out / "rec.mcap"]
    for p in users:
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(p.name)
    other = CliRunner().invoke(app, args[:-1] + ["2"])
    assert other.exit_code == 0, other.output
    assert "1 built, 0 already complete" in other.output and "removed first (rebuild): 00000" in other.output
    assert all(p.read_text() == p.name for p in users)
    assert json.loads((out / "dataset" / "dataset.json").read_text())["capture"]["seed"] == 2
    assert not (out / "capture").exists()


def test_demo_write_capture_builds_the_same_dataset_from_files(tmp_path):
    """``--write-capture`` renders to OUT/capture and builds from it: the same sample bytes as the
    in-memory demo (the markers and dataset.json name their source)."""
    from tests.helpers import describe_differences, tree_bytes

    mem, disk = tmp_path / "mem", tmp_path / "disk"
    base = ["--frames", "1", "--scale", "0.05", "--seed", "1"]
    assert CliRunner().invoke(app, ["demo", str(mem), *base]).exit_code == 0
    result = CliRunner().invoke(app, ["demo", str(disk), *base, "--write-capture"])
    assert result.exit_code == 0, result.output
    assert (disk / "capture" / "capture.json").is_file()
    a, b = tree_bytes(mem / "dataset"), tree_bytes(disk / "dataset")
    assert sorted(a) == sorted(b)
    differ = sorted(k for k in a if a[k] != b[k])
    assert differ == [".done/00000.json", "dataset.json"], describe_differences(mem / "dataset", disk / "dataset", differ)
    assert tree_bytes(mem / "contact_sheets") == tree_bytes(disk / "contact_sheets")


def test_demo_never_writes_through_a_symlinked_capture(tmp_path, capsys):
    """``OUT/capture`` a link to a real capture and ``--write-capture``: refused before anything is
    rendered, the capture untouched (a demo of another seed would have rendered over it)."""
    real = tmp_path / "real"
    shutil.copytree(small_capture_dir(), real)
    before = {p: p.read_bytes() for p in real.rglob("*") if p.is_file()}
    (tmp_path / "demo").mkdir()
    (tmp_path / "demo" / "capture").symlink_to(real, target_is_directory=True)
    code, _, err = run_cli(["demo", str(tmp_path / "demo"), "--frames", "1", "--scale", "0.05", "--seed", "2",
                            "--write-capture"], capsys)
    assert code == 2 and "symbolic link" in err, err
    assert {p: p.read_bytes() for p in real.rglob("*") if p.is_file()} == before
    assert sorted(p.name for p in (tmp_path / "demo").iterdir()) == ["capture"]


def test_demo_rejects_bad_options(tmp_path):
    result = CliRunner().invoke(app, ["demo", str(tmp_path / "x"), "--scale", "3"])
    assert result.exit_code != 0 and "--scale" in result.output
