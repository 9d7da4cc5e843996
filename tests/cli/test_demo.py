"""``jaxfish demo``: render, build and draw contact sheets in one command (tiny scale for the test;
the same sizes as tests/dataset so the compiled functions are shared)."""

from __future__ import annotations

import json

import numpy as np
from typer.testing import CliRunner

from jaxfish.cli import app
from jaxfish.dataset import CONTACT_COLUMNS, CONTACT_ROWS
from jaxfish.io import read_image


def test_demo_renders_builds_and_draws_contact_sheets(tmp_path):
    out = tmp_path / "demo"
    args = ["demo", str(out), "--frames", "1", "--scale", "0.05", "--seed", "1"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert (out / "capture" / "capture.json").is_file()
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


def test_demo_rejects_bad_options(tmp_path):
    result = CliRunner().invoke(app, ["demo", str(tmp_path / "x"), "--scale", "3"])
    assert result.exit_code != 0 and "--scale" in result.output
