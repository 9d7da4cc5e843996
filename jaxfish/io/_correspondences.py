"""Correspondence files and calibration JSON for every lens model (edge I/O, not jitted).

**Correspondences** (JSON)::

    {"frame": "board",                        # "board" | "vehicle" | "camera"
     "views": [{"name": "img_000",            # optional, default "view{i}"
                "points": [[x, y, z], ...],   # metres, in `frame`
                "pixels": [[u, v], ...],      # pixel-centre convention: (0, 0) = centre of the top-left pixel
                "weights": [1.0, ...]}]}      # optional, >= 0

``frame`` says what the 3D points are: ``"board"`` (each view has its own unknown board pose,
e.g. checkerboard corners), ``"vehicle"`` (one pose, the camera mounting: every view shares it),
or ``"camera"`` (points already in the OpenCV camera frame: no pose).

**Calibration of any lens model** (JSON): WoodScape's layout with the model in
``intrinsic.model``::

    {"name": "FV",
     "extrinsic": {"quaternion": [x, y, z, w], "translation": [tx, ty, tz]},   # camera -> vehicle (ISO 8855)
     "intrinsic": {"model": "kannala_brandt", "width": 1280.0, "height": 966.0,
                   "fx": ..., "fy": ..., "cx": ..., "cy": ..., "k1": ..., "k2": ..., "k3": ..., "k4": ...}}

with the parameters of `jaxfish.refit.PARAMETER_NAMES` (``cx``, ``cy`` in jaxfish's pixel-centre
convention). ``"radial_poly"`` files are exactly WoodScape's (and read by `load_calibration`).
As in WoodScape/SynWoodScape files, the extrinsic may instead hold SynWoodScape's
``"translation used in CARLA (CARLA reference)"`` (CARLA frame, y right): the calibration's
``flavor`` is then ``"synwoodscape"`` and writing it back keeps that form.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from .._errors import CalibrationError, JaxfishError
from ..calibration import Calibration
from ..cameras import WoodScapeFisheye
from ..refit import (
    MAX_CORRESPONDENCE_VALUE,
    Correspondences,
    intrinsics_from_dict,
    intrinsics_to_dict,
    intrinsics_vector,
)
from ..transforms import CARLA_TO_ISO, Pose
from ._calibration_json import (
    SYNWOODSCAPE_TRANSLATION_KEY,
    WOODSCAPE_TRANSLATION_KEY,
    calibration_from_dict,
    calibration_to_dict,
)
from ._json import read_json, write_json

CORRESPONDENCE_FRAMES: tuple[str, ...] = ("board", "vehicle", "camera")
"""Values of a correspondences file's ``frame``."""


class CorrespondenceError(JaxfishError):
    """A correspondences file is malformed (the message names the file and field)."""


def _read_json(path: Path, error: type[JaxfishError]) -> Any:
    return read_json(path, error)




