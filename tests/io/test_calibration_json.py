"""Calibration JSON: real files of both flavours, round trips, errata, and every bad input."""

from __future__ import annotations

import json

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import jaxfish as jf
from jaxfish.io import calibration_to_dict
from tests.conftest import shared_path


def _read(path):
    with open(path) as f:
        return json.load(f)


def test_load_real_files(real_calibration_path):
    calib = jf.load_calibration(real_calibration_path)
    data = _read(real_calibration_path)
    assert calib.name == data["name"] and calib.name in jf.CAMERA_NAMES
    intr = data["intrinsic"]
    np.testing.assert_array_equal(np.asarray(calib.camera.k), [intr["k1"], intr["k2"], intr["k3"], intr["k4"]])
    assert (calib.camera.width, calib.camera.height) == (int(intr["width"]), int(intr["height"]))
    np.testing.assert_allclose(
        np.asarray(calib.camera.principal_point),
        [intr["width"] / 2 + intr["cx_offset"] - 0.5, intr["height"] / 2 + intr["cy_offset"] - 0.5],
    )
    # The quaternion is scalar-last (scipy order) and maps camera -> vehicle.
    r = Rotation.from_quat(data["extrinsic"]["quaternion"]).as_matrix()
    np.testing.assert_allclose(np.asarray(calib.camera_to_vehicle.rotation_matrix), r, atol=1e-14)
    # Read as (x, y, z, w), every camera looks below the horizon towards its own side of the car
    # (read as (w, x, y, z) they would look at the sky or sideways).
    axis = np.asarray(calib.camera_to_vehicle.rotate(jnp.asarray([0.0, 0.0, 1.0])))
    assert axis[2] < -0.3
    side = {"FV": (0, 1), "RV": (0, -1), "MVL": (1, 1), "MVR": (1, -1)}[calib.name]
    assert np.sign(axis[side[0]]) == side[1] and abs(axis[side[0]]) > 0.2


def test_woodscape_front_camera_pose():
    calib = jf.load_calibration(shared_path("calibration/woodscape/FV.json"))
    assert calib.flavor == "woodscape"
    axis = np.asarray(calib.camera_to_vehicle.rotate(jnp.asarray([0.0, 0.0, 1.0])))
    assert axis[0] > 0.9, "the front camera looks forward (ISO +x)"
    np.testing.assert_allclose(np.asarray(calib.camera_to_vehicle.translation), [3.7484, 0.0, 0.66017])


def test_synwoodscape_translation_is_converted_to_iso():
    path = shared_path("calibration/synwoodscape/MVL.json")
    raw = _read(path)["extrinsic"]["translation used in CARLA (CARLA reference)"]
    calib = jf.load_calibration(path)
    assert calib.flavor == "synwoodscape"
    np.testing.assert_allclose(np.asarray(calib.camera_to_vehicle.translation), [raw[0], -raw[1], raw[2]])


@pytest.mark.parametrize("name", jf.CAMERA_NAMES)
def test_synwoodscape_errata_option(name):
    calib = jf.load_calibration(shared_path(f"calibration/synwoodscape/{name}.json"), apply_errata=True)
    x, y, z = jf.SYNWOODSCAPE_CORRECTED_TRANSLATIONS_CARLA[name]
    np.testing.assert_allclose(np.asarray(calib.camera_to_vehicle.translation), [x, -y, z])
    if name in ("MVL", "MVR"):
        # The corrected mirror cameras sit on the side they look at.
        axis = np.asarray(calib.camera_to_vehicle.rotate(jnp.asarray([0.0, 0.0, 1.0])))
        assert np.sign(axis[1]) == np.sign(float(calib.camera_to_vehicle.translation[1]))


def test_save_load_roundtrip(real_calibration_path, tmp_path):
    calib = jf.load_calibration(real_calibration_path)
    out = jf.save_calibration(calib, tmp_path / "c.json")
    again = jf.load_calibration(out)
    assert again.flavor == calib.flavor and again.name == calib.name
    np.testing.assert_allclose(np.asarray(again.camera_to_vehicle.as_matrix()), np.asarray(calib.camera_to_vehicle.as_matrix()), atol=1e-14)
    np.testing.assert_array_equal(np.asarray(again.camera.k), np.asarray(calib.camera.k))
    assert float(again.camera.cx_offset) == float(calib.camera.cx_offset)
    # The written file has the same keys as the original.
    assert _read(out).keys() == _read(real_calibration_path).keys()
    assert _read(out)["extrinsic"].keys() == _read(real_calibration_path)["extrinsic"].keys()


