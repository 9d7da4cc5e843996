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
from ._labels import _carla_version, _frame_motion, compiled_pixel_rays, write_depth_npy

BEV_METADATA_ATTRIBUTE = "jaxfish:bev"
"""Metadata key of the BEV scale/axes JSON in the BEV PNGs written by `write_bev_ground_truth`."""
BEV_AXES = ("image up = vehicle forward (+x, ISO 8855), image right = vehicle right (-y); "
            "pixel (u, v) sees the ground point [x, y] = pixel_to_vehicle_xy @ [u, v, 1] (metres)")
"""How a BEV pixel maps to the vehicle frame, in words (also in every BEV PNG's metadata)."""


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


def capture_bev_ground_truth(reader, frame: int, *, rays=None, backward_flow: bool = False,
                             carla_version: str | None = None,
                             occupancy_min_height_m: float | None = None, **options: Any) -> dict[str, Any]:
    """Ground truth of a capture frame's BEV top view (`CaptureReader`).

    Returns `capture_ground_truth`'s keys (``"truth"``: `jaxfish.groundtruth.CameraGroundTruth`
    from `jaxfish.groundtruth.view_ground_truth` with the capture's BEV camera and mount,
    ``"boxes_prev"``, ``"boxes"``, ``"vehicle_to_world_prev"``, ``"vehicle_to_world"``,
    ``"camera"``, ``"rays"`` (as given), ``"actors"``, ``"events": None``) plus ``"height_m"`` ``(H, W)`` float32 metres
    above the ground (the capture's ``height_curr.exr``, or from the BEV depth when absent),
    ``"occupancy"`` ``(H, W)`` bool (`jaxfish.bev.occupancy_map`), ``"metres_per_pixel"`` (float)
    and ``"camera_to_vehicle"`` (`Pose`). ``options`` go to ``view_ground_truth``."""
    import jax.numpy as jnp

    from .. import bev as jbev
    from .. import groundtruth as gt
    from ._capture import CaptureError, frame_dir

    cam, c2v = bev_sensor(reader)
    actors, boxes_prev, boxes, v2w_p, v2w = _frame_motion(reader, frame)
    d = frame_dir(reader.root, frame) / "bev"
    for instant in ("prev", "curr"):
        for kind in ("rgb", "depth", "semantic"):
            p = d / f"{kind}_{instant}.png"
            if not p.is_file():
                raise CaptureError(f"{p}: file missing (BEV {kind} at {'t-1' if instant == 'prev' else 't'})")
    view_prev, view = reader.view(frame, "bev", "prev", actor_ids=False), reader.view(frame, "bev", "curr", actor_ids=False)
    if view.depth_m.shape != (cam.height, cam.width):
        raise CaptureError(f"{d / 'depth_curr.png'}: BEV image {view.depth_m.shape} does not match sensors.json "
                           f"bev width x height {cam.width} x {cam.height}")
    version = _carla_version(reader, carla_version)
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
            "vehicle_to_world": v2w, "events": None, "camera": cam, "rays": rays, "actors": actors, "height_m": height,
            "occupancy": occupancy, "occupancy_min_height_m": thr,
            "metres_per_pixel": float(cam.metres_per_pixel), "camera_to_vehicle": c2v}


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


def write_bev_ground_truth(root: str | os.PathLike, sample: str, result: Mapping[str, Any], *,
                           png_level: int = PNG_LEVEL) -> list[Path]:
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
                                                    color_range_m=[lo, hi]), png_level=png_level))
    out.append(write_png_with_metadata(root / "bev_occupancy" / f"{stem}.png", occ.astype(np.uint8) * 255,
                                       bev_metadata(cam, c2v, content="occupancy: 255 = top surface higher than "
                                                    f"{thr:g} m above the ground, 0 = free", occupancy_min_height_m=thr), png_level=png_level))
    return out


def _split_classes(world, base, centre, rot, half, cls, margin_m):
    """Vehicle-like pixels inside a two-wheeler or ego box take the box's class (first box wins)."""
    import jax.numpy as jnp

    from ..groundtruth import carla_to_synwoodscape  # noqa: F401  (documents where the rule comes from)

    d = world[None] - centre[:, None, None, :]
    local = jnp.einsum("kji,khwj->khwi", rot, d)
    inside = jnp.all(jnp.abs(local) <= half[:, None, None, :] + margin_m, axis=-1)  # (K, H, W)
    hit = jnp.any(inside, axis=0)
    box_cls = jnp.where(hit, cls[jnp.argmax(inside, axis=0)], -1)
    vehicle_like = (base == 10) | (base == 21)
    return jnp.where(vehicle_like & hit, box_cls, base)


def _camera_maps_kernel(lut, cam, rays, c2w, depth, tag, centre, rot, half, cls, margin_m):
    import jax.numpy as jnp

    from .. import groundtruth as gt
    from ..reprojection import resample_depth, resample_nearest

    # as `jaxfish.groundtruth.fisheye_images`, without the RGB
    rng, valid = resample_depth(depth.astype(jnp.float32), lut, far_m=gt.FAR_RANGE_M)
    tags, _ = resample_nearest(tag, lut, reduce="centre")
    pts, ok = gt.pixel_points(cam, rng, dtype=jnp.float32, rays=rays)
    world = gt.apply_pose(c2w, pts)
    base = gt.carla_to_synwoodscape(tags.astype(jnp.int32))
    sem = _split_classes(world, base, centre, rot, half, cls, margin_m)
    valid = valid & ok
    return rng, jnp.where(valid, sem, -1), valid


