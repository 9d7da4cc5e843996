"""BEV (top view) ground truth of a capture frame and its extra files (height map, occupancy).

The standard modalities of the BEV (RGB, depth, semantics, instances, motion, flow, boxes) are
those of any camera (`capture_ground_truth`'s result layout, written by
`write_camera_ground_truth` with camera name ``"BEV"``); this module adds the height map and the
occupancy grid, each PNG carrying the BEV scale and axes as metadata (`BEV_METADATA_ATTRIBUTE`).
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from .._errors import ImageError, JaxfishError
from ._images import PNG_LEVEL, read_image_metadata, write_image
from ._json import read_json

BEV_METADATA_ATTRIBUTE = "jaxfish:bev"
"""Metadata key of the BEV scale/axes JSON in the BEV PNGs written by `write_bev_ground_truth`."""
BEV_METRES_PER_PIXEL_RANGE = (1e-6, 1e6)
"""The scale a BEV description may give (metres per pixel): float32 keeps it and its inverse finite."""
_ROTATION_TOL = 1e-4  # |R^T R - I| and |det R - 1| of a stored rotation (float32 round trips: ~1e-7)


def _pose_from_json(d: Any, where: str):
    import jax.numpy as jnp

    from ..transforms import Pose
    from ._capture import CaptureError

    try:
        r = np.asarray(d["rotation_matrix"], np.float64)
        t = np.asarray(d["translation"], np.float64)
    except (KeyError, TypeError, ValueError) as e:
        raise CaptureError(f"{where}: field 'camera_to_vehicle' malformed ({e!r})") from e
    if r.shape != (3, 3) or t.shape != (3,) or not (np.all(np.isfinite(r)) and np.all(np.isfinite(t))):
        raise CaptureError(f"{where}: field 'camera_to_vehicle' needs a finite 3x3 rotation_matrix and 3-vector translation")
    orth = float(np.max(np.abs(r.T @ r - np.eye(3))))
    det = float(np.linalg.det(r))
    if orth > _ROTATION_TOL or abs(det - 1.0) > _ROTATION_TOL:
        raise CaptureError(f"{where}: field 'camera_to_vehicle.rotation_matrix' is not a rotation "
                           f"(max |R^T R - I| = {orth:.3g}, det = {det:.6g}; needs R^T R = I and det = +1)")
    return Pose(r, t, dtype=jnp.float32)


def bev_sensor(reader) -> tuple[Any, Any]:
    """The capture's BEV camera (`Orthographic`, float32) and its ``camera_to_vehicle`` pose, from
    ``sensors.json`` (`CaptureError` naming the file and field when absent or malformed)."""
    from ._capture import CaptureError

    where = f"{reader.root / 'sensors.json'}"
    sensors = reader.sensors()
    if "bev" not in sensors:
        raise CaptureError(f"{where}: field 'bev' missing (the capture has no BEV camera)")
    return _bev_camera_and_pose(sensors["bev"], where, CaptureError, "bev.")


def bev_from_metadata(metadata: Mapping[str, Any], where: str = "BEV metadata") -> tuple[Any, Any]:
    """The BEV camera (`Orthographic`) and ``camera_to_vehicle`` pose described by a `bev_metadata`
    dict (e.g. a dataset's ``calibration_data/BEV.json`` or a BEV PNG's metadata); ``where`` names
    the source in errors."""
    return _bev_camera_and_pose(metadata, where, ImageError, "")


def _bev_camera_and_pose(d: Mapping[str, Any], where: str, error: type[JaxfishError], prefix: str):
    """`Orthographic` (float32) and ``camera_to_vehicle`` pose of a BEV description ``d``; errors are
    ``error`` naming ``where`` and the field (``prefix`` + name)."""
    import jax.numpy as jnp

    from ..cameras import Orthographic

    mpp = d.get("metres_per_pixel") if isinstance(d, Mapping) else None
    if isinstance(mpp, (int, float)) and not isinstance(mpp, bool) and not (math.isfinite(mpp) and mpp > 0):
        raise error(f"{where}: field '{prefix}metres_per_pixel': expected a positive number of metres, got {mpp!r}")
    lo, hi = BEV_METRES_PER_PIXEL_RANGE
    if isinstance(mpp, (int, float)) and not isinstance(mpp, bool) and not lo <= mpp <= hi:
        raise error(f"{where}: field '{prefix}metres_per_pixel': expected {lo:g} to {hi:g} metres per pixel, got {mpp!r}")
    for key in ("cx", "cy"):
        c = d.get(key) if isinstance(d, Mapping) else None
        if isinstance(c, (int, float)) and not isinstance(c, bool) and not (math.isfinite(c) and abs(c) <= 1e7):
            raise error(f"{where}: field '{prefix}{key}': expected a finite number of pixels (at most 1e7), got {c!r}")
    try:
        cam = Orthographic(float(d["metres_per_pixel"]), width=int(d["width"]), height=int(d["height"]),
                           cx=float(d["cx"]), cy=float(d["cy"]), dtype=jnp.float32)
    except KeyError as e:
        raise error(f"{where}: field '{prefix}{e.args[0]}' missing") from e
    except (TypeError, ValueError) as e:
        raise error(f"{where}: field '{prefix.rstrip('.') or 'BEV scale'}' malformed ({e})") from e
    if "camera_to_vehicle" not in d:
        raise error(f"{where}: field '{prefix}camera_to_vehicle' missing")
    try:
        return cam, _pose_from_json(d["camera_to_vehicle"], where)
    except JaxfishError as e:
        if isinstance(e, error):
            raise
        raise error(str(e)) from e


def load_bev_calibration(path: str | os.PathLike) -> tuple[Any, Any]:
    """BEV camera and pose from a ``BEV.json`` (`bev_metadata` as JSON) or a BEV PNG carrying
    `BEV_METADATA_ATTRIBUTE` (`bev_from_metadata`)."""
    path = Path(path)
    if not path.is_file():
        raise ImageError(f"{path}: BEV calibration file not found")
    if path.suffix.lower() == ".json":
        meta = read_json(path, ImageError)
    else:
        meta = read_bev_metadata(path)
    return bev_from_metadata(meta, str(path))


def write_png_with_metadata(path: str | os.PathLike, image: np.ndarray, metadata: Mapping[str, Any], *,
                            png_level: int = PNG_LEVEL) -> Path:
    """uint8 PNG (``(H, W)`` or ``(H, W, C)``) with ``metadata`` as JSON in the text attribute
    `BEV_METADATA_ATTRIBUTE` (atomic)."""
    a = np.asarray(image)
    if a.dtype != np.uint8:
        raise ImageError(f"{path}: expected uint8 pixels, got {a.dtype}")
    return write_image(path, a, metadata={BEV_METADATA_ATTRIBUTE: dict(metadata)}, png_level=png_level)


def read_bev_metadata(path: str | os.PathLike) -> dict[str, Any]:
    """The BEV scale and axes stored in a BEV PNG by `write_bev_ground_truth` (`bev_metadata`)."""
    meta = read_image_metadata(path, BEV_METADATA_ATTRIBUTE)
    if not isinstance(meta, dict):
        raise ImageError(f"{path}: metadata '{BEV_METADATA_ATTRIBUTE}' must be a JSON object, got {type(meta).__name__}")
    return meta
