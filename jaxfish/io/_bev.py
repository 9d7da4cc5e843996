"""BEV (top view) ground truth of a capture frame and its extra files (height map, occupancy).

The standard modalities of the BEV (RGB, depth, semantics, instances, motion, flow, boxes) are
those of any camera (`capture_ground_truth`'s result layout, written by
`write_camera_ground_truth` with camera name ``"BEV"``); this module adds the height map and the
occupancy grid, each PNG carrying the BEV scale and axes as metadata (`BEV_METADATA_ATTRIBUTE`).
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import OpenImageIO as oiio

from .._errors import ImageError
from ._atomic import atomic_path
from ._labels import write_depth_npy

#: Metadata key of the BEV scale/axes JSON in the BEV PNGs written by `write_bev_ground_truth`.
BEV_METADATA_ATTRIBUTE = "jaxfish:bev"
#: How a BEV pixel maps to the vehicle frame, in words (also in every BEV PNG's metadata).
BEV_AXES = ("image up = vehicle forward (+x, ISO 8855), image right = vehicle right (-y); "
            "pixel (u, v) sees the ground point [x, y] = pixel_to_vehicle_xy @ [u, v, 1] (metres)")


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
    return Pose(r, t, dtype=jnp.float32)


def bev_sensor(reader) -> tuple[Any, Any]:
    """The capture's BEV camera (`Orthographic`, float32) and its ``camera_to_vehicle`` pose, from
    ``sensors.json`` (`CaptureError` naming the file and field when absent or malformed)."""
    import jax.numpy as jnp

    from ..cameras import Orthographic
    from ._capture import CaptureError

    where = f"{reader.root / 'sensors.json'}"
    sensors = reader.sensors()
    if "bev" not in sensors:
        raise CaptureError(f"{where}: field 'bev' missing (the capture has no BEV camera)")
    bev = sensors["bev"]
    try:
        cam = Orthographic(float(bev["metres_per_pixel"]), width=int(bev["width"]), height=int(bev["height"]),
                           cx=float(bev["cx"]), cy=float(bev["cy"]), dtype=jnp.float32)
    except KeyError as e:
        raise CaptureError(f"{where}: field 'bev.{e.args[0]}' missing") from e
    except (TypeError, ValueError) as e:
        raise CaptureError(f"{where}: field 'bev' malformed ({e})") from e
    if "camera_to_vehicle" not in bev:
        raise CaptureError(f"{where}: field 'bev.camera_to_vehicle' missing")
    return cam, _pose_from_json(bev["camera_to_vehicle"], where)


def capture_bev_ground_truth(reader, frame: int, *, rays=None, backward_flow: bool = False,
                             carla_version: str | None = None,
                             occupancy_min_height_m: float | None = None, **options: Any) -> dict[str, Any]:
    """Ground truth of a capture frame's BEV top view (`CaptureReader`).

    Returns `capture_ground_truth`'s keys (``"truth"``: `jaxfish.groundtruth.CameraGroundTruth`
    from `jaxfish.groundtruth.view_ground_truth` with the capture's BEV camera and mount,
    ``"boxes_prev"``, ``"boxes"``, ``"vehicle_to_world_prev"``, ``"vehicle_to_world"``,
    ``"camera"``, ``"actors"``, ``"events": None``) plus ``"height_m"`` ``(H, W)`` float32 metres
    above the ground (the capture's ``height_curr.exr``, or from the BEV depth when absent),
    ``"occupancy"`` ``(H, W)`` bool (`jaxfish.bev.occupancy_map`), ``"metres_per_pixel"`` (float)
    and ``"camera_to_vehicle"`` (`Pose`). ``options`` go to ``view_ground_truth``."""
    import jax.numpy as jnp

    from .. import bev as jbev
    from .. import groundtruth as gt
    from ._capture import CaptureError, frame_dir

    cam, c2v = bev_sensor(reader)
    actors = reader.actors(frame)  # names the frame when it is missing
    ego = reader.ego(frame)
    d = frame_dir(reader.root, frame) / "bev"
    for instant in ("prev", "curr"):
        for kind in ("rgb", "depth", "semantic"):
            p = d / f"{kind}_{instant}.png"
            if not p.is_file():
                raise CaptureError(f"{p}: file missing (BEV {kind} at {'t-1' if instant == 'prev' else 't'})")
    view_prev, view = reader.view(frame, "bev", "prev"), reader.view(frame, "bev", "curr")
    if view.depth_m.shape != (cam.height, cam.width):
        raise CaptureError(f"{d / 'depth_curr.png'}: BEV image {view.depth_m.shape} does not match sensors.json "
                           f"bev width x height {cam.width} x {cam.height}")
    try:
        boxes_prev = gt.boxes_from_actors(actors, "t-1")
        boxes = gt.boxes_from_actors(actors, "t")
        v2w_p = gt.vehicle_to_world_from_carla(np.asarray(ego["transform_prev"]["location"], np.float32),
                                               np.asarray(ego["transform_prev"]["rotation"], np.float32))
        v2w = gt.vehicle_to_world_from_carla(np.asarray(ego["transform"]["location"], np.float32),
                                             np.asarray(ego["transform"]["rotation"], np.float32))
    except (KeyError, TypeError, ValueError) as e:
        raise CaptureError(f"{reader.root}: frame {frame}: malformed actors.json / ego.json ({e})") from e
    tags = str(reader.meta.get("carla_semantic_tags", "0.9.10"))
    version = carla_version or ("0.9.10" if tags in ("0.9.10", "0.9.11", "0.9.12", "0.9.13") else "0.9.14")
    truth = gt.view_ground_truth(cam, c2v, view_prev, view, boxes_prev, boxes, v2w_p, v2w, backward_flow=backward_flow,
                                 carla_version=version, rays=rays, **options)
    exr = d / "height_curr.exr"
    if exr.is_file():
        height = reader.height(frame, "bev").astype(np.float32)
        if height.shape != (cam.height, cam.width):
            raise CaptureError(f"{exr}: height map {height.shape} does not match the BEV image {(cam.height, cam.width)}")
    else:
        height = np.asarray(jbev.height_map(cam, c2v, jnp.asarray(view.depth_m, jnp.float32)))
    thr = jbev.OCCUPANCY_MIN_HEIGHT_M if occupancy_min_height_m is None else float(occupancy_min_height_m)
    occupancy = np.asarray(jbev.occupancy_map(height, min_height_m=thr))
    return {"truth": truth, "boxes_prev": boxes_prev, "boxes": boxes, "vehicle_to_world_prev": v2w_p,
            "vehicle_to_world": v2w, "events": None, "camera": cam, "actors": actors, "height_m": height,
            "occupancy": occupancy, "occupancy_min_height_m": thr,
            "metres_per_pixel": float(cam.metres_per_pixel), "camera_to_vehicle": c2v}


def bev_metadata(camera, camera_to_vehicle, **extra: Any) -> dict[str, Any]:
    """The BEV scale and axes as a JSON-able dict: ``metres_per_pixel``, ``width``, ``height``,
    ``cx``, ``cy``, ``pixel_to_vehicle_xy`` (2 x 3 affine, `jaxfish.bev.bev_pixel_to_vehicle`),
    ``camera_to_vehicle`` (rotation matrix and translation), ``axes`` (words), ``frame``, plus
    ``extra``."""
    from .. import bev as jbev

    a = np.asarray(jbev.bev_pixel_to_vehicle(camera, camera_to_vehicle), np.float64)
    return {"metres_per_pixel": float(camera.metres_per_pixel), "width": int(camera.width), "height": int(camera.height),
            "cx": float(camera.cx), "cy": float(camera.cy), "pixel_to_vehicle_xy": np.round(a, 9).tolist(),
            "camera_to_vehicle": {"rotation_matrix": np.asarray(camera_to_vehicle.rotation_matrix, np.float64).tolist(),
                                  "translation": np.asarray(camera_to_vehicle.translation, np.float64).tolist()},
            "axes": BEV_AXES, "frame": "ISO 8855 vehicle frame (x forward, y left, z up; origin on the ground)",
            **extra}


def write_png_with_metadata(path: str | os.PathLike, image: np.ndarray, metadata: Mapping[str, Any]) -> Path:
    """uint8 PNG (``(H, W)`` or ``(H, W, C)``) with ``metadata`` as JSON in the text attribute
    `BEV_METADATA_ATTRIBUTE` (atomic)."""
    path = Path(path)
    a = np.asarray(image)
    if a.dtype != np.uint8:
        raise ImageError(f"{path}: expected uint8 pixels, got {a.dtype}")
    if a.ndim == 2:
        a = a[..., None]  # OpenImageIO scrambles 2-D arrays (CONVENTIONS §8)
    if a.ndim != 3:
        raise ImageError(f"{path}: expected (H, W) or (H, W, C) pixels, got {a.shape}")
    a = np.ascontiguousarray(a)
    h, w, c = a.shape
    with atomic_path(path) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None:
            raise ImageError(f"{path}: cannot create writer ({oiio.geterror()})")
        spec = oiio.ImageSpec(w, h, c, oiio.UINT8)
        spec.attribute(BEV_METADATA_ATTRIBUTE, json.dumps(dict(metadata)))
        if not out.open(str(tmp), spec) or not out.write_image(a):
            err = out.geterror()
            out.close()
            raise ImageError(f"{path}: cannot write ({err})")
        out.close()
    return path


def read_bev_metadata(path: str | os.PathLike) -> dict[str, Any]:
    """The BEV scale and axes stored in a BEV PNG by `write_bev_ground_truth` (`bev_metadata`)."""
    path = Path(path)
    if not path.is_file():
        raise ImageError(f"{path}: image file not found")
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise ImageError(f"{path}: cannot open ({oiio.geterror()})")
    try:
        value = inp.spec().get_string_attribute(BEV_METADATA_ATTRIBUTE, "")
    finally:
        inp.close()
    if not value:
        raise ImageError(f"{path}: no '{BEV_METADATA_ATTRIBUTE}' metadata")
    return json.loads(value)


def write_bev_ground_truth(root: str | os.PathLike, sample: str, result: Mapping[str, Any]) -> list[Path]:
    """Write the BEV extras of a `capture_bev_ground_truth` result under ``root``:
    ``bev_height/raw_data/{sample}_BEV.npy`` (float32 metres above the ground),
    ``bev_height/colormap/{sample}_BEV.png`` (`jaxfish.bev.colorize_height`) and
    ``bev_occupancy/{sample}_BEV.png`` (0 free / 255 occupied), each PNG with the BEV scale and
    axes (`bev_metadata`) in its metadata. The standard modalities are written by
    ``write_camera_ground_truth(root, sample, "BEV", result)``. Returns the paths written."""
    from .. import bev as jbev

    missing = [k for k in ("height_m", "occupancy", "camera", "camera_to_vehicle") if k not in result]
    if missing:
        raise ImageError(f"{root}: BEV result for sample {sample!r} lacks {missing} (use capture_bev_ground_truth)")
    root = Path(root)
    stem = f"{sample}_BEV"
    cam, c2v = result["camera"], result["camera_to_vehicle"]
    height = np.asarray(result["height_m"], np.float32)
    occ = np.asarray(result["occupancy"], bool)
    if height.shape != (cam.height, cam.width) or occ.shape != height.shape:
        raise ImageError(f"{root}: sample {sample!r}: height {height.shape} / occupancy {occ.shape} do not match "
                         f"the BEV image {(cam.height, cam.width)}")
    lo, hi = jbev.HEIGHT_COLOR_RANGE_M
    thr = float(result.get("occupancy_min_height_m", jbev.OCCUPANCY_MIN_HEIGHT_M))
    out = [write_depth_npy(root / "bev_height" / "raw_data" / f"{stem}.npy", height)]
    color = np.asarray(jbev.colorize_height(height))
    out.append(write_png_with_metadata(root / "bev_height" / "colormap" / f"{stem}.png", color,
                                       bev_metadata(cam, c2v, content="height above the ground (m), viridis",
                                                    color_range_m=[lo, hi])))
    out.append(write_png_with_metadata(root / "bev_occupancy" / f"{stem}.png", occ.astype(np.uint8) * 255,
                                       bev_metadata(cam, c2v, content="occupancy: 255 = top surface higher than "
                                                    f"{thr:g} m above the ground, 0 = free", occupancy_min_height_m=thr)))
    return out
