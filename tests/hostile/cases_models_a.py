"""Hostile calibrations of the Mei, OpenCV, FOV and Fisheye624 models (issue #19): each is refused
by ``jaxfish convert`` naming the file and the field, with nothing written."""

from __future__ import annotations

import json
from pathlib import Path

from .corpus import Case

_CAMERAS = {
    "mei": ("MeiCamera", (760.0, 765.0, 640.2, 481.7, 1.35, (-0.28, 0.07, 1.2e-3, -6e-4))),
    "opencv": ("OpenCVPinhole", (610.0, 612.0, 640.3, 483.2, (-0.05, 0.01, 1.1e-3, -6e-4, 1e-3))),
    "fov": ("FieldOfView", (300.0, 302.0, 640.2, 481.7, 1.9)),
    "fisheye624": ("Fisheye624", (330.0, 331.5, 640.2, 481.7, (0.02, -0.003, 0.001, -1e-4, 0.0, 0.0))),
}


def _calibration(model: str, edit=None, text_edit=None):
    """A setup writing ``{tmp}/c.json``: a 1280 x 966 calibration of ``model``, its ``intrinsic``
    object changed by ``edit`` (or its text by ``text_edit``)."""

    def setup(tmp: Path) -> None:
        import jax.numpy as jnp

        import jaxfish as jf
        from jaxfish.io import camera_calibration_to_dict

        cls, args = _CAMERAS[model]
        cam = getattr(jf, cls)(*args, width=1280, height=966)
        data = camera_calibration_to_dict(jf.Calibration("FV", cam, jf.Pose.identity(dtype=jnp.float64)))
        if edit is not None:
            edit(data["intrinsic"])
        text = json.dumps(data)
        (tmp / "c.json").write_text(text if text_edit is None else text_edit(text))

    return setup


_CONVERT = "convert {tmp}/c.json --to kb -o {tmp}/out.json"
_OUT = ("{tmp}/out.json",)

CASES = [
    Case("models_a-fov-w-at-pi", _CONVERT, setup=_calibration("fov", lambda i: i.update(w=3.1416)),
         says=("c.json", "intrinsic.w", "below pi"), absent=_OUT),
    Case("models_a-fov-w-negative-beyond-pi", _CONVERT, setup=_calibration("fov", lambda i: i.update(w=-7.0)),
         says=("intrinsic.w",), absent=_OUT),
    Case("models_a-mei-xi-below-minus-1", _CONVERT, setup=_calibration("mei", lambda i: i.update(xi=-1.5)),
         says=("c.json", "intrinsic.xi", "above -1"), absent=_OUT),
    Case("models_a-mei-skew-key", _CONVERT, setup=_calibration("mei", lambda i: i.update(s=0.0)),
         says=("intrinsic.s'", "unexpected key for model mei"), absent=_OUT),
    Case("models_a-opencv-missing-s4", _CONVERT, setup=_calibration("opencv", lambda i: i.pop("s4")),
         says=("intrinsic.s4", "missing"), absent=_OUT),
    Case("models_a-opencv-zero-focal", _CONVERT, setup=_calibration("opencv", lambda i: i.update(fy=0.0)),
         says=("intrinsic.fy",), absent=_OUT),
    Case("models_a-fisheye624-nan-k5", _CONVERT,
         setup=_calibration("fisheye624", text_edit=lambda t: t.replace('"k5": 0.0', '"k5": NaN')),
         says=("intrinsic.k5", "finite number"), absent=_OUT),
    Case("models_a-fisheye624-string-p0", _CONVERT, setup=_calibration("fisheye624", lambda i: i.update(p0="0.001")),
         says=("intrinsic.p0",), absent=_OUT),
    Case("models_a-convert-to-unknown-key", "convert {tmp}/c.json --to fisheye625 -o {tmp}/out.json",
         setup=_calibration("fov"), says=("--to", "fisheye625", "unknown lens model"), absent=_OUT),
    Case("models_a-opencv-distortion-of-length-3", call=lambda tmp: __import__("jaxfish").OpenCVPinhole(
        500.0, 500.0, 320.0, 240.0, (0.1, 0.2, 0.3), width=640, height=480), raises=ValueError,
        says=("distortion must have shape",)),
]
