"""Hostile inputs of the OCamCalib / f-theta / CARLA wide-angle lens models (issue #19, helper models-b)."""

from __future__ import annotations

import json
import os
from pathlib import Path

from .corpus import Case, edit_json

OCAM = {"model": "ocamcalib", "width": 1280.0, "height": 1024.0, "xc": 478.9, "yc": 639.8, "c": 1.0, "d": 0.0,
        "e": 0.0, **{f"a{i}": v for i, v in enumerate([-338.0, 0.0, 1.1e-3, -7.4e-7, 7.4e-10, 0.0, 0.0, 0.0])},
        **{f"invpol{i}": 0.0 for i in range(24)}}
FTHETA = {"model": "ftheta", "width": 1920.0, "height": 1280.0, "cx": 958.7, "cy": 641.3,
          "bw1": 1.9e-3, "bw2": 1e-7, "bw3": -2e-10, "bw4": 0.0, "bw5": 0.0, **{f"fw{i}": 0.0 for i in range(1, 6)},
          "max_angle": 1.7, "c": 1.0, "d": 0.0, "e": 0.0}
CARLA = {"model": "carla_wide_angle", "width": 1281.0, "height": 963.0, "camera_model": "kannala-brandt",
         "fov": 190.0, "k0": 0.083, "k1": 0.011, "k2": 0.0086, "k3": 0.00085}
KB_CENTRED = {"model": "kannala_brandt", "width": 1281.0, "height": 963.0, "fx": 300.0, "fy": 300.0, "cx": 640.0,
              "cy": 481.0, "k1": 0.03, "k2": -0.004, "k3": 0.0006, "k4": -0.00004}


def _calibration(intrinsic: dict, **changes):
    def setup(tmp: Path) -> None:
        data = {"name": "FV", "extrinsic": {"quaternion": [0, 0, 0, 1], "translation": [3.7, 0.0, 0.6]},
                "intrinsic": dict(intrinsic, **changes)}
        (tmp / "lens.json").write_text(json.dumps(data))
    return setup


def _text(name: str, content: bytes):
    def setup(tmp: Path) -> None:
        (tmp / name).write_bytes(content)
    return setup


def _fifo(tmp: Path) -> None:
    os.mkfifo(tmp / "calib_results.txt")


def _load(name: str, *args):
    def call(tmp: Path):
        from jaxfish.io import load_ocamcalib

        return load_ocamcalib(tmp / name, *args)
    return call


def _blueprint(attrs, *size):
    def call(tmp: Path):
        from jaxfish import CarlaWideAngle

        return CarlaWideAngle.from_blueprint(attrs, *size)
    return call


def _swap_model(model: str):
    def setup(tmp: Path) -> None:
        edit_json(tmp / "FV.json", lambda d: d["intrinsic"].update(model=model))
    return setup


