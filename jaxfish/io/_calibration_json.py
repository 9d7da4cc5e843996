"""Read and write WoodScape / SynWoodScape calibration JSON files (edge I/O, not jitted)."""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from .._errors import CalibrationError
from ..calibration import (
    CAMERA_NAMES,
    SYNWOODSCAPE_CORRECTED_TRANSLATIONS_CARLA,
    Calibration,
)
from ..cameras import MAX_IMAGE_SIDE, WoodScapeFisheye
from ..refit._parameters import intrinsic_range_problem
from ..transforms import CARLA_TO_ISO, Pose
from ._json import read_json, regular_file, write_json

WOODSCAPE_TRANSLATION_KEY = "translation"
"""The ``extrinsic`` key of a WoodScape calibration's translation (ISO 8855 vehicle frame, metres)."""
SYNWOODSCAPE_TRANSLATION_KEY = "translation used in CARLA (CARLA reference)"
"""The ``extrinsic`` key of a SynWoodScape calibration's translation (CARLA frame, metres)."""
_INTRINSIC_NUMBERS = ("aspect_ratio", "cx_offset", "cy_offset", "height", "k1", "k2", "k3", "k4", "width")
_INTRINSIC_KEYS = frozenset(_INTRINSIC_NUMBERS + ("model", "poly_order"))
_QUATERNION_NORM_TOLERANCE = 1e-3


def _fail(source: str, field: str, message: str) -> CalibrationError:
    return CalibrationError(f"{source}: field '{field}': {message}")


