"""kalibr camchain YAML (``camchain.yaml`` / ``camchain-imucam.yaml``).

Each camera ``camN`` has ``camera_model`` (pinhole, omni, ds, eucm), ``intrinsics`` (pinhole
``[fu, fv, pu, pv]``, omni ``[xi, fu, fv, pu, pv]``, ds ``[xi, alpha, fu, fv, pu, pv]``, eucm
``[alpha, beta, fu, fv, pu, pv]``), ``distortion_model`` (radtan, equidistant, fov, none) with
``distortion_coeffs``, ``resolution: [W, H]``, and the chain: ``T_cn_cnm1`` (4x4, camera n-1 ->
camera n) and/or ``T_cam_imu`` (4x4, IMU -> camera). Pixels: kalibr's principal point is in
jaxfish's pixel-centre convention.

Vehicle frame: with ``T_cam_imu`` on every camera, the IMU frame (``camera_to_vehicle =
T_cam_imu⁻¹``); otherwise ``cam0``'s optical frame, the chain composed from ``T_cn_cnm1``.
Written files carry both (the vehicle frame in the role of kalibr's IMU), and the camera name in
``rostopic: /NAME/image_raw``.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from typing import Any

import numpy as np

from ._common import (
    CameraRecord,
    ModelMapping,
    fail,
    find_reader,
    find_writer,
    mapping,
    numbers,
    require,
    rigid_inverse,
    rigid_matrix,
    short,
    whole,
)


def _omni_to_unified(p: dict[str, float]) -> dict[str, float]:
    s = 1.0 + p["xi"]
    return {"alpha": p["xi"] / s, "fx": p["fx"] / s, "fy": p["fy"] / s, "cx": p["cx"], "cy": p["cy"]}


def _unified_to_omni(p: dict[str, float]) -> dict[str, float] | None:
    a = p["alpha"]
    if not 0.0 <= a < 1.0:
        return None
    return {"xi": a / (1.0 - a), "fx": p["fx"] / (1.0 - a), "fy": p["fy"] / (1.0 - a), "cx": p["cx"], "cy": p["cy"]}


_PINHOLE = ("fx", "fy", "cx", "cy")
KALIBR_MODELS: tuple[ModelMapping, ...] = (
    ModelMapping(("pinhole", "equidistant"), "kannala_brandt", (*_PINHOLE, "k1", "k2", "k3", "k4")),
    ModelMapping(("pinhole", "radtan"), "opencv", (*_PINHOLE, "k1", "k2", "p1", "p2")),
    ModelMapping(("pinhole", "fov"), "fov", (*_PINHOLE, "w")),
    ModelMapping(("pinhole", "none"), "pinhole", _PINHOLE),
    ModelMapping(("pinhole", "none"), "opencv", _PINHOLE),
    ModelMapping(("omni", "radtan"), "mei", ("xi", *_PINHOLE, "k1", "k2", "p1", "p2")),
    ModelMapping(("omni", "none"), "mei", ("xi", *_PINHOLE)),
    ModelMapping(("omni", "none"), "unified", ("xi", *_PINHOLE), decode=_omni_to_unified, encode=_unified_to_omni),
    ModelMapping(("ds", "none"), "double_sphere", ("xi", "alpha", *_PINHOLE)),
    ModelMapping(("eucm", "none"), "extended_unified", ("alpha", "beta", *_PINHOLE)),
)
"""kalibr (camera_model, distortion_model) <-> jaxfish model; the tool's parameter list is
``intrinsics + distortion_coeffs``. The first row of a jaxfish model is the one written."""

_N_INTRINSICS = {"pinhole": 4, "omni": 5, "ds": 6, "eucm": 6}


def read(data: Any, source: str) -> list[CameraRecord]:
    """The cameras of a parsed camchain YAML."""
    data = mapping(data, source, "<root>")
    keys = sorted((k for k in data if isinstance(k, str) and re.fullmatch(r"cam\d+", k)), key=lambda k: int(k[3:]))
    if not keys:
        raise fail(source, "cam0", "missing (a kalibr camchain has cam0, cam1, ...)")
    if keys != [f"cam{i}" for i in range(len(keys))]:
        raise fail(source, f"cam{len(keys)}", f"cameras must be numbered cam0..camN without gaps, got {keys}")
    records: list[CameraRecord] = []
    chain: list[np.ndarray] = []  # camera -> cam0
    imu: list[np.ndarray | None] = []
    for i, key in enumerate(keys):
        cam = mapping(data[key], source, key)
        model = require(cam, "camera_model", source, key)
        if model not in _N_INTRINSICS:
            raise fail(source, f"{key}.camera_model", f"expected one of {', '.join(_N_INTRINSICS)}, got {short(model)}")
        dist = cam.get("distortion_model", "none")
        dist = "none" if dist is None else dist
        n = _N_INTRINSICS[model]
        intr = numbers(require(cam, "intrinsics", source, key), source, f"{key}.intrinsics", n)
        coeffs = numbers(cam.get("distortion_coeffs") or [], source, f"{key}.distortion_coeffs")
        if dist == "none" and any(c != 0.0 for c in coeffs):
            raise fail(source, f"{key}.distortion_coeffs", "distortion_model none takes no coefficients")
        tool = (model, dist)
        m = find_reader(KALIBR_MODELS, tool)
        if m is None:
            raise fail(source, f"{key}.distortion_model", f"{model} with distortion {short(dist)} is not a kalibr model "
                       "jaxfish reads (pinhole: radtan, equidistant, fov, none; omni: radtan, none; ds, eucm: none)")
        want = len(m.params) - n
        if dist == "none":
            coeffs = []
        if len(coeffs) != want:
            raise fail(source, f"{key}.distortion_coeffs", f"{dist} has {want} coefficients, got {len(coeffs)}")
        params = m.read(intr + coeffs, source, f"{key}.camera_model")
        res = require(cam, "resolution", source, key)
        if not isinstance(res, (list, tuple)) or len(res) != 2:
            raise fail(source, f"{key}.resolution", f"expected [width, height], got {short(res)}")
        w, h = (whole(v, source, f"{key}.resolution[{j}]") for j, v in enumerate(res))
        if i == 0:
            chain.append(np.eye(4))
        else:
            if "T_cn_cnm1" in cam:
                t = rigid_matrix(cam["T_cn_cnm1"], source, f"{key}.T_cn_cnm1")  # cam n-1 -> cam n
                chain.append(chain[-1] @ rigid_inverse(t))
            else:
                chain.append(None)  # type: ignore[arg-type]
        imu.append(rigid_matrix(cam["T_cam_imu"], source, f"{key}.T_cam_imu") if "T_cam_imu" in cam else None)
        topic = cam.get("rostopic")
        name = key
        if isinstance(topic, str):
            match = re.fullmatch(r"/?([^/]+)/image_raw", topic)
            if match:
                name = match.group(1)
        records.append(CameraRecord(name, m.model, params, w, h, np.eye(4), where=key))
    if all(t is not None for t in imu):
        for r, t in zip(records, imu, strict=True):
            r.camera_to_vehicle = rigid_inverse(t)
    else:
        for i, (r, c) in enumerate(zip(records, chain, strict=True)):
            if c is None:
                raise fail(source, f"cam{i}.T_cn_cnm1", "missing (needed to place the camera: no T_cam_imu either)")
            r.camera_to_vehicle = c
    names = [r.name for r in records]
    if len(set(names)) != len(names):
        for r in records:
            r.name = r.where
    return records


def write(records: Sequence[CameraRecord]) -> dict[str, Any]:
    """The camchain object (to dump as YAML) of cameras whose models kalibr has (`writable`)."""
    out: dict[str, Any] = {}
    prev = None
    for i, r in enumerate(records):
        found = find_writer(KALIBR_MODELS, r.model, r.params)
        assert found is not None, r.model
        m, values = found
        n = _N_INTRINSICS[m.tool[0]]
        veh_to_cam = rigid_inverse(r.camera_to_vehicle)
        cam: dict[str, Any] = {
            "camera_model": m.tool[0],
            "intrinsics": [float(v) for v in values[:n]],
            "distortion_model": m.tool[1],
            "distortion_coeffs": [float(v) for v in values[n:]],
            "resolution": [int(r.width), int(r.height)],
            "rostopic": f"/{r.name}/image_raw",
            "T_cam_imu": [[float(x) for x in row] for row in veh_to_cam],
        }
        if prev is not None:
            cam["T_cn_cnm1"] = [[float(x) for x in row] for row in veh_to_cam @ prev]
        prev = r.camera_to_vehicle
        out[f"cam{i}"] = cam
    return out