def correspondence_array(value: Any, cols: int | None, source: str, field: str) -> np.ndarray:
    """A finite float64 array of ``cols``-vectors (or numbers), at most `MAX_CORRESPONDENCE_VALUE` in
    magnitude; `CorrespondenceError` naming the file and field otherwise."""
    try:
        if np.asarray(value).dtype.kind not in "iuf":  # strings ("1"), booleans, ragged lists: not numbers
            raise TypeError
        a = np.asarray(value, dtype=np.float64)
    except OverflowError:  # an integer beyond ~1.8e308
        raise CorrespondenceError(f"{source}: field '{field}': values must be finite") from None
    except (TypeError, ValueError):
        raise CorrespondenceError(f"{source}: field '{field}': expected a list of numbers") from None
    if cols is not None and (a.ndim != 2 or a.shape[1] != cols):
        raise CorrespondenceError(f"{source}: field '{field}': expected a list of {cols}-vectors, got shape {a.shape}")
    if cols is None and a.ndim != 1:
        raise CorrespondenceError(f"{source}: field '{field}': expected a list of numbers, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise CorrespondenceError(f"{source}: field '{field}': values must be finite")
    if a.size and np.abs(a).max() > MAX_CORRESPONDENCE_VALUE:
        raise CorrespondenceError(f"{source}: field '{field}': values must be at most {MAX_CORRESPONDENCE_VALUE:g} in "
                                  f"magnitude, got {np.abs(a).max():g}")
    return a


def correspondences_from_dict(data: Any, *, source: str = "<correspondences>", dtype=None
                              ) -> tuple[Correspondences, str, list[str]]:
    """Validate a parsed correspondences object; returns ``(correspondences, frame, view_names)``."""
    if not isinstance(data, dict):
        raise CorrespondenceError(f"{source}: field '<root>': expected an object")
    extra = sorted(set(data) - {"frame", "views"})
    if extra:
        raise CorrespondenceError(f"{source}: field '{extra[0]}': unexpected key (allowed: frame, views)")
    frame = data.get("frame", "board")
    if frame not in CORRESPONDENCE_FRAMES:
        raise CorrespondenceError(f"{source}: field 'frame': expected one of {CORRESPONDENCE_FRAMES}, got {frame!r}")
    views = data.get("views")
    if not isinstance(views, list) or not views:
        raise CorrespondenceError(f"{source}: field 'views': expected a non-empty list of views")
    pts, pix, wts, ids, names = [], [], [], [], []
    for i, view in enumerate(views):
        where = f"views[{i}]"
        if not isinstance(view, dict):
            raise CorrespondenceError(f"{source}: field '{where}': expected an object")
        extra = sorted(set(view) - {"name", "points", "pixels", "weights"})
        if extra == ["camera"]:
            raise CorrespondenceError(f"{source}: field '{where}.camera': views that name cameras are a rig's "
                                      "correspondences (jaxfish refit --rig, jaxfish.io.load_rig_correspondences)")
        if extra:
            raise CorrespondenceError(f"{source}: field '{where}.{extra[0]}': unexpected key")
        for key in ("points", "pixels"):
            if key not in view:
                raise CorrespondenceError(f"{source}: field '{where}.{key}': missing")
        p = correspondence_array(view["points"], 3, source, f"{where}.points")
        q = correspondence_array(view["pixels"], 2, source, f"{where}.pixels")
        if len(p) != len(q):
            raise CorrespondenceError(f"{source}: field '{where}.pixels': {len(q)} pixels for {len(p)} points")
        w = correspondence_array(view["weights"], None, source, f"{where}.weights") if "weights" in view else np.ones(len(p))
        if len(w) != len(p) or np.any(w < 0):
            raise CorrespondenceError(f"{source}: field '{where}.weights': expected {len(p)} non-negative numbers")
        name = view.get("name", f"view{i}")
        if not isinstance(name, str):
            raise CorrespondenceError(f"{source}: field '{where}.name': expected a string")
        if name in names:  # each view has a pose of its own, reported under its name
            raise CorrespondenceError(f"{source}: field '{where}.name': {name!r} names views[{names.index(name)}] "
                                      f"too; each view needs its own name")
        pts.append(p)
        pix.append(q)
        wts.append(w)
        ids.append(np.full(len(p), i, dtype=np.int32))
        names.append(name)
    corr = Correspondences(np.concatenate(pts), np.concatenate(pix), np.concatenate(ids), np.concatenate(wts),
                           n_views=len(views), dtype=dtype if dtype is not None else np.float64)
    return corr, frame, names


def load_correspondences(path: str | os.PathLike, *, dtype=None) -> tuple[Correspondences, str, list[str]]:
    """Read a correspondences JSON file (format in this module's docstring); returns
    ``(correspondences, frame, view_names)``. Malformed files raise `CorrespondenceError`
    naming the file and field."""
    path = Path(path)
    return correspondences_from_dict(_read_json(path, CorrespondenceError), source=str(path), dtype=dtype)


def correspondences_to_dict(corr: Correspondences, *, frame: str = "board", view_names=None) -> dict[str, Any]:
    """The JSON object of correspondences (inverse of `correspondences_from_dict`)."""
    if frame not in CORRESPONDENCE_FRAMES:
        raise ValueError(f"frame must be one of {CORRESPONDENCE_FRAMES}, got {frame!r}")
    view = np.asarray(corr.view)
    pts, pix, w = (np.asarray(x, dtype=np.float64) for x in (corr.points, corr.pixels, corr.weight))
    views = []
    for i in range(corr.n_views):
        m = view == i
        views.append({
            "name": view_names[i] if view_names is not None else f"view{i}",
            "points": pts[m].tolist(), "pixels": pix[m].tolist(), "weights": w[m].tolist(),
        })
    return {"frame": frame, "views": views}


def save_correspondences(corr: Correspondences, path: str | os.PathLike, *, frame: str = "board",
                         view_names=None) -> Path:
    """Write correspondences as JSON, atomically."""
    path = Path(path)
    write_json(path, correspondences_to_dict(corr, frame=frame, view_names=view_names), indent=None)
    return path


def camera_calibration_from_dict(data: Any, *, source: str = "<calibration>", dtype=None) -> Calibration:
    """A `Calibration` of any lens model from its JSON object (layout in this module's docstring).

    ``radial_poly`` objects go through WoodScape's loader (`calibration_from_dict`, including
    SynWoodScape files); the camera of other models is the model's class (`KannalaBrandt`, ...).
    """
    if not isinstance(data, dict):
        raise CalibrationError(f"{source}: field '<root>': expected an object")
    intr = data.get("intrinsic")
    if isinstance(intr, dict) and intr.get("model", "radial_poly") == "radial_poly":
        return calibration_from_dict(data, source=source, dtype=dtype)
    allowed = {"name", "intrinsic", "extrinsic"}
    for key in sorted(allowed):
        if key not in data:
            raise CalibrationError(f"{source}: field '{key}': missing")
    extra = sorted(set(data) - allowed)
    if extra:
        raise CalibrationError(f"{source}: field '{extra[0]}': unexpected key")
    name = data["name"]
    if not isinstance(name, str) or not name:
        raise CalibrationError(f"{source}: field 'name': expected a non-empty string, got {name!r}")
    try:
        camera = intrinsics_from_dict(intr, source=source, dtype=dtype)
    except CalibrationError:
        raise
    except ValueError as e:
        raise CalibrationError(str(e)) from None
    ext = data["extrinsic"]
    flavor, t_key = ("synwoodscape", SYNWOODSCAPE_TRANSLATION_KEY) if isinstance(ext, dict) and SYNWOODSCAPE_TRANSLATION_KEY in ext \
        else ("woodscape", WOODSCAPE_TRANSLATION_KEY)
    if not isinstance(ext, dict) or set(ext) != {"quaternion", t_key}:
        raise CalibrationError(f"{source}: field 'extrinsic': expected {{'quaternion': [x, y, z, w], 'translation': [x, y, z]}}"
                               f" (or SynWoodScape's {SYNWOODSCAPE_TRANSLATION_KEY!r} instead of 'translation')")
    q = np.asarray(ext["quaternion"], dtype=np.float64) if _numbers(ext["quaternion"], 4) else None
    t = np.asarray(ext[t_key], dtype=np.float64) if _numbers(ext[t_key], 3) else None
    if q is None:
        raise CalibrationError(f"{source}: field 'extrinsic.quaternion': expected 4 finite numbers (x, y, z, w)")
    if t is None:
        raise CalibrationError(f"{source}: field 'extrinsic.{t_key}': expected 3 finite numbers")
    qn = float(np.linalg.norm(q))
    if abs(qn - 1.0) > 1e-3:
        raise CalibrationError(f"{source}: field 'extrinsic.quaternion': expected a unit quaternion, norm is {qn:.6g}")
    if flavor == "synwoodscape":
        t = CARLA_TO_ISO @ t  # CARLA (y right) -> ISO 8855 (y left), as `calibration_from_dict`
    pose = Pose.from_quaternion_xyzw(q / qn, t, dtype=intrinsics_vector(camera).dtype)  # every model (not all have fx)
    return Calibration(name, camera, pose, flavor)


def _numbers(value: Any, n: int) -> bool:
    return (isinstance(value, list) and len(value) == n
            and all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in value))


