"""A calibrated camera: intrinsics (WoodScape fisheye) + mounting pose on the vehicle."""

from __future__ import annotations

from typing import Literal

import equinox as eqx
import numpy as np

from .._numerics import resolve_dtype
from ..cameras import AbstractCamera, WoodScapeFisheye
from ..transforms import Pose

CAMERA_NAMES: tuple[str, ...] = ("FV", "MVL", "MVR", "RV")
"""The four surround-view cameras of WoodScape/SynWoodScape: front, mirror-left, mirror-right, rear."""

SYNWOODSCAPE_CORRECTED_TRANSLATIONS_CARLA: dict[str, tuple[float, float, float]] = {
    "FV": (1.92, 0.0, 0.9),
    "RV": (-1.92, 0.0, 0.9),
    "MVR": (0.8, 0.9, 1.0),
    "MVL": (0.8, -0.9, 1.0),
}
"""Corrected camera translations of SynWoodScape in the **CARLA** frame (x forward, y right, z up,
metres, origin at the CARLA ego actor), from the dataset author (valeoai/WoodScape issue #113).
The published MVL/MVR translations are wrong; FV and RV are unchanged."""

Flavor = Literal["woodscape", "synwoodscape"]


class Calibration(eqx.Module):
    """One calibrated fisheye camera of a rig.

    - `name`: camera name (``"FV"``, ``"MVL"``, ``"MVR"``, ``"RV"`` for the standard rig);
    - `camera`: the intrinsics, a `WoodScapeFisheye` for WoodScape files (other lens models come
      from `jaxfish.refit`'s calibration files; `resize` / `crop` need a `WoodScapeFisheye`);
    - `camera_to_vehicle`: `Pose` mapping OpenCV camera coordinates to the ISO 8855 vehicle frame
      (x forward, y left, z up, metres): ``p_vehicle = R p_cam + t``;
    - `flavor`: ``"woodscape"`` (vehicle origin below the rear-axle centre) or ``"synwoodscape"``
      (origin at the CARLA ego actor; the file stores the translation in CARLA's y-right frame).
    """

    name: str = eqx.field(static=True)
    camera: AbstractCamera
    camera_to_vehicle: Pose
    flavor: str = eqx.field(static=True, default="woodscape")

    def __check_init__(self):
        if self.flavor not in ("woodscape", "synwoodscape"):
            raise ValueError(f"Calibration.flavor must be 'woodscape' or 'synwoodscape', got {self.flavor!r}")

    @property
    def vehicle_to_camera(self) -> Pose:
        """The inverse mounting pose: ISO vehicle frame -> OpenCV camera frame."""
        return self.camera_to_vehicle.inverse()

    @property
    def image_size(self) -> tuple[int, int]:
        """``(width, height)`` in pixels."""
        return self.camera.image_size

    def resize(self, width: int, height: int) -> Calibration:
        """The calibration of the same lens after resizing the image to ``width x height``
        (see `resize_fisheye`); the pose is unchanged."""
        return eqx.tree_at(lambda c: c.camera, self, resize_fisheye(self.camera, width, height))

    def crop(self, x0: int, y0: int, width: int, height: int) -> Calibration:
        """The calibration of the crop ``[x0, x0 + width) x [y0, y0 + height)`` (pixels)."""
        return eqx.tree_at(lambda c: c.camera, self, crop_fisheye(self.camera, x0, y0, width, height))

    def astype(self, dtype) -> Calibration:
        """A copy whose floating parameters have the given dtype."""
        dtype = resolve_dtype(dtype)
        pose = Pose(self.camera_to_vehicle.rotation_matrix, self.camera_to_vehicle.translation, dtype=dtype)
        return Calibration(self.name, self.camera.astype(dtype), pose, self.flavor)


def resize_fisheye(camera: WoodScapeFisheye, width: int, height: int) -> WoodScapeFisheye:
    """Exact WoodScape intrinsics for the image resized to ``width x height``.

    A resize maps pixel edges to pixel edges: ``u' = (u + 0.5) sx - 0.5`` with ``sx = W'/W`` (and
    likewise v), so ``k' = sx k``, ``aspect' = aspect sy / sx``, ``cx_offset' = sx cx_offset``,
    ``cy_offset' = sy cy_offset``. Non-uniform resizes are exact too (only ``u`` is scaled by ``k``,
    ``v`` by ``k * aspect``), unlike OmniDet's scaling.
    """
    if not isinstance(camera, WoodScapeFisheye):
        raise TypeError(f"resize_fisheye: needs a WoodScapeFisheye, got {type(camera).__name__}")
    width, height = int(width), int(height)
    if width <= 0 or height <= 0:
        raise ValueError(f"resize_fisheye: size must be positive, got {width}x{height}")
    sx = width / camera.width
    sy = height / camera.height
    return WoodScapeFisheye(
        camera.k * sx,
        width=width,
        height=height,
        cx_offset=camera.cx_offset * sx,
        cy_offset=camera.cy_offset * sy,
        aspect_ratio=camera.aspect_ratio * (sy / sx),
        dtype=camera.k.dtype,
    )


def crop_fisheye(camera: WoodScapeFisheye, x0: int, y0: int, width: int, height: int) -> WoodScapeFisheye:
    """Exact WoodScape intrinsics for the crop whose top-left pixel is ``(x0, y0)`` of the original.

    ``u' = u - x0``: the principal point moves, the polynomial does not. The crop may extend
    beyond the original image (padding).
    """
    if not isinstance(camera, WoodScapeFisheye):
        raise TypeError(f"crop_fisheye: needs a WoodScapeFisheye, got {type(camera).__name__}")
    width, height = int(width), int(height)
    if width <= 0 or height <= 0:
        raise ValueError(f"crop_fisheye: size must be positive, got {width}x{height}")
    for name, value in (("x0", x0), ("y0", y0)):
        if not np.all(np.isfinite(np.asarray(value, dtype=float))):
            raise ValueError(f"crop_fisheye: {name} must be a finite pixel offset, got {value!r}")
    cx = camera.cx_offset + (camera.width / 2 - 0.5) - x0
    cy = camera.cy_offset + (camera.height / 2 - 0.5) - y0
    return WoodScapeFisheye(
        camera.k,
        width=width,
        height=height,
        cx_offset=cx - (width / 2 - 0.5),
        cy_offset=cy - (height / 2 - 0.5),
        aspect_ratio=camera.aspect_ratio,
        dtype=camera.k.dtype,
    )