def capture_camera_maps(reader, frame: int, *, luts: Mapping[str, Any] | None = None,
                        rays: Mapping[str, Any] | None = None, margin_m: float = 0.05) -> dict[str, Any]:
    """Range and class maps of every fisheye camera of a capture frame at t: the inputs of
    `jaxfish.bev.fuse_cameras` and `jaxfish.bev.ipm_semantics`, lighter than the full
    `capture_ground_truth` (no flow, instances or events).

    Per camera the cube faces' depth and tags are resampled to the fisheye as
    `jaxfish.groundtruth.fisheye_images` does (range along the ray, CARLA tag); tags become SynWoodScape classes, and vehicle pixels whose 3D
    point lies in a two-wheeler or the ego box (grown by ``margin_m``) take that box's class (21,
    24), as in the full ground truth. ``luts`` / ``rays`` (per camera name: `Lut`, `pixel_rays`)
    are per-calibration constants, built here when absent. Returns ``{"names", "cameras",
    "cameras_to_vehicle": lists, "range_m", "semantic" (-1 where no ray), "valid": (N, H, W)
    arrays, "luts", "rays": dicts to pass back for the next frame, "range_resolution_rad": the
    angle of one cube-face pixel, (pi / 2) / face size: the angular step of the resampled range
    maps, for `jaxfish.bev.fuse_cameras_dense`'s tolerance}``."""
    import jax.numpy as jnp

    from .. import groundtruth as gt
    from ..reprojection import CubeRig, build_lut
    from ._capture import CaptureError

    rig = reader.rig()
    names = list(reader.cameras)
    luts = dict(luts or {})
    rays = dict(rays or {})
    actors = reader.actors(frame)
    ego = reader.ego(frame)
    try:
        boxes = gt.boxes_from_actors(actors, "t")
        v2w = gt.vehicle_to_world_from_carla(np.asarray(ego["transform"]["location"], np.float32),
                                             np.asarray(ego["transform"]["rotation"], np.float32))
    except (KeyError, TypeError, ValueError) as e:
        raise CaptureError(f"{reader.root}: frame {frame}: malformed actors.json / ego.json ({e})") from e
    sel = np.asarray(boxes.active) & np.isin(np.asarray(boxes.class_id), (21, 24))
    # one never-containing padding box keeps the kernel's box axis non-empty
    centre = jnp.asarray(np.concatenate([np.asarray(boxes.box_to_world.translation)[sel].reshape(-1, 3),
                                         np.zeros((1, 3))]), jnp.float32)
    rot = jnp.asarray(np.concatenate([np.asarray(boxes.box_to_world.rotation_matrix)[sel].reshape(-1, 3, 3),
                                      np.eye(3)[None]]), jnp.float32)
    half = jnp.asarray(np.concatenate([np.asarray(boxes.half_extent)[sel].reshape(-1, 3), np.full((1, 3), -1e9)]),
                       jnp.float32)
    cls = jnp.asarray(np.concatenate([np.asarray(boxes.class_id)[sel].reshape(-1), [-1]]), jnp.int32)
    faces = tuple(reader.faces)
    kernel = _jit_camera_maps()
    cams, poses, rng, sem, val = [], [], [], [], []
    face_px = 1
    for name in names:
        if name not in rig:
            raise CaptureError(f"{reader.root}/calibration: camera {name!r} missing")
        calib = rig[name].astype(jnp.float32)
        cam = calib.camera.astype(jnp.float32)
        stack = reader.faces_stack(frame, name, "curr")
        face_px = int(stack.depth_m.shape[1])
        if name not in luts:
            size = int(reader.meta.get("face_size", 0)) or stack.depth_m.shape[1]
            luts[name] = build_lut(CubeRig(size, faces=faces, dtype=jnp.float32), cam)
        if name not in rays:
            rays[name] = compiled_pixel_rays(cam)
        c2w = gt.camera_to_world(v2w, calib.camera_to_vehicle)
        r, s, v = kernel(luts[name], cam, rays[name], c2w, jnp.asarray(stack.depth_m), jnp.asarray(stack.semantic),
                         centre, rot, half, cls, float(margin_m))
        cams.append(cam)
        poses.append(calib.camera_to_vehicle)
        rng.append(np.asarray(r))
        sem.append(np.asarray(s))
        val.append(np.asarray(v))
    shapes = {a.shape for a in rng}
    if len(shapes) != 1:
        raise CaptureError(f"{reader.root}/calibration: the fisheye cameras differ in image size ({sorted(shapes)})")
    face = int(reader.meta.get("face_size", 0)) or face_px
    return {"names": names, "cameras": cams, "cameras_to_vehicle": poses, "range_m": np.stack(rng),
            "semantic": np.stack(sem).astype(np.int32), "valid": np.stack(val), "luts": luts, "rays": rays,
            "range_resolution_rad": math.pi / 2 / face}


_KERNEL: list[Any] = []


def _jit_camera_maps():
    import jax

    if not _KERNEL:
        _KERNEL.append(jax.jit(_camera_maps_kernel, static_argnums=(10,)))
    return _KERNEL[0]