def load_camera_calibration(path: str | os.PathLike, *, dtype=None) -> Calibration:
    """Read a jaxfish calibration JSON of any lens model (WoodScape ``radial_poly`` files included).
    `jaxfish.io.load_camera_calibration` also reads other tools' files."""
    path = Path(path)
    return camera_calibration_from_dict(_read_json(path, CalibrationError), source=str(path), dtype=dtype)


def camera_calibration_to_dict(calib: Calibration) -> dict[str, Any]:
    """The JSON object of a calibration of any lens model, in the calibration's flavor: a
    ``radial_poly`` camera gives exactly `calibration_to_dict`'s WoodScape object; other models
    write the extrinsic as it does (WoodScape: ISO 8855 ``"translation"``; SynWoodScape: the CARLA
    frame translation under SynWoodScape's key), so a conversion keeps the file's vehicle frame."""
    if isinstance(calib.camera, WoodScapeFisheye):
        return calibration_to_dict(calib)
    q = np.asarray(calib.camera_to_vehicle.as_quaternion_xyzw(), dtype=float)
    t = np.asarray(calib.camera_to_vehicle.translation, dtype=float)
    if q.ndim != 1 or t.ndim != 1:
        raise ValueError("camera_calibration_to_dict: expected a single (unbatched) calibration")
    t_key = WOODSCAPE_TRANSLATION_KEY
    if calib.flavor == "synwoodscape":
        t, t_key = CARLA_TO_ISO @ t, SYNWOODSCAPE_TRANSLATION_KEY
    return {
        "extrinsic": {"quaternion": [float(x) for x in q], t_key: [float(x) for x in t]},
        "intrinsic": intrinsics_to_dict(calib.camera),
        "name": calib.name,
    }


def save_camera_calibration(calib: Calibration, path: str | os.PathLike) -> Path:
    """Write a calibration of any lens model as JSON, atomically."""
    path = Path(path)
    write_json(path, camera_calibration_to_dict(calib), indent=2, error=CalibrationError)
    return path
