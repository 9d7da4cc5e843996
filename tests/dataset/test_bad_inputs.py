"""Bad capture input: every problem names the file and field, a failing sample leaves none of its
files behind, and problems of the whole capture stop the build before anything is written."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from jaxfish import CalibrationError
from jaxfish.dataset import DatasetError, build_dataset, remove_sample_files
from jaxfish.io import CaptureError, write_image


def _copy(capture: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "capture"
    shutil.copytree(capture, dst)
    return dst


def _edit_json(path: Path, edit) -> None:
    doc = json.loads(path.read_text())
    edit(doc)
    path.write_text(json.dumps(doc))


def _first_actor(doc):
    return next(a for a in doc["actors"] if not a.get("is_ego"))


def _wrong_size_face(cap: Path) -> None:
    write_image(cap / "frames/000000/cameras/FV/front/rgb_curr.png", np.zeros((16, 16, 4), np.uint8))


def _gray_depth(cap: Path) -> None:
    size = json.loads((cap / "capture.json").read_text())["face_size"]
    write_image(cap / "frames/000000/cameras/FV/front/depth_curr.png", np.zeros((size, size), np.uint8))


def _float_dvs(cap: Path) -> None:
    np.save(cap / "frames/000000/cameras/FV/front/dvs.npy", np.zeros((5, 4), np.float32))


def _dvs_outside(cap: Path) -> None:
    path = cap / "frames/000000/cameras/FV/front/dvs.npy"
    ev = np.load(path).copy()
    ev["x"][0] = 5000  # off a small face: corrupt, not droppable
    np.save(path, ev)


def _corrupt_lidar(cap: Path) -> None:
    (cap / "frames/000000/lidar.npy").write_bytes(b"garbage")


def _nan_height(cap: Path) -> None:
    from jaxfish.io import read_image

    path = cap / "frames/000000/bev/height_curr.exr"
    h = np.array(read_image(path), np.float32)
    h[2, 4] = np.nan
    write_image(path, h)


def _nan_radar(cap: Path) -> None:
    path = cap / "frames/000000/radar.npy"
    r = np.load(path).copy()
    r["depth"][0] = np.inf
    np.save(path, r)


# (mutation of frame 0, text the reason must hold: the file and the field)
SAMPLE_CASES = {
    "wrong_size_face": (_wrong_size_face, ["FV/front/rgb_curr.png", "16x16", "expected"]),
    "gray_depth": (_gray_depth, ["FV/front/depth_curr.png", "decode_depth"]),
    "float_dvs": (_float_dvs, ["FV/front/dvs.npy", "dtype"]),
    "dvs_outside": (_dvs_outside, ["FV/front/dvs.npy", "field 'x'", "5000"]),
    "corrupt_lidar": (_corrupt_lidar, ["lidar.npy", "not a readable .npy"]),
    "nan_ego": (lambda c: _edit_json(c / "frames/000000/ego.json",
                                     lambda d: d["transform"]["rotation"].__setitem__(1, float("nan"))),
                ["ego.json", "transform.rotation", "finite"]),
    "zero_box": (lambda c: _edit_json(c / "frames/000000/actors.json",
                                      lambda d: _first_actor(d)["bounding_box"].__setitem__("extent", [0, 0, 0])),
                 ["actors.json", "bounding_box.extent", "zero-size box"]),
    "negative_box": (lambda c: _edit_json(c / "frames/000000/actors.json",
                                          lambda d: _first_actor(d)["bounding_box"].__setitem__("extent", [-2, 1, 1])),
                     ["actors.json", "bounding_box.extent", ">= 0"]),
    "duplicate_id": (lambda c: _edit_json(c / "frames/000000/actors.json",
                                          lambda d: d["actors"][-1].__setitem__("id", d["actors"][0]["id"])),
                     ["actors.json", ".id", "appears twice"]),
    "no_actors_list": (lambda c: (c / "frames/000000/actors.json").write_text("{}"), ["actors.json", "field 'actors'"]),
    # numbers that would reach the dataset as NaN or infinity (box corners, distances, heights)
    "huge_box": (lambda c: _edit_json(c / "frames/000000/actors.json",
                                      lambda d: _first_actor(d)["bounding_box"]["extent"].__setitem__(0, 1e300)),
                 ["actors.json", "bounding_box.extent", "at most 1e+06"]),
    "huge_location": (lambda c: _edit_json(c / "frames/000000/actors.json",
                                           lambda d: _first_actor(d)["transform"]["location"].__setitem__(2, -1e308)),
                      ["actors.json", "transform.location", "at most 1e+06"]),
    "nan_height": (_nan_height, ["bev/height_curr.exr", "not finite", "(u=4, v=2)"]),
    "inf_radar": (_nan_radar, ["radar.npy", "field 'depth'", "not finite"]),
}


@pytest.mark.parametrize("case", sorted(SAMPLE_CASES))
def test_a_bad_sample_is_named_and_leaves_none_of_its_files(small_capture, tmp_path, case):
    mutate, expected = SAMPLE_CASES[case]
    cap = _copy(small_capture, tmp_path)
    mutate(cap)
    out = tmp_path / "out"
    report = build_dataset(cap, out, frames=[0])
    assert list(report.failed) == ["00000"], report.summary()
    reason = report.failed["00000"]
    for text in expected:
        assert text in reason, (text, reason)
    left = [p for p in out.rglob("00000*") if p.is_file()]
    assert not left, f"half-written sample: {left[:3]}"


def test_remove_sample_files_removes_exactly_one_sample(reference_build, tmp_path):
    out = tmp_path / "copy"
    shutil.copytree(reference_build[0], out)
    before = {p for p in out.rglob("*") if p.is_file()}
    marker = json.loads((out / ".done" / "00001.json").read_text())
    assert remove_sample_files(out, "00001") == len(marker["files"]) + 1  # its files and its marker
    after = {p for p in out.rglob("*") if p.is_file()}
    assert {p.relative_to(out).as_posix() for p in before - after} == set(marker["files"]) | {".done/00001.json"}


# Problems of the whole capture: the build stops before writing anything (CLI: exit 2).
CAPTURE_CASES = {
    "sensors_json": (lambda c: (c / "sensors.json").write_text("{"), CaptureError, ["sensors.json", "invalid JSON"]),
    "tag_table": (lambda c: _edit_json(c / "capture.json", lambda d: d.__setitem__("carla_semantic_tags", "banana")),
                  CaptureError, ["capture.json", "carla_semantic_tags"]),
    "frames_type": (lambda c: _edit_json(c / "capture.json", lambda d: d.__setitem__("frames", "0,1")),
                    CaptureError, ["capture.json", "'frames'"]),
    "unknown_camera": (lambda c: _edit_json(c / "capture.json", lambda d: d["cameras"].append("XX")),
                       CaptureError, ["capture.json", "'cameras'", "XX.json"]),
    "bev_scale": (lambda c: _edit_json(c / "sensors.json", lambda d: d["bev"].__setitem__("metres_per_pixel", 0)),
                  CaptureError, ["sensors.json", "bev.metres_per_pixel"]),
    "calibration": (lambda c: (c / "calibration/FV.json").write_text('{"extrinsic": {'), CalibrationError, ["FV.json"]),
    "dt_nan": (lambda c: _edit_json(c / "capture.json", lambda d: d.__setitem__("dt_s", float("nan"))),
               CaptureError, ["capture.json", "'dt_s'"]),
    "useless_calibration": (lambda c: _edit_json(c / "calibration/FV.json", lambda d: d["intrinsic"].__setitem__("k1", 1e300)),
                            CalibrationError, ["calibration/FV.json", "intrinsic.k1", "at most 1e+07"]),
}


@pytest.mark.parametrize("case", sorted(CAPTURE_CASES))
def test_a_bad_capture_stops_the_build_before_writing(small_capture, tmp_path, case):
    mutate, error, expected = CAPTURE_CASES[case]
    cap = _copy(small_capture, tmp_path)
    mutate(cap)
    with pytest.raises(error) as info:
        build_dataset(cap, tmp_path / "out")
    for text in expected:
        assert text in str(info.value), (text, str(info.value))
    assert not (tmp_path / "out").exists()


def test_a_bad_calibration_never_replaces_a_finished_datasets_copy(small_capture, reference_build, tmp_path):
    out = tmp_path / "done"
    shutil.copytree(reference_build[0], out)
    good = (out / "calibration_data/FV.json").read_bytes()
    cap = _copy(small_capture, tmp_path)
    (cap / "calibration/FV.json").write_text('{"extrinsic": {')
    with pytest.raises(CalibrationError):
        build_dataset(cap, out)
    assert (out / "calibration_data/FV.json").read_bytes() == good


@pytest.mark.parametrize("kwargs, message", [
    ({"workers": 0}, "workers must be an integer >= 1"),
    ({"frames": [0.5]}, "frames must be integer frame numbers, got 0.5"),
    ({"frames": ["a"]}, "frames must be integer frame numbers, got 'a'"),
    ({"scheduler": "notanaddress"}, "scheduler 'notanaddress': cannot connect"),
])
def test_bad_build_arguments_are_named(small_capture, tmp_path, kwargs, message):
    with pytest.raises(DatasetError, match=message):
        build_dataset(small_capture, tmp_path / "out", **kwargs)


def test_dataset_files_with_a_non_finite_number_write_nothing(small_capture, tmp_path):
    """The strict JSON writer is the last guard: a NaN that got past the readers (here put into the
    reader's header after it was checked) names dataset.json and the field, and no dataset-level
    file is written."""
    from jaxfish.dataset import write_dataset_files
    from jaxfish.io import CaptureReader

    reader = CaptureReader(small_capture)
    reader.meta = {**reader.meta, "dt_s": float("nan")}
    out = tmp_path / "out"
    with pytest.raises(DatasetError, match=r"dataset\.json: not written: field 'capture\.dt_s' is not a finite number"):
        write_dataset_files(reader, out)
    assert not out.exists() or not [p for p in out.rglob("*") if p.is_file()]
