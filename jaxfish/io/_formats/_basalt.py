"""basalt calibration JSON (cereal): ``value0.intrinsics[i]`` = ``{"camera_type": TYPE,
"intrinsics": {name: value}}`` (kb4, ds, eucm, ucm, pinhole, pinhole-radtan8, fov),
``value0.resolution[i] = [W, H]`` and ``value0.T_imu_cam[i]`` = ``{"px", "py", "pz", "qx", "qy",
"qz", "qw"}`` (camera -> IMU; the IMU frame is jaxfish's vehicle frame). basalt's principal point is
in jaxfish's pixel-centre convention. Written files carry the IMU fields basalt's loader expects
(zero biases and noise); camera names are ``cam0``, ``cam1``... (basalt files have none).
"""

from __future__ import annotations

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
    number,
    quaternion_matrix,
    quaternion_xyzw,
    require,
    short,
    whole,
)

_P = ("fx", "fy", "cx", "cy")
BASALT_MODELS: tuple[ModelMapping, ...] = (
    ModelMapping("kb4", "kannala_brandt", (*_P, "k1", "k2", "k3", "k4")),
    ModelMapping("ds", "double_sphere", (*_P, "xi", "alpha")),
    ModelMapping("eucm", "extended_unified", (*_P, "alpha", "beta")),
    ModelMapping("ucm", "unified", (*_P, "alpha")),
    ModelMapping("pinhole", "pinhole", _P),
    ModelMapping("pinhole-radtan8", "opencv", (*_P, "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")),
    ModelMapping("fov", "fov", (*_P, "w")),
)
"""basalt camera_type <-> jaxfish model; the names are basalt's ``intrinsics`` keys (which are
jaxfish's parameter names). ``pinhole-radtan8`` also has ``rpmax`` (its validity radius; read and
ignored, written 0: basalt then derives it)."""


def read(data: Any, source: str) -> list[CameraRecord]:
    """The cameras of a parsed basalt calibration JSON."""
    root = mapping(data, source, "<root>")
    v = mapping(require(root, "value0", source, ""), source, "value0")
    intr = require(v, "intrinsics", source, "value0")
    if not isinstance(intr, list) or not intr:
        raise fail(source, "value0.intrinsics", "expected a non-empty list of cameras")
    res = require(v, "resolution", source, "value0")
    poses = require(v, "T_imu_cam", source, "value0")
    for key, val in (("resolution", res), ("T_imu_cam", poses)):
        if not isinstance(val, list) or len(val) != len(intr):
            raise fail(source, f"value0.{key}", f"expected a list of {len(intr)} entries (one per camera)")
    records = []
    for i, cam in enumerate(intr):
        where = f"value0.intrinsics[{i}]"
        cam = mapping(cam, source, where)
        ctype = require(cam, "camera_type", source, where)
        m = find_reader(BASALT_MODELS, ctype)
        if m is None:
            raise fail(source, f"{where}.camera_type", f"expected one of {', '.join(r.tool for r in BASALT_MODELS)}, "
                       f"got {short(ctype)}")
        vals = mapping(require(cam, "intrinsics", source, where), source, f"{where}.intrinsics")
        allowed = set(m.params) | ({"rpmax"} if ctype == "pinhole-radtan8" else set())
        extra = sorted(set(vals) - allowed)
        if extra:
            raise fail(source, f"{where}.intrinsics.{extra[0]}", f"unexpected key for camera_type {ctype}")
        values = [number(require(vals, p, source, f"{where}.intrinsics"), source, f"{where}.intrinsics.{p}")
                  for p in m.params]
        params = m.read(values, source, f"{where}.camera_type")
        r = res[i]
        if not isinstance(r, list) or len(r) != 2:
            raise fail(source, f"value0.resolution[{i}]", f"expected [width, height], got {short(r)}")
        w, h = (whole(x, source, f"value0.resolution[{i}][{j}]") for j, x in enumerate(r))
        pw = f"value0.T_imu_cam[{i}]"
        p = mapping(poses[i], source, pw)
        t = [number(require(p, k, source, pw), source, f"{pw}.{k}") for k in ("px", "py", "pz")]
        q = np.array([number(require(p, k, source, pw), source, f"{pw}.{k}") for k in ("qx", "qy", "qz", "qw")])
        qn = float(np.linalg.norm(q))
        if abs(qn - 1.0) > 1e-3:
            raise fail(source, f"{pw}.qw", f"expected a unit quaternion (qx, qy, qz, qw), norm is {qn:.6g}")
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = quaternion_matrix(q), t
        records.append(CameraRecord(f"cam{i}", m.model, params, w, h, pose, where=where))
    return records


def write(records: Sequence[CameraRecord]) -> dict[str, Any]:
    """The basalt calibration object of cameras whose models basalt has."""
    intr, res, poses = [], [], []
    for r in records:
        found = find_writer(BASALT_MODELS, r.model, r.params)
        assert found is not None, r.model
        m, values = found
        vals = {k: float(x) for k, x in zip(m.params, values, strict=True)}
        if m.tool == "pinhole-radtan8":
            vals["rpmax"] = 0.0
        intr.append({"camera_type": m.tool, "intrinsics": vals})
        res.append([int(r.width), int(r.height)])
        m4 = r.camera_to_vehicle
        q = quaternion_xyzw(m4[:3, :3])
        poses.append({"px": float(m4[0, 3]), "py": float(m4[1, 3]), "pz": float(m4[2, 3]),
                      "qx": float(q[0]), "qy": float(q[1]), "qz": float(q[2]), "qw": float(q[3])})
    zero3 = [0.0, 0.0, 0.0]
    return {"value0": {
        "T_imu_cam": poses, "intrinsics": intr, "resolution": res,
        "calib_accel_bias": [0.0] * 9, "calib_gyro_bias": [0.0] * 12, "imu_update_rate": 200.0,
        "accel_noise_std": zero3, "gyro_noise_std": zero3, "accel_bias_std": zero3, "gyro_bias_std": zero3,
        "cam_time_offset_ns": 0, "vignette": [],
    }}
