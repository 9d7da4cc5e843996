"""The dataset folder describes what is in it and holds only what jaxfish wrote there: a resume with
another capture or other options is refused (or rebuilt on request), the user's files survive a
build, a folder that is not a jaxfish dataset is refused, and two builds never share a folder."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from jaxfish.dataset import (
    LAYOUT_VERSION,
    BuildOptions,
    DatasetError,
    build_dataset,
    capture_fingerprint,
    frame_fingerprint,
)
from jaxfish.io import CaptureReader
from tests.io.test_folder import STALE, USER_FILES, hold_lock, release

SAMPLES = ["00000", "00001"]


def _tree(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def test_markers_and_dataset_json_record_the_capture_fingerprint_and_the_options(small_capture, reference_build):
    out = reference_build[0]
    reader = CaptureReader(small_capture)
    capture = capture_fingerprint(reader)
    assert sorted(capture) == ["calibration/FV.json", "calibration/MVL.json", "calibration/MVR.json",
                               "calibration/RV.json", "capture.json", "sensors.json"]
    manifest = json.loads((out / "dataset.json").read_text())
    assert manifest["source"] == capture and manifest["options"] == BuildOptions().to_dict()
    for frame, sid in enumerate(SAMPLES):
        marker = json.loads((out / ".done" / f"{sid}.json").read_text())
        assert marker["options"] == BuildOptions().to_dict() and marker["layout_version"] == LAYOUT_VERSION
        assert marker["source"] == {**capture, f"frames/{frame:06d}": frame_fingerprint(small_capture, frame)}
    assert frame_fingerprint(small_capture, 0) != frame_fingerprint(small_capture, 1)


def test_a_resume_with_other_options_is_refused_until_rebuild(small_capture, reference_build, tmp_path):
    out = _copy(reference_build[0], tmp_path / "dataset")
    before = _tree(out)
    other = BuildOptions(backward_flow=True, png_level=9, motion_threshold_m=5.0)
    with pytest.raises(DatasetError) as info:
        build_dataset(small_capture, out, options=other)
    message = str(info.value)
    for text in (str(out), "00000, 00001", "option backward_flow is False there, True in this build",
                 "option motion_threshold_m is 0.5 there, 5.0 in this build", "option png_level is 1 there, 9",
                 "--rebuild", "rebuild=True"):
        assert text in message, (text, message)
    assert "bev" not in message.split("(", 1)[1].split(")")[0]  # only what differs is named
    assert _tree(out) == before  # refused before writing anything
    with pytest.raises(DatasetError, match="option bev is True there, False"):
        build_dataset(small_capture, out, options=BuildOptions(bev=False), frames=[0])
    # Options that do not change the bytes are not compared.
    report = build_dataset(small_capture, out, options=BuildOptions(write_threads=0, batch_frames=2))
    assert report.skipped == SAMPLES and _tree(out) == before

    report = build_dataset(small_capture, out, options=BuildOptions(png_level=9), frames=[0], rebuild=True)
    assert report.ok and report.replaced == SAMPLES and report.built == ["00000"]
    assert "removed first (rebuild): 00000, 00001" in report.summary()
    manifest = json.loads((out / "dataset.json").read_text())
    assert manifest["samples"] == ["00000"] and manifest["options"]["png_level"] == 9
    assert not list(out.rglob("00001*"))  # the sample made with other options is gone
    marker = json.loads((out / ".done" / "00000.json").read_text())
    assert marker["options"]["png_level"] == 9
    ref = reference_build[0]
    for rel in marker["files"]:
        if not rel.endswith(".png"):
            assert (out / rel).read_bytes() == (ref / rel).read_bytes(), rel
    again = build_dataset(small_capture, out, options=BuildOptions(png_level=9), frames=[0])
    assert again.skipped == ["00000"] and not again.replaced


def test_a_resume_from_another_capture_is_refused_naming_what_differs(small_capture, reference_build, tmp_path):
    out = _copy(reference_build[0], tmp_path / "dataset")
    before = _tree(out)
    reseeded = _copy(small_capture, tmp_path / "reseeded")  # as if rendered with another seed
    header = json.loads((reseeded / "capture.json").read_text())
    header["seed"] = 2
    (reseeded / "capture.json").write_text(json.dumps(header))
    with pytest.raises(DatasetError, match=r"capture.s capture.json differs"):
        build_dataset(reseeded, out, frames=[0])
    moved = _copy(small_capture, tmp_path / "moved")  # one frame's content differs
    ego = json.loads((moved / "frames/000001/ego.json").read_text())
    ego["transform"]["location"][0] += 1.0
    (moved / "frames/000001/ego.json").write_text(json.dumps(ego))
    with pytest.raises(DatasetError) as info:
        build_dataset(moved, out, frames=[0])
    assert "frames/000001 differs" in str(info.value) and "capture.json" not in str(info.value)
    assert "sample(s) 00001 were made" in str(info.value)
    recalibrated = _copy(small_capture, tmp_path / "recalibrated")
    calib = json.loads((recalibrated / "calibration/MVL.json").read_text())
    calib["intrinsic"]["cx_offset"] = float(calib["intrinsic"]["cx_offset"]) + 0.5
    (recalibrated / "calibration/MVL.json").write_text(json.dumps(calib))
    with pytest.raises(DatasetError, match="calibration/MVL.json differs"):
        build_dataset(recalibrated, out)
    assert _tree(out) == before
    # The same capture elsewhere (a copy, its files' times changed) is the same capture.
    report = build_dataset(_copy(small_capture, tmp_path / "copy"), out)
    assert report.skipped == SAMPLES and _tree(out) == before


def test_a_marker_without_fingerprint_is_refused_until_rebuild(small_capture, reference_build, tmp_path):
    out = _copy(reference_build[0], tmp_path / "dataset")
    marker = out / ".done" / "00001.json"
    doc = json.loads(marker.read_text())
    del doc["source"], doc["options"]
    marker.write_text(json.dumps(doc))
    with pytest.raises(DatasetError, match="records no capture fingerprint"):
        build_dataset(small_capture, out, frames=[0])


def test_a_build_keeps_the_users_files_and_removes_only_its_own_temporaries(small_capture, reference_build, tmp_path):
    out = _copy(reference_build[0], tmp_path / "dataset")
    for rel in USER_FILES:
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        (out / rel).write_text(rel)
    for rel in (STALE, f"rgb_images/{STALE}"):  # what a killed build leaves
        (out / rel).write_bytes(b"half")
    report = build_dataset(small_capture, out)
    assert report.ok and report.skipped == SAMPLES and report.stale_removed == 2
    assert not (out / STALE).exists() and not (out / "rgb_images" / STALE).exists()
    for rel in USER_FILES:
        assert (out / rel).read_text() == rel, rel


def test_a_folder_that_is_not_a_jaxfish_dataset_is_refused(small_capture, tmp_path):
    out = tmp_path / "recordings"
    out.mkdir()
    (out / "rec.mcap").write_bytes(b"a recording")
    with pytest.raises(DatasetError, match="not empty and not a jaxfish dataset .it holds rec.mcap"):
        build_dataset(small_capture, out)
    assert [p.name for p in out.iterdir()] == ["rec.mcap"]
    (tmp_path / "file").write_text("x")
    with pytest.raises(DatasetError, match="not a folder"):
        build_dataset(small_capture, tmp_path / "file")
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "dataset.json").write_text(json.dumps({"format": "someone-elses"}))
    with pytest.raises(DatasetError, match="no dataset.json"):
        build_dataset(small_capture, foreign)
    assert [p.name for p in foreign.iterdir()] == ["dataset.json"]


def test_a_second_build_of_a_folder_is_refused_while_the_first_runs(small_capture, reference_build, tmp_path):
    out = _copy(reference_build[0], tmp_path / "dataset")
    before = _tree(out)
    (out / STALE).write_bytes(b"a live build's temporary")  # while another build runs, its files stay
    proc = hold_lock(out)  # another build: another process holds the folder
    try:
        with pytest.raises(DatasetError, match="another jaxfish build is writing into this folder"):
            build_dataset(small_capture, out)
        assert (out / STALE).exists()
    finally:
        release(proc)
    report = build_dataset(small_capture, out)
    assert report.ok and report.skipped == SAMPLES and report.stale_removed == 1 and _tree(out) == before


def test_dataset_files_without_the_bev_describe_no_bev_camera(small_capture, reference_build, tmp_path):
    """A folder rebuilt with ``bev=False`` keeps no ``calibration_data/BEV.json`` of its former build."""
    from jaxfish.dataset import write_dataset_files

    out = _copy(reference_build[0], tmp_path / "dataset")
    assert (out / "calibration_data" / "BEV.json").is_file()
    write_dataset_files(CaptureReader(small_capture), out, BuildOptions(bev=False))
    assert not (out / "calibration_data" / "BEV.json").exists()
    assert json.loads((out / "dataset.json").read_text())["conventions"]["bev"] is None