def _number(value: Any, source: str, field: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _fail(source, field, f"expected a number, got {type(value).__name__} {value!r}")
    try:
        number = float(value)  # an integer beyond ~1.8e308 has no float
    except OverflowError:
        number = math.inf
    if not math.isfinite(number):
        text = repr(value) if isinstance(value, float) or len(str(value)) < 40 else f"an integer of {len(str(value))} digits"
        raise _fail(source, field, f"expected a finite number, got {text}")
    return number


def _vector(value: Any, n: int, source: str, field: str) -> np.ndarray:
    if not isinstance(value, (list, tuple)) or len(value) != n:
        raise _fail(source, field, f"expected a list of {n} numbers, got {value!r}")
    return np.array([_number(x, source, f"{field}[{i}]") for i, x in enumerate(value)])


def _mapping(value: Any, source: str, field: str) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise _fail(source, field, f"expected an object, got {type(value).__name__}")
    return value


def _check_keys(obj: Mapping[str, Any], required: set[str], allowed: set[str], source: str, where: str) -> None:
    missing = sorted(required - set(obj))
    if missing:
        name = f"{where}.{missing[0]}" if where else missing[0]
        raise _fail(source, name, "missing")
    extra = sorted(set(obj) - allowed)
    if extra:
        name = f"{where}.{extra[0]}" if where else extra[0]
        raise _fail(source, name, f"unexpected key (allowed: {', '.join(sorted(allowed))})")


def calibration_from_dict(
    data: Any, *, source: str = "<calibration>", apply_errata: bool = False, dtype=None
) -> Calibration:
    """Validate and convert a parsed WoodScape/SynWoodScape calibration JSON object.

    Every problem raises `CalibrationError` naming ``source`` and the field. See
    `load_calibration` for the meaning of ``apply_errata``.
    """
    data = _mapping(data, source, "<root>")
    _check_keys(data, {"extrinsic", "intrinsic", "name"}, {"extrinsic", "intrinsic", "name"}, source, "")
    name = data["name"]
    if not isinstance(name, str) or not name:
        raise _fail(source, "name", f"expected a non-empty string, got {name!r}")

    ext = _mapping(data["extrinsic"], source, "extrinsic")
    if SYNWOODSCAPE_TRANSLATION_KEY in ext:
        flavor, t_key = "synwoodscape", SYNWOODSCAPE_TRANSLATION_KEY
    else:
        flavor, t_key = "woodscape", WOODSCAPE_TRANSLATION_KEY
    _check_keys(ext, {"quaternion", t_key}, {"quaternion", t_key}, source, "extrinsic")
    q = _vector(ext["quaternion"], 4, source, "extrinsic.quaternion")
    qn = float(np.linalg.norm(q))
    if abs(qn - 1.0) > _QUATERNION_NORM_TOLERANCE:
        raise _fail(source, "extrinsic.quaternion", f"expected a unit quaternion (x, y, z, w), norm is {qn:.6g}")
    t = _vector(ext[t_key], 3, source, f"extrinsic.{t_key}")
    if flavor == "synwoodscape":
        if apply_errata:
            if name not in SYNWOODSCAPE_CORRECTED_TRANSLATIONS_CARLA:
                raise _fail(source, "name", f"apply_errata needs one of {CAMERA_NAMES}, got {name!r}")
            t = np.asarray(SYNWOODSCAPE_CORRECTED_TRANSLATIONS_CARLA[name], dtype=float)
        t = CARLA_TO_ISO @ t  # CARLA (y right) -> ISO 8855 (y left)

    intr = _mapping(data["intrinsic"], source, "intrinsic")
    if intr.get("model", "radial_poly") != "radial_poly":  # before the key check: another model's keys differ
        raise _fail(source, "intrinsic.model", f"only 'radial_poly' is supported, got {intr['model']!r} "
                    "(jaxfish.io.load_camera_calibration reads every lens model)")
    _check_keys(intr, set(_INTRINSIC_KEYS), set(_INTRINSIC_KEYS), source, "intrinsic")
    if _number(intr["poly_order"], source, "intrinsic.poly_order") != 4:
        raise _fail(source, "intrinsic.poly_order", f"only 4 is supported, got {intr['poly_order']!r}")
    vals = {key: _number(intr[key], source, f"intrinsic.{key}") for key in _INTRINSIC_NUMBERS}
    for key in ("width", "height"):
        if vals[key] <= 0 or vals[key] != int(vals[key]):
            raise _fail(source, f"intrinsic.{key}", f"expected a positive whole number of pixels, got {intr[key]!r}")
        if vals[key] > MAX_IMAGE_SIDE:
            raise _fail(source, f"intrinsic.{key}", f"expected at most {MAX_IMAGE_SIDE} pixels, got {intr[key]!r}")
    if vals["aspect_ratio"] <= 0:
        raise _fail(source, "intrinsic.aspect_ratio", f"expected a positive number, got {intr['aspect_ratio']!r}")
    if vals["k1"] <= 0:
        raise _fail(
            source, "intrinsic.k1",
            f"rho(theta) must increase at theta = 0 (k1 > 0 pixels/radian), got {intr['k1']!r}",
        )
    for key in _INTRINSIC_NUMBERS:
        problem = intrinsic_range_problem("radial_poly", key, vals[key])
        if problem is not None:
            raise _fail(source, f"intrinsic.{key}", problem)
    cam = WoodScapeFisheye(
        np.array([vals["k1"], vals["k2"], vals["k3"], vals["k4"]]),
        width=int(vals["width"]), height=int(vals["height"]),
        cx_offset=vals["cx_offset"], cy_offset=vals["cy_offset"], aspect_ratio=vals["aspect_ratio"],
        dtype=dtype,
    )
    pose = Pose.from_quaternion_xyzw(q / qn, t, dtype=cam.k.dtype)
    return Calibration(name, cam, pose, flavor)


def load_calibration(path: str | os.PathLike, *, apply_errata: bool = False, dtype=None) -> Calibration:
    """Load a WoodScape or SynWoodScape calibration JSON file.

    - WoodScape files (key ``"translation"``) are in the ISO 8855 vehicle frame.
    - SynWoodScape files (key ``"translation used in CARLA (CARLA reference)"``) store the
      translation in CARLA's frame (y right); it is converted to ISO 8855 (y flipped) so that
      `Calibration.camera_to_vehicle` is consistent; the quaternion is used as is.
    - ``apply_errata=True`` (SynWoodScape files only) replaces the published translation with the
      dataset author's correction (`SYNWOODSCAPE_CORRECTED_TRANSLATIONS_CARLA`, WoodScape issue
      #113): the published MVL/MVR translations are wrong. Other fixes: `eqx.tree_at` on the result.

    Raises `FileNotFoundError` for a missing file and `CalibrationError` (a `ValueError`) naming
    the file and field for anything malformed, and naming the path when it is not a regular file
    (a directory, a FIFO, a symbolic link loop).
    """
    path = regular_file(path, CalibrationError, "calibration file")
    data = read_json(path, CalibrationError)
    return calibration_from_dict(data, source=str(path), apply_errata=apply_errata, dtype=dtype)


def calibration_to_dict(calib: Calibration, *, flavor: str | None = None) -> dict[str, Any]:
    """The WoodScape JSON object of a calibration. ``flavor`` (default: the calibration's own)
    ``"synwoodscape"`` writes the translation in CARLA's frame under SynWoodScape's key."""
    flavor = flavor or calib.flavor
    if flavor not in ("woodscape", "synwoodscape"):
        raise ValueError(f"flavor must be 'woodscape' or 'synwoodscape', got {flavor!r}")
    cam = calib.camera
    q = np.asarray(calib.camera_to_vehicle.as_quaternion_xyzw(), dtype=float)
    t = np.asarray(calib.camera_to_vehicle.translation, dtype=float)
    if q.ndim != 1 or t.ndim != 1:
        raise ValueError("calibration_to_dict: expected a single (unbatched) calibration")
    if flavor == "synwoodscape":
        t = CARLA_TO_ISO @ t
    k = [float(x) for x in np.asarray(cam.k)]
    return {
        "extrinsic": {
            "quaternion": [float(x) for x in q],
            (SYNWOODSCAPE_TRANSLATION_KEY if flavor == "synwoodscape" else WOODSCAPE_TRANSLATION_KEY): [float(x) for x in t],
        },
        "intrinsic": {
            "aspect_ratio": float(cam.aspect_ratio),
            "cx_offset": float(cam.cx_offset),
            "cy_offset": float(cam.cy_offset),
            "height": float(cam.height),
            "k1": k[0], "k2": k[1], "k3": k[2], "k4": k[3],
            "model": "radial_poly",
            "poly_order": 4,
            "width": float(cam.width),
        },
        "name": calib.name,
    }


def save_calibration(calib: Calibration, path: str | os.PathLike, *, flavor: str | None = None) -> Path:
    """Write a calibration as WoodScape JSON, atomically (a temporary file renamed into place)."""
    path = Path(path)
    write_json(path, calibration_to_dict(calib, flavor=flavor), indent=2, error=CalibrationError)
    return path


def load_rig(directory: str | os.PathLike, *, names=CAMERA_NAMES, apply_errata: bool = False, dtype=None) -> dict[str, Calibration]:
    """Load ``{name}.json`` for every camera name from a directory (e.g. SynWoodScape's
    ``calibration_data/``); a missing file raises `FileNotFoundError` naming it."""
    directory = Path(directory)
    if not directory.is_dir():
        raise FileNotFoundError(f"{directory}: calibration directory not found")
    rig = {}
    for name in names:
        calib = load_calibration(directory / f"{name}.json", apply_errata=apply_errata, dtype=dtype)
        if calib.name != name:
            raise CalibrationError(f"{directory / (name + '.json')}: field 'name': expected {name!r}, got {calib.name!r}")
        rig[name] = calib
    return rig


def save_rig(rig: Mapping[str, Calibration], directory: str | os.PathLike, *, flavor: str | None = None) -> list[Path]:
    """Write ``{name}.json`` for every calibration of a rig."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    return [save_calibration(c, directory / f"{name}.json", flavor=flavor) for name, c in rig.items()]
