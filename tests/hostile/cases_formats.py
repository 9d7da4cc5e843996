"""Hostile calibration files of other tools (kalibr, COLMAP, OpenCV, basalt, CARLA), ``jaxfish
export`` and ``jaxfish refit --rig`` (issue #19 items 5-6): each names the file and field, exit 2,
nothing written."""

from __future__ import annotations

import json
from pathlib import Path

from .corpus import Case

_KALIBR = """cam0:
  camera_model: pinhole
  intrinsics: [330.0, 330.0, 640.0, 480.0]
  distortion_model: equidistant
  distortion_coeffs: [0.02, 0.01, 0.0, 0.0]
  resolution: [1280, 966]
"""


_TWO = _KALIBR + _KALIBR.replace("cam0", "cam1") + "  T_cn_cnm1: [[1, 0, 0, -0.1], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]\n"


def _write(name: str, text: str):
    def setup(tmp: Path) -> None:
        (tmp / name).write_text(text)
    return setup


def _rig_corr(tmp: Path, views=None) -> None:
    """A rig correspondences file (two views of one target by cam0) and a one-camera kalibr rig."""
    pts = [[x * 0.1, y * 0.1, 0.0] for x in range(3) for y in range(3)]
    pix = [[600.0 + 10 * i, 400.0 + 7 * i] for i in range(9)]
    views = views if views is not None else [{"name": "t0", "camera": "cam0", "points": pts, "pixels": pix}]
    (tmp / "corr.json").write_text(json.dumps({"frame": "board", "views": views}))
    (tmp / "rig.yaml").write_text(_KALIBR)


def _named_calibration(tmp: Path, name: str) -> None:
    """A Kannala-Brandt calibration JSON named ``name``, and a second one so that OpenCV writes a folder."""
    intr = {"model": "kannala_brandt", "width": 1280.0, "height": 966.0, "fx": 330.0, "fy": 330.0, "cx": 640.0,
            "cy": 480.0, "k1": 0.02, "k2": 0.0, "k3": 0.0, "k4": 0.0}
    ext = {"quaternion": [0.0, 0.0, 0.0, 1.0], "translation": [0.0, 0.0, 0.0]}
    (tmp / "c.json").write_text(json.dumps({"name": name, "intrinsic": intr, "extrinsic": ext}))
    (tmp / "c2.json").write_text(json.dumps({"name": "other", "intrinsic": intr, "extrinsic": ext}))


