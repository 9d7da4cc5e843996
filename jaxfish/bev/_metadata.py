"""The BEV's scale and axes as JSON-able metadata (stored in BEV PNGs and ``calibration_data/BEV.json``)."""

from __future__ import annotations

from typing import Any

import numpy as np
from jaxtyping import ArrayLike, Float

from ..cameras import Orthographic
from ..transforms import Pose
from ._grid import bev_pixel_to_vehicle

BEV_AXES = ("image up = vehicle forward (+x, ISO 8855), image right = vehicle right (-y); "
            "pixel (u, v) sees the ground point [x, y] = pixel_to_vehicle_xy @ [u, v, 1] (metres)")
"""How a BEV pixel maps to the vehicle frame, in words (also in every BEV PNG's metadata)."""


def bev_metadata(camera: Orthographic, camera_to_vehicle: Pose, *,
                 pixel_to_vehicle_xy: Float[ArrayLike, "2 3"] | None = None, **extra: Any) -> dict[str, Any]:
    """The BEV scale and axes as a JSON-able dict: ``metres_per_pixel``, ``width``, ``height``,
    ``cx``, ``cy``, ``pixel_to_vehicle_xy`` (2 x 3 affine, `bev_pixel_to_vehicle`, computed when not
    given), ``camera_to_vehicle`` (rotation matrix and translation), ``axes`` (words, `BEV_AXES`),
    ``frame``, plus ``extra``."""
    a = bev_pixel_to_vehicle(camera, camera_to_vehicle) if pixel_to_vehicle_xy is None else pixel_to_vehicle_xy
    a = np.asarray(a, np.float64)
    return {"metres_per_pixel": float(camera.metres_per_pixel), "width": int(camera.width), "height": int(camera.height),
            "cx": float(camera.cx), "cy": float(camera.cy), "pixel_to_vehicle_xy": np.round(a, 9).tolist(),
            "camera_to_vehicle": {"rotation_matrix": np.asarray(camera_to_vehicle.rotation_matrix, np.float64).tolist(),
                                  "translation": np.asarray(camera_to_vehicle.translation, np.float64).tolist()},
            "axes": BEV_AXES, "frame": "ISO 8855 vehicle frame (x forward, y left, z up; origin on the ground)",
            **extra}