CASES = [
    # Calibration JSON of the three models, through `jaxfish convert`.
    Case("models-b-convert-ocamcalib-positive-a0", "convert {tmp}/lens.json --to kb -o {tmp}/o.json",
         setup=_calibration(OCAM, a0=12.0), says=("intrinsic.a0", "negative"), absent=("{tmp}/o.json",)),
    Case("models-b-convert-ocamcalib-missing-invpol", "convert {tmp}/lens.json --to kb -o {tmp}/o.json",
         setup=_calibration({k: v for k, v in OCAM.items() if k != "invpol23"}), says=("intrinsic.invpol23", "missing")),
    Case("models-b-convert-ftheta-max-angle-beyond-pi", "convert {tmp}/lens.json --to kb -o {tmp}/o.json",
         setup=_calibration(FTHETA, max_angle=4.0), says=("intrinsic.max_angle",)),
    Case("models-b-convert-ftheta-negative-slope", "convert {tmp}/lens.json --to kb -o {tmp}/o.json",
         setup=_calibration(FTHETA, bw1=-0.002), says=("intrinsic.bw1",)),
    Case("models-b-convert-carla-unknown-lens", "convert {tmp}/lens.json --to kb -o {tmp}/o.json",
         setup=_calibration(CARLA, camera_model="fisheye"), says=("intrinsic.camera_model", "equisolid")),
    Case("models-b-convert-carla-lens-not-a-string", "convert {tmp}/lens.json --to kb -o {tmp}/o.json",
         setup=_calibration(CARLA, camera_model=3), says=("intrinsic.camera_model",)),
    Case("models-b-convert-carla-fov-beyond-the-lens", "convert {tmp}/lens.json --to kb -o {tmp}/o.json",
         setup=_calibration(CARLA, camera_model="orthographic", fov=200.0), says=("intrinsic.fov", "orthographic")),
    Case("models-b-convert-model-key-of-another-model", "convert {calib} --to kb -o {tmp}/o.json",
         setup=_swap_model("ftheta"), says=("intrinsic.", "missing (model ftheta)")),
    # Conversions that must work end to end (exit 0, the file written and readable).
    Case("models-b-convert-to-ocamcalib", "convert {calib} --to ocamcalib --fov image -o {tmp}/o.json", exit=0,
         stdout_says=("wrote {tmp}/o.json",), kept=("{tmp}/o.json",)),
    Case("models-b-convert-to-ftheta", "convert {calib} --to ftheta --fov image -o {tmp}/o.json", exit=0,
         stdout_says=("wrote {tmp}/o.json",), kept=("{tmp}/o.json",)),
    Case("models-b-convert-centred-kb-to-carla", "convert {tmp}/lens.json --to carla_wide_angle --fov image "
         "-o {tmp}/o.json", setup=_calibration(KB_CENTRED), exit=0, stdout_says=("wrote {tmp}/o.json",),
         kept=("{tmp}/o.json",)),
    # OCamCalib's calib_results.txt.
    Case("models-b-ocamcalib-not-utf8", call=_load("calib_results.txt"), setup=_text("calib_results.txt", b"\xff\xfe5 -3"),
         says=("calib_results.txt", "UTF-8")),
    Case("models-b-ocamcalib-huge", call=_load("calib_results.txt"),
         setup=_text("calib_results.txt", b"1 " * 600000), says=("calib_results.txt", "larger than")),
    Case("models-b-ocamcalib-empty", call=_load("calib_results.txt"), setup=_text("calib_results.txt", b""),
         says=("calib_results.txt", "field 'pol length'", "missing")),
    Case("models-b-ocamcalib-only-comments", call=_load("calib_results.txt"),
         setup=_text("calib_results.txt", b"#polynomial\n#center\n"), says=("field 'pol length'",)),
    Case("models-b-ocamcalib-huge-length", call=_load("calib_results.txt"),
         setup=_text("calib_results.txt", b"999999999 1 2 3"), says=("field 'pol length'", "1 to 64")),
    Case("models-b-ocamcalib-overflowing-number", call=_load("calib_results.txt"),
         setup=_text("calib_results.txt", b"2 -1e400 0"), says=("field 'pol[0]'", "finite")),
    Case("models-b-ocamcalib-fifo", call=_load("calib_results.txt", 10, 10), setup=_fifo,
         says=("calib_results.txt",)),
    Case("models-b-ocamcalib-directory", call=_load("sub", 10, 10), setup=lambda t: (t / "sub").mkdir(),
         says=("sub",)),
    Case("models-b-ocamcalib-missing-file", call=_load("none.txt", 10, 10), raises=FileNotFoundError,
         says=("none.txt",)),
    Case("models-b-ocamcalib-giant-image", call=_load("calib_results.txt"),
         setup=_text("calib_results.txt", b"2 -300 0\n1 300\n10 10\n1 0 0\n1e12 10\n"),
         says=("field 'image size height'",)),
    # CARLA blueprint attributes.
    Case("models-b-blueprint-not-a-mapping", call=_blueprint(["fov", "90"]), says=("blueprint attributes",)),
    Case("models-b-blueprint-nan-fov", call=_blueprint({"fov": "nan"}), says=("'fov'", "finite")),
    Case("models-b-blueprint-zero-fov", call=_blueprint({"fov": "0"}), says=("'fov'",)),
    Case("models-b-blueprint-huge-image", call=_blueprint({"image_size_x": "1e9"}), says=("CarlaWideAngle", "65536")),
    Case("models-b-blueprint-fractional-size", call=_blueprint({"image_size_y": "600.5"}), says=("'image_size_y'",)),
    Case("models-b-blueprint-size-disagrees", call=_blueprint({"image_size_x": "800"}, 640, 480),
         says=("'image_size_x'", "640")),
    Case("models-b-blueprint-kb-folding-before-fov", call=_blueprint({"camera_model": "kannala-brandt", "fov": "300",
                                                                     "k0": "-0.5", "k1": "0", "k2": "0", "k3": "0"}), says=("'fov'", "kannala-brandt")),
]
