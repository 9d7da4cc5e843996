"""Results on stdout, progress and diagnostics on stderr (``jaxfish convert ... > report.txt``
keeps only the report), and a resumed build's summary says how many samples it skipped."""

from __future__ import annotations

import json
import shutil

from typer.testing import CliRunner

from jaxfish.cli import app
from jaxfish.dataset import BuildReport
from tests.conftest import shared_path


def test_convert_report_on_stdout_nothing_on_stderr(tmp_path):
    src = shared_path("calibration/woodscape/FV.json")
    out, report = tmp_path / "kb.json", tmp_path / "kb_report.json"
    result = CliRunner().invoke(app, ["convert", str(src), "--to", "kb", "-o", str(out), "-r", str(report)])
    assert result.exit_code == 0, result.output
    lines = result.stdout.splitlines()
    summary = json.loads(report.read_text())
    assert lines[0].startswith("radial_poly -> kannala_brandt over the 1280x966 image") and f"rms {summary['rms_px']:.4g} px" in lines[0]
    assert lines[1] == f"wrote {out}" and len(lines) == 2  # one line each: never hard-wrapped
    assert result.stderr == ""


def test_refit_example_and_refit_results_on_stdout(tmp_path):
    corners, out = tmp_path / "corners.json", tmp_path / "fit.json"
    runner = CliRunner()
    result = runner.invoke(app, ["refit", "--example", str(corners)])  # no other argument needed
    assert result.exit_code == 0, result.output
    assert result.stdout.startswith(f"wrote {corners}: ") and result.stderr == ""
    data = json.loads(corners.read_text())
    assert data["frame"] == "board" and len(data["views"]) == 5 and data["views"][0]["name"] == "img_000"
    result = runner.invoke(app, ["refit", str(corners), "--model", "radial_poly", "--width", "1280", "--height", "966",
                                 "--out", str(out), "--fix", "aspect_ratio"])
    assert result.exit_code == 0, result.output
    assert result.stdout.startswith("refit radial_poly: rms ") and f"wrote {out}" in result.stdout
    assert "  k1 = 336" in result.stdout and result.stderr == ""
    result = runner.invoke(app, ["refit", "--example", str(tmp_path)])  # a directory: refused, nothing written
    assert result.exit_code == 2 and "is a directory" in result.stderr


def test_refit_help_says_what_defaults_from_the_calibration():
    result = CliRunner().invoke(app, ["refit", "--help"], env={"COLUMNS": "200"})
    text = " ".join(result.stdout.split())
    assert result.exit_code == 0
    assert "default: the --calibration's" in text and "--example" in text
    assert "the model, image size, start values, extrinsic, name and flavor come from that file" in text


def test_build_results_on_stdout_progress_on_stderr_resume_counts_skips(tmp_path):
    from tests.dataset.small_capture import small_capture_dir

    capture = tmp_path / "capture"
    shutil.copytree(small_capture_dir(), capture)
    runner = CliRunner()
    args = ["build", str(capture), str(tmp_path / "ds"), "--frames", "0", "--no-bev", "--write-threads", "0"]
    first = runner.invoke(app, args)
    assert first.exit_code == 0, first.output
    assert first.stdout.startswith("1 built, 0 already complete, 0 failed of 1 sample(s) in ")
    assert "samples/s)" in first.stdout and "skipped" not in first.stdout
    again = runner.invoke(app, args)
    assert again.exit_code == 0, again.output
    assert again.stdout.startswith("0 built, 1 already complete, 0 failed of 1 sample(s) in ")
    assert "(none built; 1 skipped as already complete)" in again.stdout
    assert "samples/s" not in again.stdout and "samples/s" not in again.stderr  # no "0.00 samples/s"
    assert "sample 00000 skipped (already complete)" in " ".join(again.stderr.split())


def test_build_report_summary_rate_counts_built_samples_only(tmp_path):
    r = BuildReport(tmp_path, ["00000", "00001", "00002"], built=["00002"], skipped=["00000", "00001"], seconds=2.0)
    assert "(0.50 samples/s; 2 skipped as already complete)" in r.summary()
    r = BuildReport(tmp_path, ["00000"], failed={"00000": "capture.json: bad"}, seconds=1.0)
    assert "(none built)" in r.summary() and "  sample 00000 failed: capture.json: bad" in r.summary()
