"""OpenCV FileStorage YAML (``cv::FileStorage`` / ``cv2.FileStorage``): the intrinsic matrix
``K`` (or ``camera_matrix``), distortion ``D`` (or ``distortion_coefficients``), ``xi`` for
``cv2.omnidir``, the image size (``image_width``/``image_height`` or ``image_size: [W, H]``),
and optionally the pose (``R``/``rvec`` and ``T``/``tvec``: vehicle -> camera, as
``cv2.calibrateCamera``'s board poses and ``cv2.stereoCalibrate``'s second camera) and
``distortion_model``. OpenCV's principal point is in jaxfish's pixel-centre convention.

The model: ``xi`` present -> ``cv2.omnidir`` (Mei); ``distortion_model``
``fisheye``/``equidistant`` -> ``cv2.fisheye`` (Kannala-Brandt, 4 coefficients);
``pinhole``/``none`` -> an ideal pinhole (every coefficient 0);
``plumb_bob``/``radtan``/``rational_polynomial``/``thin_prism`` or 5, 8, 12, 14 coefficients ->
``cv2.projectPoints``' model (k1, k2, p1, p2[, k3[, k4, k5, k6[, s1..s4[, τx, τy]]]]). Four
coefficients without ``distortion_model`` are ambiguous (cv2.fisheye's k1..k4 or cv2's k1, k2,
p1, p2) and refused. One camera per file: a rig is written as one ``NAME.yaml`` per camera.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from ._common import (
    CameraRecord,
    ModelMapping,
    fail,
    find_reader,
    find_writer,
    number,
    numbers,
    rigid_inverse,
    rodrigues,
    short,
    whole,
)

_P = ("fx", "fy", "cx", "cy")
_OPENCV_D = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4")
OPENCV_MODELS: tuple[ModelMapping, ...] = (
    ModelMapping("fisheye", "kannala_brandt", (*_P, "k1", "k2", "k3", "k4")),
    ModelMapping("omnidir", "mei", (*_P, "xi", "k1", "k2", "p1", "p2")),
    ModelMapping("opencv", "opencv", (*_P, *_OPENCV_D)),
    ModelMapping("pinhole", "pinhole", _P),
    ModelMapping("opencv", "pinhole", _P),
)
"""OpenCV model <-> jaxfish model (``K``'s fx, fy, cx, cy, then ``xi`` and the coefficients of
``D``, padded with zeros to the longest form). The first row of a jaxfish model is written."""

_DISTORTION_MODELS = {"fisheye": "fisheye", "equidistant": "fisheye", "kannala_brandt": "fisheye",
                      "omnidir": "omnidir", "mei": "omnidir",
                      "plumb_bob": "opencv", "radtan": "opencv", "rational_polynomial": "opencv",
                      "thin_prism": "opencv", "opencv": "opencv", "pinhole": "pinhole", "none": "pinhole"}


def _matrix(value: Any, source: str, field: str) -> np.ndarray:
    """An ``!!opencv-matrix`` (parsed to a mapping with rows, cols, data) or a plain list."""
    if isinstance(value, dict):
        for key in ("rows", "cols", "data"):
            if key not in value:
                raise fail(source, f"{field}.{key}", "missing")
        rows, cols = whole(value["rows"], source, f"{field}.rows"), whole(value["cols"], source, f"{field}.cols")
        data = numbers(value["data"], source, f"{field}.data", rows * cols)
        return np.asarray(data, dtype=np.float64).reshape(rows, cols)
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return np.asarray([[number(value, source, field)]])
    if isinstance(value, list) and value and all(isinstance(r, list) for r in value):
        rows = [numbers(r, source, f"{field}[{i}]") for i, r in enumerate(value)]
        if len({len(r) for r in rows}) != 1:
            raise fail(source, field, "rows of different lengths")
        return np.asarray(rows, dtype=np.float64)
    return np.asarray([numbers(value, source, field)], dtype=np.float64)


def _first(data: dict, keys: tuple[str, ...]) -> tuple[str, Any] | tuple[None, None]:
    for k in keys:
        if k in data:
            return k, data[k]
    return None, None


def read(data: Any, source: str, name: str) -> list[CameraRecord]:
    """The camera of a parsed FileStorage YAML."""
    if not isinstance(data, dict):
        raise fail(source, "<root>", f"expected a mapping, got {type(data).__name__}")
    k_key, k_val = _first(data, ("K", "camera_matrix", "cameraMatrix", "M"))
    if k_key is None:
        raise fail(source, "K", "missing (the intrinsic matrix: K or camera_matrix)")
    k = _matrix(k_val, source, k_key)
    if k.shape != (3, 3):
        raise fail(source, k_key, f"expected a 3x3 matrix, got {k.shape[0]}x{k.shape[1]}")
    if k[1, 0] != 0 or k[2, 0] != 0 or k[2, 1] != 0 or k[2, 2] != 1:
        raise fail(source, k_key, f"expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {k.tolist()}")
    if k[0, 1] != 0:
        raise fail(source, k_key, f"skew s = {k[0, 1]!r}: jaxfish's models have no skew (only s = 0 is read)")
    d_key, d_val = _first(data, ("D", "distortion_coefficients", "dist_coeffs", "distCoeffs"))
    d = _matrix(d_val, source, d_key).ravel() if d_key is not None else np.zeros(0)
    xi_key, xi_val = _first(data, ("xi", "Xi"))
    dm = data.get("distortion_model")
    if xi_key is not None:
        tool = "omnidir"
    elif dm is not None:
        if not isinstance(dm, str) or dm.lower() not in _DISTORTION_MODELS:
            raise fail(source, "distortion_model", f"expected one of {', '.join(_DISTORTION_MODELS)}, got {short(dm)}")
        tool = _DISTORTION_MODELS[dm.lower()]
    elif len(d) == 4:
        raise fail(source, "distortion_model", f"missing: {d_key} has 4 coefficients, which are cv2.fisheye's "
                   "k1..k4 or cv2's k1, k2, p1, p2; say which with distortion_model: fisheye or plumb_bob")
    else:
        tool = "opencv"
    values = [k[0, 0], k[1, 1], k[0, 2], k[1, 2]]
    if tool == "fisheye":
        if len(d) != 4:
            raise fail(source, d_key or "D", f"cv2.fisheye has 4 coefficients (k1..k4), got {len(d)}")
        values += d.tolist()
    elif tool == "omnidir":
        xi = _matrix(xi_val, source, xi_key).ravel()
        if xi.size != 1:
            raise fail(source, xi_key, f"expected one number, got {xi.size}")
        if len(d) != 4:
            raise fail(source, d_key or "D", f"cv2.omnidir has 4 coefficients (k1, k2, p1, p2), got {len(d)}")
        values += [float(xi[0]), *d.tolist()]
    else:
        if len(d) not in (0, 4, 5, 8, 12, 14):
            raise fail(source, d_key or "D", f"cv2 takes 4, 5, 8, 12 or 14 coefficients, got {len(d)}")
        if len(d) == 14:
            if d[12] != 0 or d[13] != 0:
                raise fail(source, d_key or "D", f"tilted sensor (tauX, tauY) = ({short(d[12])}, {short(d[13])}): jaxfish's opencv "
                           "model has none (only 0 is read)")
            d = d[:12]
        values += d.tolist() + [0.0] * (12 - len(d))
    if tool == "pinhole":
        if len(d) not in (0, 4, 5, 8, 12, 14) or any(v != 0 for v in d):
            raise fail(source, d_key or "D", f"distortion_model {dm} takes no distortion (all coefficients 0)")
        d = np.zeros(0)
        values = values[:4]
    m = find_reader(OPENCV_MODELS, tool)
    assert m is not None
    if tool == "opencv" and not m.available:
        raise fail(source, d_key or "D", "cv2's pinhole distortion is jaxfish's lens model 'opencv', which this "
                   "version of jaxfish does not have")
    if m.model == "pinhole" and tool == "opencv":  # an ideal pinhole only
        if any(v != 0 for v in values[4:]):
            raise fail(source, d_key or "D", "cv2's distortion is jaxfish's lens model 'opencv', which this version of "
                       "jaxfish does not have (only all-zero coefficients, an ideal pinhole, are read)")
        values = values[: len(m.params)]
    params = m.read(values, source, d_key or k_key)
    w_key, size = _first(data, ("image_size", "imageSize"))
    if size is not None:
        size = _matrix(size, source, w_key).ravel()
        if size.size != 2:
            raise fail(source, w_key, f"expected [width, height], got {size.tolist()}")
        w, h = (whole(float(v), source, f"{w_key}[{j}]") for j, v in enumerate(size))
    else:
        for key in ("image_width", "image_height"):
            if key not in data:
                raise fail(source, key, "missing (the image size: image_width and image_height, or image_size)")
        w, h = whole(data["image_width"], source, "image_width"), whole(data["image_height"], source, "image_height")
    pose = np.eye(4)
    r_key, r_val = _first(data, ("R", "rvec"))
    t_key, t_val = _first(data, ("T", "tvec", "t"))
    if (r_key is None) != (t_key is None):
        raise fail(source, t_key or "T" if r_key is not None else r_key or "R", "a pose needs both R (or rvec) and T (or tvec)")
    if r_key is not None:
        r = _matrix(r_val, source, r_key)
        if r.size == 3:
            r = rodrigues(r.ravel())
        elif r.shape != (3, 3):
            raise fail(source, r_key, f"expected a 3x3 rotation or a rotation vector, got {r.shape}")
        err = float(np.abs(r @ r.T - np.eye(3)).max())
        if err > 1e-4 or np.linalg.det(r) < 0:
            raise fail(source, r_key, f"expected a rotation (R Rᵀ = I, det +1), off by {err:.3g}")
        t = _matrix(t_val, source, t_key).ravel()
        if t.size != 3:
            raise fail(source, t_key, f"expected 3 numbers, got {t.size}")
        v2c = np.eye(4)
        v2c[:3, :3], v2c[:3, 3] = r, t
        pose = rigid_inverse(v2c)
    cam_name = data.get("camera_name", name)
    if not isinstance(cam_name, str) or not cam_name:
        raise fail(source, "camera_name", f"expected a non-empty string, got {short(cam_name)}")
    return [CameraRecord(cam_name, m.model, params, w, h, pose, where="<root>")]


def write(record: CameraRecord) -> str:
    """A FileStorage YAML text (cv2.FileStorage reads it) of one camera."""
    found = find_writer(OPENCV_MODELS, record.model, record.params)
    assert found is not None, record.model
    m, values = found
    fx, fy, cx, cy = values[:4]
    k = [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0]
    v2c = rigid_inverse(record.camera_to_vehicle)
    lines = ["%YAML:1.0", "---", f"camera_name: {_quote(record.name)}",
             f"image_width: {record.width}", f"image_height: {record.height}"]
    dm = {"fisheye": "fisheye", "omnidir": "omnidir", "opencv": "rational_polynomial", "pinhole": "pinhole"}[m.tool]
    if m.tool == "omnidir":
        lines.append(f"xi: {_num(values[4])}")
        d = values[5:]
    elif m.tool == "fisheye":
        d = values[4:]
    elif m.tool == "pinhole":
        d = [0.0] * 5
    else:
        d = list(values[4:]) + [0.0] * (12 - len(values[4:]))
        for n in (5, 8, 12):  # the shortest of cv2's lengths that holds every nonzero coefficient
            if all(v == 0.0 for v in d[n:]):
                d = d[:n]
                break
        dm = "plumb_bob" if len(d) == 5 else "rational_polynomial" if len(d) == 8 else "thin_prism"
    lines.append(f"distortion_model: {dm}")
    lines += _mat("K", 3, 3, k) + _mat("D", 1, len(d), d) + _mat("R", 3, 3, v2c[:3, :3].ravel()) + _mat("T", 3, 1, v2c[:3, 3])
    return "\n".join(lines) + "\n"


def _num(v: float) -> str:
    text = repr(float(v))
    return text if ("." in text or "e" in text or "n" in text) else text + "."


def _quote(s: str) -> str:
    """A YAML double-quoted string (always quoted: ``yes`` or ``123`` unquoted are not strings)."""
    return json.dumps(s)


def _mat(name: str, rows: int, cols: int, data) -> list[str]:
    return [f"{name}: !!opencv-matrix", f"   rows: {rows}", f"   cols: {cols}", "   dt: d",
            "   data: [ " + ", ".join(_num(v) for v in data) + " ]"]