CASES = [
    # Reading: every format's broken file names the file and field.
    Case("formats-kalibr-malformed-yaml", "convert {tmp}/c.yaml --to kb --out {tmp}/o.json",
         setup=_write("c.yaml", "cam0: [unclosed\n  intrinsics: {"), says=("c.yaml", "malformed YAML", "line"),
         absent=("{tmp}/o.json",)),
    Case("formats-kalibr-missing-intrinsics", "convert {tmp}/c.yaml --to kb --out {tmp}/o.json",
         setup=_write("c.yaml", _KALIBR.replace("  intrinsics: [330.0, 330.0, 640.0, 480.0]\n", "")),
         says=("c.yaml: field 'cam0.intrinsics': missing",), absent=("{tmp}/o.json",)),
    Case("formats-kalibr-unknown-camera-model", "convert {tmp}/c.yaml --to kb --out {tmp}/o.json",
         setup=_write("c.yaml", _KALIBR.replace("camera_model: pinhole", "camera_model: scaramuzza")),
         says=("field 'cam0.camera_model'", "scaramuzza")),
    Case("formats-kalibr-short-intrinsics", "convert {tmp}/c.yaml --to kb --out {tmp}/o.json",
         setup=_write("c.yaml", _KALIBR.replace("[330.0, 330.0, 640.0, 480.0]", "[330.0, 640.0, 480.0]")),
         says=("field 'cam0.intrinsics': expected 4 numbers, got 3",)),
    Case("formats-kalibr-string-coefficient", "convert {tmp}/c.yaml --to kb --out {tmp}/o.json",
         setup=_write("c.yaml", _KALIBR.replace("[0.02, 0.01, 0.0, 0.0]", "[0.02, abc, 0.0, 0.0]")),
         says=("field 'cam0.distortion_coeffs[1]'", "abc")),
    Case("formats-kalibr-nan-focal", "convert {tmp}/c.yaml --to kb --out {tmp}/o.json",
         setup=_write("c.yaml", _KALIBR.replace("[330.0, 330.0,", "[.nan, 330.0,")),
         says=("field 'cam0.intrinsics[0]'", "finite")),
    Case("formats-kalibr-gap-in-cameras", "convert {tmp}/c.yaml --to kb --out {tmp}/o.json",
         setup=_write("c.yaml", _KALIBR + _KALIBR.replace("cam0", "cam2")), says=("cam0..camN",)),
    Case("formats-kalibr-chain-not-rigid", "convert {tmp}/c.yaml --to kb --out {tmp}/o.json",
         setup=_write("c.yaml", _KALIBR + _KALIBR.replace("cam0", "cam1")
                      + "  T_cn_cnm1: [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]\n"),
         says=("field 'cam1.T_cn_cnm1'", "rotation")),
    Case("formats-kalibr-zero-width", "convert {tmp}/c.yaml --to kb --out {tmp}/o.json",
         setup=_write("c.yaml", _KALIBR.replace("[1280, 966]", "[0, 966]")), says=("field 'cam0.resolution[0]'",)),
    Case("formats-kalibr-negative-focal", "convert {tmp}/c.yaml --to kb --out {tmp}/o.json",
         setup=_write("c.yaml", _KALIBR.replace("[330.0, 330.0,", "[-330.0, 330.0,")),
         says=("c.yaml", "intrinsic.fx", "positive")),
    Case("formats-colmap-unknown-model", "convert {tmp}/cameras.txt --to kb --out {tmp}/o.json",
         setup=_write("cameras.txt", "1 SPHERICAL 1280 966 1 2 3\n"), says=("cameras.txt: field 'line 1.MODEL'",)),
    Case("formats-colmap-too-few-params", "convert {tmp}/cameras.txt --to kb --out {tmp}/o.json",
         setup=_write("cameras.txt", "1 OPENCV_FISHEYE 1280 966 330 330 640 480\n"),
         says=("field 'line 1.MODEL'", "8 parameters")),
    Case("formats-colmap-bad-number", "convert {tmp}/cameras.txt --to kb --out {tmp}/o.json",
         setup=_write("cameras.txt", "# c\n1 PINHOLE 1280 966 330 x 640 480\n"), says=("field 'line 2.PARAMS[1]'",)),
    Case("formats-colmap-image-of-unknown-camera", "convert {tmp} --to kb --out {tmp}/o.json",
         setup=lambda t: (_write("cameras.txt", "1 PINHOLE 1280 966 330 330 640 480\n")(t),
                          _write("images.txt", "1 1 0 0 0 0 0 0 7 a.png\n\n")(t)),
         says=("images.txt: field 'line 1.CAMERA_ID'", "camera 7")),
    Case("formats-colmap-not-utf8", "convert {tmp}/cameras.txt --to kb --out {tmp}/o.json",
         setup=lambda t: (t / "cameras.txt").write_bytes(b"\xff\xfe1 PINHOLE"), says=("cameras.txt", "UTF-8")),
    Case("formats-opencv-missing-K", "convert {tmp}/c.yml --to kb --out {tmp}/o.json",
         setup=_write("c.yml", "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\n"), says=("c.yml: field 'K': missing",)),
    Case("formats-opencv-matrix-wrong-size", "convert {tmp}/c.yml --to kb --out {tmp}/o.json",
         setup=_write("c.yml", "%YAML:1.0\n---\nK: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [1, 2]\n"),
         says=("field 'K.data': expected 9 numbers, got 2",)),
    Case("formats-opencv-skew", "convert {tmp}/c.yml --to kb --out {tmp}/o.json",
         setup=_write("c.yml", "K: [[500, 3, 320], [0, 500, 240], [0, 0, 1]]\nD: [0, 0, 0, 0]\n"
                      "distortion_model: fisheye\nimage_width: 640\nimage_height: 480\n"), says=("field 'K'", "skew")),
    Case("formats-opencv-missing-size", "convert {tmp}/c.yml --to kb --out {tmp}/o.json",
         setup=_write("c.yml", "K: [[500, 0, 320], [0, 500, 240], [0, 0, 1]]\nD: [0, 0, 0, 0]\ndistortion_model: fisheye\n"),
         says=("field 'image_width': missing",)),
    Case("formats-opencv-root-list", "convert {tmp}/c.yml --to kb --out {tmp}/o.json",
         setup=_write("c.yml", "- 1\n- 2\n"), says=("c.yml: field '<root>'",)),
    Case("formats-basalt-missing-resolution", "convert {tmp}/b.json --to kb --out {tmp}/o.json",
         setup=_write("b.json", json.dumps({"value0": {"intrinsics": [{"camera_type": "kb4", "intrinsics": {}}],
                                                      "T_imu_cam": [{}]}})),
         says=("b.json: field 'value0.resolution': missing",)),
    Case("formats-basalt-missing-parameter", "convert {tmp}/b.json --to kb --out {tmp}/o.json",
         setup=_write("b.json", json.dumps({"value0": {
             "intrinsics": [{"camera_type": "ucm", "intrinsics": {"fx": 1, "fy": 1, "cx": 1, "cy": 1}}],
             "resolution": [[640, 480]], "T_imu_cam": [{"px": 0, "py": 0, "pz": 0, "qx": 0, "qy": 0, "qz": 0, "qw": 1}]}})),
         says=("field 'value0.intrinsics[0].intrinsics.alpha': missing",)),
    Case("formats-basalt-unknown-camera-type", "convert {tmp}/b.json --to kb --out {tmp}/o.json",
         setup=_write("b.json", json.dumps({"value0": {"intrinsics": [{"camera_type": "bal", "intrinsics": {}}],
                                                      "resolution": [[640, 480]], "T_imu_cam": [{}]}})),
         says=("field 'value0.intrinsics[0].camera_type'", "bal")),
    Case("formats-carla-bad-rotation", "convert {tmp}/s.json --to kb --out {tmp}/o.json",
         setup=_write("s.json", json.dumps({"attributes": {"image_size_x": "800", "image_size_y": "600"},
                                            "transform": {"location": [0, 0, 1], "rotation": [0, "up"]}})),
         says=("s.json: field '<root>.transform.rotation'",)),
    Case("formats-carla-fov-180", "convert {tmp}/s.json --to kb --out {tmp}/o.json",
         setup=_write("s.json", json.dumps({"attributes": {"image_size_x": "800", "image_size_y": "600", "fov": "180"}})),
         says=("field '<root>.attributes.fov'",)),
    Case("formats-carla-not-a-camera", "convert {tmp}/s.json --to kb --out {tmp}/o.json",
         setup=_write("s.json", json.dumps({"blueprint": "sensor.lidar.ray_cast", "attributes": {}})),
         says=("field '<root>.blueprint'", "sensor.camera")),
    Case("formats-yaml-nested-deeply", "convert {tmp}/c.yaml --to kb --out {tmp}/o.json",
         setup=_write("c.yaml", "cam0: " + "[" * 100000 + "]" * 100000 + "\n"), says=("c.yaml", "YAML")),
    Case("formats-yaml-alias-bomb", "convert {tmp}/c.yaml --to kb --out {tmp}/o.json",
         setup=_write("c.yaml", "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
             f"{chr(98 + i)}: &{chr(98 + i)} [*{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, "
             f"*{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}]\n" for i in range(8))
             + "K: *i\n"), says=("c.yaml: field 'K[0][0]': expected a number, got list [[[...]",)),
    Case("formats-several-cameras-unnamed", "convert {tmp}/c.yaml --to kb --out {tmp}/o.json",
         setup=_write("c.yaml", _TWO), says=("holds 2 cameras", "::NAME"),
         absent=("{tmp}/o.json",)),
    Case("formats-several-cameras-named", "convert {tmp}/c.yaml::cam1 --to kb --out {tmp}/o.json",
         setup=_write("c.yaml", _TWO), exit=0, stdout_says=("wrote {tmp}/o.json",)),
    # jaxfish export
    Case("formats-export-name-escapes-folder", "export {tmp}/c.json {tmp}/c2.json --format opencv --out {tmp}/ocv",
         setup=lambda t: _named_calibration(t, "../escaped"), says=("camera name '../escaped'",),
         absent=("{tmp}/escaped.yaml", "{tmp}/ocv")),
    Case("formats-export-colmap-name-with-space", "export {tmp}/c.json --format colmap --out {tmp}/sp",
         setup=lambda t: _named_calibration(t, "front cam"), says=("camera name 'front cam'",), absent=("{tmp}/sp",)),
    Case("formats-export-unknown-format", "export {calib} --format ros --out {tmp}/o.yaml", says=("--format", "ros"),
         absent=("{tmp}/o.yaml",)),
    Case("formats-export-to-model-the-format-lacks", "export {calib} --format colmap --to ds --out {tmp}/o",
         says=("--to double_sphere", "colmap does not hold"), absent=("{tmp}/o",)),
    Case("formats-export-file-format-into-folder", "export {calib} --format kalibr --out {tmp}",
         says=("is a directory",)),
    Case("formats-export-bad-max-error", "export {calib} --format kalibr --out {tmp}/o.yaml --max-error nan",
         says=("--max-error",), absent=("{tmp}/o.yaml",)),
    Case("formats-export-broken-input", "export {tmp}/c.yaml --format colmap --out {tmp}/o",
         setup=_write("c.yaml", "cam0: {camera_model: pinhole}\n"), says=("c.yaml: field 'cam0.intrinsics': missing",),
         absent=("{tmp}/o",)),
    Case("formats-export-duplicate-names", "export {calib} {calib} --format kalibr --out {tmp}/o.yaml",
         says=("two cameras are named 'FV'",), absent=("{tmp}/o.yaml",)),
    # jaxfish refit --rig
    Case("formats-rig-view-without-camera", "refit {tmp}/corr.json --rig {tmp}/rig.yaml --out {tmp}/out",
         setup=lambda t: _rig_corr(t, [{"name": "t0", "camera": "cam0", "points": [[0, 0, 0]], "pixels": [[1, 1]]},
                                       {"name": "t0", "points": [[0, 0, 0]], "pixels": [[1, 1]]}]),
         says=("corr.json: field 'views[1].camera': missing",), absent=("{tmp}/out",)),
    Case("formats-rig-unknown-camera", "refit {tmp}/corr.json --rig {tmp}/rig.yaml --out {tmp}/out",
         setup=lambda t: _rig_corr(t, [{"name": "t0", "camera": "FV", "points": [[0, 0, 0]], "pixels": [[1, 1]]}]),
         says=("views name camera 'FV'", "cam0"), absent=("{tmp}/out",)),
    Case("formats-rig-same-view-twice", "refit {tmp}/corr.json --rig {tmp}/rig.yaml --out {tmp}/out",
         setup=lambda t: _rig_corr(t, [{"name": "t0", "camera": "cam0", "points": [[0, 0, 0]], "pixels": [[1, 1]]}] * 2),
         says=("field 'views[1]'", "twice"), absent=("{tmp}/out",)),
    Case("formats-rig-with-calibration", "refit {tmp}/corr.json --rig {tmp}/rig.yaml --calibration {tmp}/rig.yaml "
         "--out {tmp}/out", setup=_rig_corr, says=("--calibration", "not used with --rig"), absent=("{tmp}/out",)),
    Case("formats-rig-unknown-reference", "refit {tmp}/corr.json --rig {tmp}/rig.yaml --reference RV --out {tmp}/out",
         setup=_rig_corr, says=("--reference 'RV'",), absent=("{tmp}/out",)),
    Case("formats-rig-estimate-without-rig", "refit {tmp}/corr.json --estimate-mountings --out {tmp}/out",
         setup=_rig_corr, says=("--estimate-mountings need --rig",), absent=("{tmp}/out",)),
    Case("formats-rig-out-is-a-file", "refit {tmp}/corr.json --rig {tmp}/rig.yaml --out {tmp}/rig.yaml",
         setup=_rig_corr, says=("not a folder",)),
    Case("formats-rig-file-to-single-refit", "refit {tmp}/corr.json --model kb --width 640 --height 480 --out {tmp}/o.json",
         setup=_rig_corr, says=("field 'views[0].camera'", "--rig"), absent=("{tmp}/o.json",)),
    Case("formats-rig-too-few-points", "refit {tmp}/corr.json --rig {tmp}/rig.yaml --out {tmp}/out",
         setup=lambda t: _rig_corr(t, [{"name": "t0", "camera": "cam0", "points": [[0, 0, 0]], "pixels": [[1, 1]]}]),
         says=("corr.json",), absent=("{tmp}/out",)),
]