def test_rig_roundtrip(tmp_path):
    rig = jf.default_rig()
    jf.save_rig(rig, tmp_path / "rig")
    again = jf.load_rig(tmp_path / "rig")
    assert list(again) == list(jf.CAMERA_NAMES)
    for name in rig:
        np.testing.assert_allclose(np.asarray(again[name].camera.k), np.asarray(rig[name].camera.k))


def _good() -> dict:
    return calibration_to_dict(jf.default_rig()["FV"])


def _write(tmp_path, data, name="bad.json"):
    p = tmp_path / name
    p.write_text(data if isinstance(data, str) else json.dumps(data))
    return p


def _mutate(path_keys, value):
    d = _good()
    obj = d
    for k in path_keys[:-1]:
        obj = obj[k]
    if value is _DELETE:
        del obj[path_keys[-1]]
    else:
        obj[path_keys[-1]] = value
    return d


_DELETE = object()

BAD_CASES = [
    (("intrinsic", "k1"), _DELETE, "intrinsic.k1", "missing"),
    (("extrinsic", "quaternion"), _DELETE, "extrinsic.quaternion", "missing"),
    (("name",), _DELETE, "name", "missing"),
    (("intrinsic", "k5"), 1.0, "intrinsic.k5", "unexpected key"),
    (("extra",), 1, "extra", "unexpected key"),
    (("intrinsic", "k2"), "abc", "intrinsic.k2", "expected a number"),
    (("intrinsic", "k3"), True, "intrinsic.k3", "expected a number"),
    (("intrinsic", "cx_offset"), float("nan"), "intrinsic.cx_offset", "finite"),
    (("intrinsic", "width"), 0.0, "intrinsic.width", "positive whole number"),
    (("intrinsic", "height"), -966.0, "intrinsic.height", "positive whole number"),
    (("intrinsic", "width"), 1280.5, "intrinsic.width", "positive whole number"),
    (("intrinsic", "width"), 1e12, "intrinsic.width", "at most 65536 pixels"),
    (("intrinsic", "height"), 65537, "intrinsic.height", "at most 65536 pixels"),
    (("intrinsic", "aspect_ratio"), 0.0, "intrinsic.aspect_ratio", "positive"),
    (("intrinsic", "k1"), -3.0, "intrinsic.k1", "must increase"),
    (("intrinsic", "k1"), 0.0, "intrinsic.k1", "must increase"),
    (("intrinsic", "model"), "kannala", "intrinsic.model", "radial_poly"),
    (("intrinsic", "poly_order"), 5, "intrinsic.poly_order", "only 4"),
    (("extrinsic", "quaternion"), [0.0, 0.0, 0.0, 2.0], "extrinsic.quaternion", "unit quaternion"),
    (("extrinsic", "quaternion"), [0.0, 0.0, 1.0], "extrinsic.quaternion", "list of 4"),
    (("extrinsic", "translation"), [1.0, 2.0], "extrinsic.translation", "list of 3"),
    (("extrinsic", "translation"), [1.0, None, 2.0], "extrinsic.translation[1]", "expected a number"),
    (("name",), "", "name", "non-empty"),
    (("intrinsic",), [1, 2], "intrinsic", "expected an object"),
    # finite numbers that make the camera useless (every pixel invalid in float32, fy = 0, ...)
    (("intrinsic", "k1"), 1e300, "intrinsic.k1", "at most 1e+07"),
    (("intrinsic", "k1"), 1e-300, "intrinsic.k1", "at least 0.001"),
    (("intrinsic", "k4"), -1e308, "intrinsic.k4", "at most 1e+07"),
    (("intrinsic", "cy_offset"), 1e20, "intrinsic.cy_offset", "at most 1e+07"),
    (("intrinsic", "aspect_ratio"), 1e-300, "intrinsic.aspect_ratio", "from 0.001 to 1000"),
    (("intrinsic", "aspect_ratio"), 1e4, "intrinsic.aspect_ratio", "from 0.001 to 1000"),
]


