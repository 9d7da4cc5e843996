"""``jaxfish build``: exit status, summary, resume, and a failing sample named with its file."""

from __future__ import annotations

import shutil

import pytest
from typer.testing import CliRunner

from jaxfish.cli import app
from jaxfish.cli._build import parse_frames
from tests.dataset.small_capture import small_capture_dir


@pytest.fixture(scope="module")
def capture():
    return small_capture_dir()


def test_build_writes_the_dataset_and_resumes(capture, tmp_path):
    out = tmp_path / "dataset"
    result = CliRunner().invoke(app, ["build", str(capture), str(out), "--frames", "0"])
    assert result.exit_code == 0, result.output
    assert "1 built, 0 already complete, 0 failed" in result.output
    assert (out / "rgb_images" / "00000_FV.png").is_file() and (out / "dataset.json").is_file()
    assert not (out / "rgb_images" / "00001_FV.png").exists()
    again = CliRunner().invoke(app, ["build", str(capture), str(out), "--frames", "0"])
    assert again.exit_code == 0 and "0 built, 1 already complete" in again.output


def test_build_exits_1_and_names_the_broken_file(capture, tmp_path):
    broken = tmp_path / "capture"
    shutil.copytree(capture, broken)
    (broken / "frames/000001/ego.json").write_text("{not json")
    result = CliRunner().invoke(app, ["build", str(broken), str(tmp_path / "dataset")])
    assert result.exit_code == 1, result.output
    assert "1 built" in result.output and "1 failed" in result.output
    assert "sample 00001 failed" in result.output and "ego.json" in result.output


def test_build_rejects_bad_arguments(capture, tmp_path):
    r = CliRunner().invoke(app, ["build", str(tmp_path / "nope"), str(tmp_path / "out")])
    assert r.exit_code == 2 and "not found" in r.output
    r = CliRunner().invoke(app, ["build", str(capture), str(tmp_path / "out"), "--frames", "1,9"])
    assert r.exit_code == 2 and "9 not in" in r.output and "frames: 0-1" in r.output, r.output
    assert not (tmp_path / "out").exists()  # bad input writes nothing
    assert parse_frames("0,2,5-7") == [0, 2, 5, 6, 7] and parse_frames(None) is None


def test_frame_ranges_are_checked_against_the_capture_before_they_are_expanded(capsys):
    import typer

    assert parse_frames("0,2,5-7", [0, 1, 2, 5, 6, 7]) == [0, 2, 5, 6, 7]
    assert parse_frames("1,0", [0, 1]) == [1, 0] and parse_frames(None, [0, 1]) is None
    for text, says in (("0-999999999", "--frames: 2, 3, 4, 5, 6 ... not in cap/capture.json (its frames: 0-1)"),
                       ("0-" + "9" * 4000, "2, 3, 4, 5, 6 ... not in"), ("1-3", "--frames: 2, 3 not in"),
                       ("5-2", "cannot read '5-2'"), ("x", "cannot read 'x'")):
        with pytest.raises(typer.Exit) as e:
            parse_frames(text, [0, 1], source="cap/capture.json")
        assert e.value.exit_code == 2
        assert says in capsys.readouterr().err
