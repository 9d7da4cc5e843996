"""jaxfish's own default surround-view rig (its own numbers, WoodScape-like)."""

from __future__ import annotations

import numpy as np

from ..cameras import WoodScapeFisheye
from ..transforms import Pose
from ._calibration import Calibration

# Per camera: k1..k4 (pixels), cx/cy offsets (pixels), aspect ratio, mounting position in the ISO
# vehicle frame (metres, origin below the rear-axle centre), yaw of the optical axis (degrees,
# counter-clockwise from vehicle +x) and downward tilt (degrees). A generic ~190-degree lens on a
# mid-size car; rho(theta) is strictly increasing on [0, pi] for all four.
_DEFAULT_RIG = {
    "FV": dict(k=(336.0, -24.0, 36.0, -4.0), off=(2.5, -2.0), aspect=1.0, t=(3.70, 0.0, 0.62), yaw=0.0, tilt=22.0),
    "MVL": dict(k=(335.0, -20.0, 30.0, -2.0), off=(-1.5, -2.5), aspect=1.0, t=(1.95, 1.02, 0.98), yaw=90.0, tilt=62.0),
    "MVR": dict(k=(337.0, -21.0, 31.0, -2.5), off=(1.0, -1.0), aspect=1.0, t=(1.95, -1.02, 0.98), yaw=-90.0, tilt=62.0),
    "RV": dict(k=(334.0, -23.0, 34.0, -3.0), off=(-2.0, 1.5), aspect=1.0, t=(-1.05, 0.0, 0.92), yaw=180.0, tilt=36.0),
}
DEFAULT_WIDTH = 1280
DEFAULT_HEIGHT = 966


def mounting_rotation(yaw_deg: float, tilt_deg: float, roll_deg: float = 0.0) -> np.ndarray:
    """camera (OpenCV) -> vehicle (ISO 8855) rotation of a camera whose optical axis points at
    ``yaw_deg`` (counter-clockwise from vehicle +x, seen from above), tilted ``tilt_deg`` below the
    horizon, and rolled by ``roll_deg`` about its optical axis. Image "down" stays towards the ground."""
    # Level camera looking along vehicle +x: z_cam -> x_veh, x_cam (right) -> -y_veh, y_cam (down) -> -z_veh.
    r0 = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    a = np.deg2rad(tilt_deg)
    # Rotate the camera about its own x axis so that z tilts towards +y (image down).
    rx = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(a), np.sin(a)], [0.0, -np.sin(a), np.cos(a)]])
    c = np.deg2rad(roll_deg)
    rz_cam = np.array([[np.cos(c), -np.sin(c), 0.0], [np.sin(c), np.cos(c), 0.0], [0.0, 0.0, 1.0]])
    y = np.deg2rad(yaw_deg)
    rz = np.array([[np.cos(y), -np.sin(y), 0.0], [np.sin(y), np.cos(y), 0.0], [0.0, 0.0, 1.0]])
    return rz @ r0 @ rx @ rz_cam


def default_rig(*, width: int = DEFAULT_WIDTH, height: int = DEFAULT_HEIGHT, dtype=None) -> dict[str, Calibration]:
    """jaxfish's default 4-camera rig ``{"FV", "MVL", "MVR", "RV"}`` (ISO vehicle frame,
    WoodScape flavour), resized exactly when another image size is asked for."""
    rig = {}
    for name, p in _DEFAULT_RIG.items():
        cam = WoodScapeFisheye(
            np.asarray(p["k"]), width=DEFAULT_WIDTH, height=DEFAULT_HEIGHT,
            cx_offset=p["off"][0], cy_offset=p["off"][1], aspect_ratio=p["aspect"], dtype=dtype,
        )
        pose = Pose(mounting_rotation(p["yaw"], p["tilt"]), np.asarray(p["t"]), dtype=cam.k.dtype)
        calib = Calibration(name, cam, pose, "woodscape")
        if (width, height) != (DEFAULT_WIDTH, DEFAULT_HEIGHT):
            calib = calib.resize(width, height)
        rig[name] = calib
    return rig