@pytest.mark.parametrize("keys,value,field,message", BAD_CASES, ids=[f"{c[2]}-{c[3]}" for c in BAD_CASES])
def test_bad_fields_name_file_and_field(tmp_path, keys, value, field, message):
    path = _write(tmp_path, _mutate(keys, value))
    with pytest.raises(jf.CalibrationError) as e:
        jf.load_calibration(path)
    text = str(e.value)
    assert str(path) in text and f"'{field}'" in text and message in text, text
    assert isinstance(e.value, ValueError)


def test_unreadable_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.json"):
        jf.load_calibration(tmp_path / "nope.json")
    p = _write(tmp_path, '{"name": "FV", ', "trunc.json")
    with pytest.raises(jf.CalibrationError, match=r"trunc\.json: invalid JSON at line 1"):
        jf.load_calibration(p)
    p = tmp_path / "binary.json"
    p.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(jf.CalibrationError, match="binary.json"):
        jf.load_calibration(p)
    p = _write(tmp_path, "[1, 2]", "list.json")
    with pytest.raises(jf.CalibrationError, match="list.json"):
        jf.load_calibration(p)


def test_paths_that_are_not_calibration_files(tmp_path):
    import os

    (tmp_path / "dir.json").mkdir()
    with pytest.raises(jf.CalibrationError, match=r"dir\.json: is a directory, expected a calibration file"):
        jf.load_calibration(tmp_path / "dir.json")
    os.mkfifo(tmp_path / "pipe.json")  # reading it would block forever
    with pytest.raises(jf.CalibrationError, match=r"pipe\.json: is a FIFO \(named pipe\)"):
        jf.load_calibration(tmp_path / "pipe.json")
    os.symlink(tmp_path / "b.json", tmp_path / "a.json")
    os.symlink(tmp_path / "a.json", tmp_path / "b.json")
    with pytest.raises(jf.CalibrationError, match=r"a\.json: cannot read the calibration file \(Too many levels"):
        jf.load_calibration(tmp_path / "a.json")
    with pytest.raises(FileNotFoundError, match=r"nope\.json: calibration file not found"):
        jf.load_calibration(tmp_path / "nope.json")


def test_numbers_beyond_the_float_range_name_the_field(tmp_path):
    for literal, shown in (("1" + "0" * 400, "an integer of 401 digits"), ("9" * 5000, "an integer of 5000 digits"),
                           ("1e400", "1e400")):
        text = json.dumps(_mutate(("extrinsic", "quaternion"), [0.0, 0.0, 0.0, "HUGE"])).replace('"HUGE"', literal)
        path = _write(tmp_path, text)
        with pytest.raises(jf.CalibrationError, match=r"field 'extrinsic\.quaternion\[3\]': expected a finite "
                                                      rf"number, got {shown}"):
            jf.load_calibration(path)


def test_errata_needs_a_known_name(tmp_path):
    d = _good()
    d["name"] = "SIDE"
    d["extrinsic"] = {"quaternion": d["extrinsic"]["quaternion"], "translation used in CARLA (CARLA reference)": [0, 0, 1]}
    path = _write(tmp_path, d)
    assert jf.load_calibration(path).name == "SIDE"
    with pytest.raises(jf.CalibrationError, match="'name'"):
        jf.load_calibration(path, apply_errata=True)


def test_load_rig_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="calibration directory"):
        jf.load_rig(tmp_path / "missing")
    jf.save_rig({"FV": jf.default_rig()["FV"]}, tmp_path / "rig")
    with pytest.raises(FileNotFoundError, match="MVL.json"):
        jf.load_rig(tmp_path / "rig")
    # A file whose name disagrees with its content.
    (tmp_path / "rig" / "MVL.json").write_text((tmp_path / "rig" / "FV.json").read_text())
    with pytest.raises(jf.CalibrationError, match="expected 'MVL'"):
        jf.load_rig(tmp_path / "rig", names=("FV", "MVL"))


def test_save_is_atomic(tmp_path):
    calib = jf.default_rig()["FV"]
    target = tmp_path / "out.json"
    target.write_text("previous")
    with pytest.raises(ValueError):
        jf.save_calibration(calib, target, flavor="other")
    assert target.read_text() == "previous"
    assert [p.name for p in tmp_path.iterdir()] == ["out.json"], "no temporary file left behind"
