"""The capture layout on disk: what every capture source (embedded scene or CARLA) writes and the
dataset builder reads. The contract is ``docs/capture_layout.md``; this module writes and reads it.

Images use CARLA's raw encodings (`jaxfish.io._carla`): BGRA RGB, 24-bit depth (planar metres),
semantic tag in R, instance (0.9.14+ layout: R tag, G + 256 B actor id). Events, lidar and radar
are ``.npy`` structured/float arrays in CARLA's raw dtypes; metadata is JSON. Writes are atomic.
"""

from __future__ import annotations

import concurrent.futures
import json
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .._errors import ImageError, JaxfishError
from .._sequences import KeptByOwner, acting_for, sequence_owner, usable_cores
from ..calibration import Calibration
from ..cameras import MAX_IMAGE_SIDE
from ..scene import (
    RADAR_DTYPE,
    SEMANTIC_LIDAR_DTYPE,
    Actor,
    CameraCapture,
    CameraImages,
    CaptureConfig,
    SensorMounts,
    StreetFrame,
    bev_camera,
    front_camera,
)
from ._atomic import atomic_copy_file
from ._calibration_json import load_rig, save_rig
from ._carla import (
    DVS_EVENT_DTYPE,
    bgra_to_rgb,
    decode_depth,
    decode_instance,
    decode_semantic,
    encode_depth,
    encode_instance,
    encode_semantic,
    rgb_to_bgra,
)
from ._folder import is_temporary
from ._images import decode_image_bytes, read_image, write_image
from ._json import read_json, regular_file, write_json
from ._npz import load_npy, npy_layout, write_npy

CAPTURE_FORMAT = "jaxfish-capture"
"""Format name and version stored in ``capture.json``."""
CAPTURE_VERSION = 1
INSTANTS = ("prev", "curr")
"""The two instants of every frame, as file-name suffixes: t-1 and t."""


class CaptureError(JaxfishError):
    """A capture directory is missing a file or holds malformed metadata (names file and field)."""


def frame_dir(root: str | os.PathLike, frame: int) -> Path:
    """``ROOT/frames/{frame:06d}``."""
    return Path(root) / "frames" / f"{int(frame):06d}"


def _json(path: Path, obj: Any) -> None:
    write_json(path, obj, indent=2, error=CaptureError)


def _transform(loc, rot) -> dict[str, list[float]]:
    return {"location": [float(v) for v in loc], "rotation": [float(v) for v in rot]}


def actor_to_dict(actor: Actor) -> dict[str, Any]:
    """JSON form of an `Actor` (CARLA units: metres, degrees, m/s, deg/s)."""
    return {
        "id": actor.id,
        "type_id": actor.type_id,
        "category": actor.category,
        "semantic_tag": actor.semantic_tag,
        "is_ego": actor.category == "ego",
        "bounding_box": {"location": list(actor.bbox_location), "extent": list(actor.bbox_extent)},
        "transform_prev": _transform(actor.location_prev, actor.rotation_prev),
        "transform": _transform(actor.location, actor.rotation),
        "velocity": list(actor.velocity),
        "angular_velocity": list(actor.angular_velocity),
        "displacement_m": actor.displacement_m,
    }


def ego_record(frame: StreetFrame) -> dict[str, Any]:
    """The ``ego.json`` record of a frame: frame number, timestamps at t and t-1 (seconds), ego id,
    CARLA transforms at t-1 and t, velocity (m/s), acceleration (m/s^2), angular velocity (deg/s)
    and bounding box."""
    ego = frame.ego
    return {
        "frame": frame.frame, "timestamp_s": frame.timestamp_s, "timestamp_prev_s": frame.timestamp_s - frame.dt_s,
        "id": ego.id, "transform_prev": _transform(ego.location_prev, ego.rotation_prev),
        "transform": _transform(ego.location, ego.rotation),
        "velocity": list(frame.ego_motion.velocity), "acceleration": list(frame.ego_motion.acceleration),
        "angular_velocity": list(frame.ego_motion.angular_velocity),
        "bounding_box": {"location": list(ego.bbox_location), "extent": list(ego.bbox_extent)},
    }


def write_images(directory: Path, images: CameraImages, instant: str, *, copy_from: Path | None = None) -> None:
    """``rgb_, depth_, semantic_, instance_{instant}.png`` (CARLA BGRA encodings) in ``directory``.
    ``copy_from``: a folder whose ``*_curr.png`` files already encode ``images`` (the previous
    frame's, for images at t-1 that are its images at t): their bytes are copied, not encoded."""
    if copy_from is not None:
        for kind in ("rgb", "depth", "semantic", "instance"):
            atomic_copy_file(copy_from / f"{kind}_curr.png", directory / f"{kind}_{instant}.png")
        return
    write_image(directory / f"rgb_{instant}.png", rgb_to_bgra(images.rgb))
    write_image(directory / f"depth_{instant}.png", encode_depth(images.depth_m))
    write_image(directory / f"semantic_{instant}.png", encode_semantic(images.semantic))
    write_image(directory / f"instance_{instant}.png", encode_instance(images.semantic, images.actor_id))


def read_images(directory: Path, instant: str = "curr", *, actor_ids: bool = True,
                reuse: tuple[str, ...] | None = None, size: tuple[int, int] | None = None,
                out: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> CameraImages:
    """Read back what `write_images` wrote (RGB uint8, depth metres float32, tags, actor ids).
    ``actor_ids=False`` skips the instance PNG (`CameraImages.actor_id` is then None): the ground
    truth never reads it (instances come from the 3D boxes). ``reuse``: a key naming the sensor
    (e.g. ``(capture root, camera, face)``) under which decoded ``curr`` images are kept, so that
    a later ``prev`` image that is a byte copy of them (consecutive ticks: see `CaptureReader`) is
    not decoded again; the arrays returned are then read-only. ``size``: the ``(H, W)`` every image
    must have. ``out``: writable ``(rgb (H, W, 3) uint8, depth (H, W) float32, semantic (H, W)
    uint8)`` arrays (e.g. one face of a camera's stack) the images are decoded into, and returned
    in `CameraImages` (as read-only views with ``reuse``: a kept ``curr`` image is a view of
    ``out``, which the caller must then leave unchanged). A wrong size or pixel type raises
    `CaptureError` naming the file; a depth, semantic or instance file that is not a PNG (e.g. a
    JPEG renamed ``.png``: lossy labels and depth) and any path that is not a regular file (a
    FIFO, a directory) raise `ImageError` naming it."""
    if instant not in INSTANTS:
        raise CaptureError(f"{directory}: instant must be one of {INSTANTS}, got {instant!r}")

    def load(kind: str, decode, dst: np.ndarray | None):
        path = directory / f"{kind}_{instant}.png"
        checked = _checked(decode, path, size, dst)
        lossless = kind != "rgb"  # labels and encoded depth: a lossy file would read wrong values
        if reuse is None:
            return checked(read_image(path, lossless=lossless))
        return _decoded_reusing(path, reuse + (kind,), instant, checked, lossless=lossless, out=dst)

    rgb_out, depth_out, sem_out = (None, None, None) if out is None else out
    if size is None and out is not None:
        size = depth_out.shape  # the images must fill the arrays they are decoded into
    rgb = load("rgb", bgra_to_rgb, rgb_out)
    depth = load("depth", decode_depth, depth_out)
    sem = load("semantic", decode_semantic, sem_out)
    if not actor_ids:
        return CameraImages(rgb=rgb, depth_m=depth, semantic=sem, actor_id=None)  # type: ignore[arg-type]
    return CameraImages(rgb=rgb, depth_m=depth, semantic=sem, actor_id=_actor_ids(directory, instant, size))


def _actor_ids(directory: Path, instant: str, size: tuple[int, int] | None) -> np.ndarray:
    """The int32 actor ids of ``instance_{instant}.png`` in ``directory``."""
    path = directory / f"instance_{instant}.png"
    _, ids = _checked(decode_instance, path, size)(read_image(path, lossless=True))
    return ids.astype(np.int32)


def face_stacks(faces: int, size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Empty ``(faces, size, size)`` stacks `read_images` decodes a camera's faces into (``out``):
    RGB ``(..., 3)`` uint8, depth float32 metres, semantic tags uint8."""
    return (aligned_empty((faces, size, size, 3), np.uint8), aligned_empty((faces, size, size), np.float32),
            aligned_empty((faces, size, size), np.uint8))


ARRAY_ALIGNMENT = 64
"""Byte alignment of the arrays `face_stacks` allocates: JAX's CPU backend takes a NumPy array
aligned to 64 bytes as it is (no copy into a buffer of its own on every call of a program)."""


def aligned_empty(shape: tuple[int, ...], dtype) -> np.ndarray:
    """``np.empty(shape, dtype)`` whose data starts at a multiple of `ARRAY_ALIGNMENT` bytes (an
    empty array holds no data: `np.empty`'s own)."""
    dtype = np.dtype(dtype)
    size = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    if size == 0:
        return np.empty(shape, dtype)
    raw = np.empty(size + ARRAY_ALIGNMENT, np.uint8)
    start = -raw.ctypes.data % ARRAY_ALIGNMENT
    return raw[start:start + size].view(dtype).reshape(shape)


def _checked(decode, path: Path, size: tuple[int, int] | None, out: np.ndarray | None = None):
    """``decode`` of the pixels of ``path`` (into ``out`` when given), with its size checked and its
    errors naming the file."""
    def run(pixels: np.ndarray):
        if size is not None and tuple(pixels.shape[:2]) != tuple(size):
            raise CaptureError(f"{path}: image is {pixels.shape[1]}x{pixels.shape[0]}, expected {size[1]}x{size[0]} "
                               "(capture.json 'face_size' / sensors.json)")
        try:
            return decode(pixels) if out is None else decode(pixels, out)
        except ImageError as e:
            raise CaptureError(f"{path}: {e}") from None
    return run


# Decoded ``curr`` images by sensor (the last one read per key and sequence, `jaxfish._sequences`),
# with their file bytes: one frame's worth (~150 MB for four 768-px cube rigs and the BEV) each.
_LAST_CURR = KeptByOwner()


def _decoded_reusing(path: Path, key: tuple[str, ...], instant: str, decode, *, lossless: bool = False,
                     out: np.ndarray | None = None) -> np.ndarray:
    """``decode(read_image(path))``, except that a ``prev`` file whose bytes equal a ``curr`` file
    last read under ``key`` (by any sequence) returns that decoded array (an exact byte comparison,
    never a guess), or copies it into ``out`` when given (the array ``decode`` also writes into)."""
    try:
        regular_file(path, ImageError, "image file")  # a FIFO would block read_bytes forever
        data = path.read_bytes()
    except (OSError, ImageError):
        return decode(read_image(path, lossless=lossless))  # read_image names the file and the reason
    if instant == "prev":
        for kept, arr in _LAST_CURR.values(key):
            if kept == data and (out is None or arr.shape == out.shape):
                if out is None:
                    return arr
                np.copyto(out, arr)
                return out
        return decode(decode_image_bytes(path, data, lossless=lossless))
    arr = decode(decode_image_bytes(path, data, lossless=lossless))
    if out is not None:
        arr = arr.view()  # the caller's array stays writable; the kept view is not
    arr.setflags(write=False)  # shared with later readers
    _LAST_CURR.put(key, (data, arr))
    return arr


# A camera's last ``curr`` face stacks decoded by `CaptureReader.faces_stacks` (rgb, depth,
# semantic; read-only), by ``(capture, camera)`` and sequence: the arrays `_LAST_CURR` keeps for
# its faces are views of them.
_LAST_STACKS = KeptByOwner()

_STACK_KINDS = ("rgb", "depth", "semantic")


def _is_face_of(arr: np.ndarray, stack: np.ndarray, i: int) -> bool:
    """Whether ``arr`` is face ``i`` of ``stack`` (the same memory, shape and strides)."""
    face = stack[i]
    return arr.shape == face.shape and arr.strides == face.strides and arr.ctypes.data == face.ctypes.data


def _kept_stacks(key: tuple[str, ...], directories: Sequence[Path]) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The kept ``curr`` stacks of the camera ``key`` (of any sequence) of which every
    ``{kind}_prev.png`` in its face ``directories`` (in stack order) is a byte copy of the ``curr``
    file its face was decoded from (an exact comparison of the bytes), else None."""
    files: dict[Path, tuple[int, bytes | None]] = {}  # file size, and its bytes once read

    def file_bytes(path: Path, size: int) -> bytes | None:
        """The file's bytes when it has ``size`` bytes (a possible copy), else None: read once."""
        if path not in files:
            try:
                regular_file(path, ImageError, "image file")
                files[path] = (path.stat().st_size, None)
            except (OSError, ImageError):
                files[path] = (-1, None)  # decoded one face at a time, whose errors name the file
        length, data = files[path]
        if length != size:
            return None
        if data is None:
            try:
                data = path.read_bytes()
            except OSError:
                data = b""  # no copy: decoded with the others, whose errors name the file
            files[path] = (length, data)
        return data

    def matches(stacks: tuple[np.ndarray, np.ndarray, np.ndarray]) -> bool:
        for i, directory in enumerate(directories):
            for kind, stack in zip(_STACK_KINDS, stacks, strict=True):
                hit = next((h for h in _LAST_CURR.values(key[:-1] + (key[-1], directory.name, kind))
                            if _is_face_of(h[1], stack, i)), None)
                if hit is None or file_bytes(directory / f"{kind}_prev.png", len(hit[0])) != hit[0]:
                    return False
        return True

    return next((stacks for stacks in _LAST_STACKS.values(key) if matches(stacks)), None)


def forget_decoded_images() -> None:
    """Drop the decoded images `CaptureReader` keeps with ``reuse_decoded=True`` (frees ~150 MB
    per sequence kept)."""
    _LAST_CURR.clear()
    _LAST_STACKS.clear()


def _pose_dict(pose) -> dict[str, Any]:
    return {"rotation_matrix": np.asarray(pose.rotation_matrix, np.float64).tolist(),
            "translation": np.asarray(pose.translation, np.float64).tolist()}


def write_capture_header(
    root: str | os.PathLike,
    rig: Mapping[str, Calibration],
    config: CaptureConfig,
    mounts: SensorMounts,
    *,
    seed: int | None,
    source: str = "embedded",
    dt_s: float = 0.1,
) -> Path:
    """Write ``capture.json`` (no frames yet), ``calibration/*.json`` and ``sensors.json``."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    save_rig(dict(rig), root / "calibration")
    bev, front = bev_camera(config), front_camera(config)
    carla = mounts.carla_transforms()
    sensors = {
        "bev": {"model": "orthographic", "width": bev.width, "height": bev.height,
                "metres_per_pixel": float(bev.metres_per_pixel), "cx": float(bev.cx), "cy": float(bev.cy),
                "camera_to_vehicle": _pose_dict(mounts.bev_camera_to_vehicle), "carla_transform": carla["bev"]},
        "front": {"model": "pinhole", "width": front.width, "height": front.height, "fov_deg": config.front_fov_deg,
                  "fx": float(front.fx), "fy": float(front.fy), "cx": float(front.cx), "cy": float(front.cy),
                  "camera_to_vehicle": _pose_dict(mounts.front_camera_to_vehicle), "carla_transform": carla["front"]},
        "lidar": {"channels": config.lidar_channels, "points_per_channel": config.lidar_points_per_channel,
                  "upper_fov_deg": config.lidar_upper_fov_deg, "lower_fov_deg": config.lidar_lower_fov_deg,
                  "range_m": config.lidar_range_m, "location_vehicle": list(mounts.lidar_location),
                  "carla_transform": carla["lidar"]},
        "radar": {"points": config.radar_points, "horizontal_fov_deg": config.radar_horizontal_fov_deg,
                  "vertical_fov_deg": config.radar_vertical_fov_deg, "range_m": config.radar_range_m,
                  "location_vehicle": list(mounts.radar_location), "carla_transform": carla["radar"]},
        "imu": {"carla_transform": carla["imu"]},
        "gnss": {"carla_transform": carla["gnss"], "geo_reference": {"latitude": 0.0, "longitude": 0.0, "altitude": 0.0}},
        "dvs": {"positive_threshold": config.dvs_threshold, "negative_threshold": config.dvs_threshold,
                "log_eps": config.dvs_log_eps, "substeps": config.dvs_substeps, "time_unit": "ns"},
    }
    _json(root / "sensors.json", sensors)
    header = {
        "format": CAPTURE_FORMAT, "version": CAPTURE_VERSION, "source": source, "seed": seed,
        "carla_semantic_tags": "0.9.10", "dt_s": dt_s, "face_size": config.face_size,
        "faces": list(config.faces), "cameras": list(rig), "frames": [],
    }
    _json(root / "capture.json", header)
    return root


def write_frame(
    root: str | os.PathLike,
    frame: StreetFrame,
    *,
    cameras: Mapping[str, CameraCapture],
    views: Mapping[str, tuple[CameraImages, CameraImages, np.ndarray]],
    lidar: np.ndarray,
    semantic_lidar: np.ndarray,
    radar: np.ndarray,
    imu: Mapping[str, Any],
    gnss: Mapping[str, Any],
    list_frame: bool = True,
    prev_written: bool = False,
) -> Path:
    """Write one frame (layout in ``docs/capture_layout.md``) and list it in ``capture.json``
    (unless ``list_frame=False``: the shards of a capture, which `list_capture_frames` lists once
    they have all finished, leave ``capture.json`` to it). ``prev_written``: the images at t-1 are
    the previous frame's images at t, already written in ``root`` (the frame before it): their
    ``*_prev.png`` files are byte copies of its ``*_curr.png``."""
    root = Path(root)
    d = frame_dir(root, frame.frame)
    before = frame_dir(root, frame.frame - 1) if prev_written else None
    for cam, cap in cameras.items():
        for face in cap.curr:
            fd = d / "cameras" / cam / face
            write_images(fd, cap.prev[face], "prev", copy_from=None if before is None else before / "cameras" / cam / face)
            write_images(fd, cap.curr[face], "curr")
            write_npy(fd / "dvs.npy", np.ascontiguousarray(np.asarray(cap.dvs[face]).astype(DVS_EVENT_DTYPE)))
    for name, (prev, curr, height) in views.items():
        write_images(d / name, prev, "prev", copy_from=None if before is None else before / name)
        write_images(d / name, curr, "curr")
        write_image(d / name / "height_curr.exr", np.asarray(height, np.float32))
    write_npy(d / "lidar.npy", np.ascontiguousarray(lidar, np.float32))
    write_npy(d / "semantic_lidar.npy", np.ascontiguousarray(np.asarray(semantic_lidar).astype(SEMANTIC_LIDAR_DTYPE)))
    write_npy(d / "radar.npy", np.ascontiguousarray(np.asarray(radar).astype(RADAR_DTYPE)))
    _json(d / "imu.json", dict(imu))
    _json(d / "gnss.json", dict(gnss))
    _json(d / "ego.json", ego_record(frame))
    _json(d / "actors.json", {"frame": frame.frame, "timestamp_s": frame.timestamp_s,
                              "actors": [actor_to_dict(a) for a in frame.actors]})
    if list_frame:
        header_path = root / "capture.json"
        header = json.loads(header_path.read_text())
        header["frames"] = sorted(set(header["frames"]) | {frame.frame})
        _json(header_path, header)
    return d


def list_capture_frames(root: str | os.PathLike, frames: Sequence[int]) -> Path:
    """Set ``capture.json``'s ``frames`` to ``frames`` (sorted, without repeats), atomically: the
    bytes `write_frame` leaves after writing those frames into a fresh header. A missing or
    malformed ``capture.json`` raises `CaptureError` naming it."""
    header_path = Path(root) / "capture.json"
    try:
        header = json.loads(header_path.read_text())
    except (OSError, ValueError) as e:
        raise CaptureError(f"{header_path}: not a readable capture header ({type(e).__name__}: {e})") from None
    if not isinstance(header, dict) or "frames" not in header:
        raise CaptureError(f"{header_path}: field 'frames' missing")
    header["frames"] = sorted({int(f) for f in frames})
    _json(header_path, header)
    return header_path


def check_capture_folder(root: str | os.PathLike) -> Path:
    """Refuse (`CaptureError`) a folder a capture must not be written into: a path that is not a
    folder, or a folder that holds files and is not a jaxfish capture (a ``capture.json`` of format
    ``jaxfish-capture``; a folder holding only what `write_capture_header` writes before it,
    the shard locks of ``.shards/`` or jaxfish's temporary files, counts as one). Returns the path."""
    root = Path(root)
    if root.exists() and not root.is_dir():
        raise CaptureError(f"{root}: not a folder (a capture is written into a folder)")
    if not root.is_dir():
        return root
    names = sorted(p.name for p in root.iterdir())
    if not names or all(n in ("calibration", "sensors.json", ".shards") or is_temporary(n) for n in names):
        return root
    header = root / "capture.json"
    try:
        ours = json.loads(header.read_text()).get("format") == CAPTURE_FORMAT
    except (OSError, ValueError, AttributeError):
        ours = False
    if not ours:
        raise CaptureError(f"{root}: not empty and not a jaxfish capture (it holds {', '.join(names[:3])}"
                           f"{' ...' if len(names) > 3 else ''}; no capture.json of format {CAPTURE_FORMAT!r}): "
                           f"write the capture into a new or empty folder")
    return root


MAX_ACTOR_ID = 65535
"""Largest actor id of ``actors.json``: instance ids are 16 bits (the capture's ``instance_*.png``
stores G + 256 B, the dataset's instance PNGs are uint16)."""
CARLA_TAG_TABLES = ("0.9.10", "0.9.14")
"""Values of ``capture.json``'s ``carla_semantic_tags``: the tag table of CARLA 0.9.10-0.9.13 or of 0.9.14+."""


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


MAX_COORDINATE = 1e6
"""Largest magnitude (metres, or degrees for rotations) of a location, box extent or rotation read
from ``actors.json`` / ``ego.json``: 1000 km, beyond any CARLA map, and small enough that box
corners, displacements and their float32 products stay finite."""


def _check_vector(record: dict[str, Any], key: str, path: Path, field: str, *, bound: float | None = None) -> list[float]:
    v = record.get(key)
    if not (isinstance(v, list) and len(v) == 3 and all(_is_number(x) for x in v)):
        raise CaptureError(f"{path}: field '{field}': expected 3 finite numbers, got {v!r}")
    if bound is not None and not all(abs(x) <= bound for x in v):
        raise CaptureError(f"{path}: field '{field}': expected 3 numbers of magnitude at most {bound:g}, got {v!r}")
    return v


def _check_transform(record: dict[str, Any], key: str, path: Path, field: str) -> None:
    t = record.get(key)
    if not isinstance(t, dict):
        raise CaptureError(f"{path}: field '{field}': expected {{'location': [x, y, z], 'rotation': [pitch, yaw, roll]}}")
    _check_vector(t, "location", path, f"{field}.location", bound=MAX_COORDINATE)
    _check_vector(t, "rotation", path, f"{field}.rotation", bound=MAX_COORDINATE)


def _check_actors(actors: list[Any], path: Path) -> None:
    """The fields of ``actors.json`` records that the ground truth uses (docs/capture_layout.md)."""
    seen: set[int] = set()
    for i, a in enumerate(actors):
        where = f"actors[{i}]"
        if not isinstance(a, dict):
            raise CaptureError(f"{path}: field '{where}': expected an actor record")
        aid = a.get("id")
        if not isinstance(aid, int) or isinstance(aid, bool) or aid <= 0:
            raise CaptureError(f"{path}: field '{where}.id': expected a positive integer, got {aid!r}")
        if aid > MAX_ACTOR_ID:
            raise CaptureError(f"{path}: field '{where}.id': actor id {aid} above {MAX_ACTOR_ID} (instance ids are "
                               "16 bits: the capture's G + 256 B and the dataset's instance PNGs)")
        if aid in seen:
            raise CaptureError(f"{path}: field '{where}.id': actor id {aid} appears twice")
        seen.add(aid)
        where = f"actors[{i}] (id {aid})"
        box = a.get("bounding_box")
        if not isinstance(box, dict):
            raise CaptureError(f"{path}: field '{where}.bounding_box': expected {{'location': [...], 'extent': [...]}}")
        _check_vector(box, "location", path, f"{where}.bounding_box.location", bound=MAX_COORDINATE)
        extent = _check_vector(box, "extent", path, f"{where}.bounding_box.extent", bound=MAX_COORDINATE)
        if min(extent) < 0:
            raise CaptureError(f"{path}: field '{where}.bounding_box.extent': half sizes must be >= 0, got {extent}")
        if max(extent) == 0 and a.get("category") != "two_wheeler":  # CARLA's zero two-wheeler axes are fixed
            raise CaptureError(f"{path}: field '{where}.bounding_box.extent': zero-size box {extent}")
        for key in ("transform_prev", "transform"):
            _check_transform(a, key, path, f"{where}.{key}")


def _check_header(meta: dict[str, Any], header: Path) -> None:
    """Types and values of ``capture.json``'s fields (each problem names the field)."""
    from ..reprojection import FIVE_FACES

    def bad(field: str, expected: str) -> CaptureError:
        return CaptureError(f"{header}: field '{field}': expected {expected}, got {meta.get(field)!r}")

    if meta["version"] != CAPTURE_VERSION:
        raise bad("version", f"{CAPTURE_VERSION} (the capture layout this jaxfish reads)")
    frames = meta["frames"]
    if not isinstance(frames, list) or not all(isinstance(f, int) and not isinstance(f, bool) and f >= 0 for f in frames):
        raise bad("frames", "a list of non-negative integers")
    if len(set(frames)) != len(frames):
        raise bad("frames", "distinct frame numbers")
    cams = meta["cameras"]
    if not isinstance(cams, list) or not cams or not all(isinstance(c, str) and c and "/" not in c for c in cams):
        raise bad("cameras", "a non-empty list of camera names")
    if len(set(cams)) != len(cams):
        raise bad("cameras", "distinct camera names")
    faces = meta["faces"]
    known = FIVE_FACES + ("back",)
    if not isinstance(faces, list) or not faces or not all(f in known for f in faces) or len(set(faces)) != len(faces):
        raise bad("faces", f"distinct cube faces of {known}")
    size = meta.get("face_size", 1)
    if not isinstance(size, int) or isinstance(size, bool) or size <= 0:
        raise bad("face_size", "a positive number of pixels")
    if size > MAX_IMAGE_SIDE:
        raise bad("face_size", f"at most {MAX_IMAGE_SIDE} pixels")
    tags = meta.get("carla_semantic_tags", "0.9.10")
    if tags not in CARLA_TAG_TABLES:
        raise bad("carla_semantic_tags", f"one of {CARLA_TAG_TABLES}")
    dt = meta.get("dt_s", 0.1)
    if not (_is_number(dt) and dt > 0):
        raise bad("dt_s", "a positive finite number of seconds (the time between t-1 and t)")


def _existing(path: Path) -> None:
    """`CaptureError` naming ``path`` unless it is a regular file (missing: "file missing"; a
    directory, a FIFO, a symbolic link loop: what it is, before anything blocks on reading it)."""
    try:
        regular_file(path, CaptureError)
    except FileNotFoundError:
        raise CaptureError(f"{path}: file missing") from None


def _check_events_array(path: Path, dtype: np.dtype, shape: tuple[int, ...]) -> None:
    """`CaptureError` naming ``path`` unless it holds a 1-D `DVS_EVENT_DTYPE` array."""
    if dtype != DVS_EVENT_DTYPE:
        raise CaptureError(f"{path}: expected dtype {DVS_EVENT_DTYPE}, got {dtype}")
    if len(shape) != 1:
        raise CaptureError(f"{path}: expected a 1-D array of events, got shape {tuple(shape)}")


def _check_events_range(path: Path, ev: np.ndarray, face_size: int | None) -> None:
    """`CaptureError` naming ``path`` and the field when an event lies outside the ``face_size``
    face (no check for None)."""
    if face_size is not None and ev.size:
        for axis in ("x", "y"):
            top = int(ev[axis].max())
            if top >= face_size:
                raise CaptureError(f"{path}: field '{axis}': event at {axis} = {top} outside the {face_size}-px face")


class DeferredEvents:
    """A face's DVS events in a capture's ``dvs.npy``, read when converted to an array
    (`CaptureReader.dvs` with ``defer=True``): ``np.asarray`` of it reads the `count` events
    (`DVS_EVENT_DTYPE`, t in ns) from the file, checks that they lie on the ``face_size`` face and
    returns them, a new array each time, so that a frame holds none of them until they are used.
    The file's header was checked when it was made; a file changed since then (shorter, or an
    event outside the face) raises `CaptureError` naming it."""

    __slots__ = ("path", "count", "_offset", "_face_size")

    def __init__(self, path: Path, count: int, offset: int, face_size: int | None):
        self.path, self.count, self._offset, self._face_size = Path(path), int(count), int(offset), face_size

    @property
    def shape(self) -> tuple[int]:
        """``(count,)``: the shape of the array it reads."""
        return (self.count,)

    @property
    def dtype(self) -> np.dtype:
        """`DVS_EVENT_DTYPE`: the dtype of the array it reads."""
        return DVS_EVENT_DTYPE

    def __len__(self) -> int:
        return self.count

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        if copy is False:
            raise ValueError(f"{self.path}: events read from a file are a new array (copy=False)")
        _existing(self.path)
        try:
            ev = np.fromfile(self.path, DVS_EVENT_DTYPE, self.count, offset=self._offset)
        except OSError as e:
            raise CaptureError(f"{self.path}: not a readable .npy array ({e})") from None
        if ev.size < self.count:
            raise CaptureError(f"{self.path}: holds {ev.size} events, {self.count} when its frame was read")
        _check_events_range(self.path, ev, self._face_size)
        return ev if dtype is None else ev.astype(dtype, copy=False)

    def __repr__(self) -> str:
        return f"DeferredEvents({str(self.path)!r}, count={self.count})"


class CaptureReader:
    """Read a capture directory (any source) laid out as ``docs/capture_layout.md``.

    ``reuse_decoded=True`` keeps the decoded ``curr`` images of the cube faces and views (one frame's
    worth per process, shared by readers: `forget_decoded_images` drops them): a frame whose
    ``*_prev.png`` files are byte copies of the previous frame's ``*_curr.png`` (what
    ``scripts/carla_capture.py`` writes for consecutive ticks) then decodes only its ``curr``
    images when frames are read in order. The dataset builder turns it on."""

    def __init__(self, root: str | os.PathLike, *, reuse_decoded: bool = False):
        self.root = Path(root)
        self._reuse_key = (str(self.root.resolve()),) if reuse_decoded else None  # the capture, once
        self._sensors: dict[str, Any] | None = None
        header = self.root / "capture.json"
        try:
            regular_file(header, CaptureError)
        except FileNotFoundError:
            raise CaptureError(f"{header}: not a capture directory (capture.json missing)") from None
        self.meta: dict[str, Any] = read_json(header, CaptureError, obj=True)
        for key in ("format", "version", "frames", "cameras", "faces"):
            if key not in self.meta:
                raise CaptureError(f"{header}: field '{key}' missing")
        if self.meta["format"] != CAPTURE_FORMAT:
            raise CaptureError(f"{header}: field 'format' is {self.meta['format']!r}, expected {CAPTURE_FORMAT!r}")
        _check_header(self.meta, header)

    @property
    def frames(self) -> list[int]:
        """Frame numbers written so far."""
        return list(self.meta["frames"])

    @property
    def cameras(self) -> list[str]:
        """Fisheye camera names of the rig."""
        return list(self.meta["cameras"])

    @property
    def faces(self) -> list[str]:
        """Cube faces rendered per camera, in `CubeRig` order."""
        return list(self.meta["faces"])

    def rig(self) -> dict[str, Calibration]:
        """The calibration of every fisheye camera (``calibration/*.json``)."""
        for name in self.cameras:
            path = self.root / "calibration" / f"{name}.json"
            if not os.path.lexists(path):  # anything else there (a FIFO, a loop) is named by load_calibration
                raise CaptureError(f"{self.root / 'capture.json'}: field 'cameras' lists {name!r} but {path} is missing")
        return load_rig(self.root / "calibration", names=tuple(self.cameras))

    def sensors(self) -> dict[str, Any]:
        """``sensors.json``: BEV, front, lidar, radar, IMU, GNSS and DVS settings and mounts (read
        once per reader: every view, the BEV checks and the builder ask for it per sample)."""
        if self._sensors is None:
            self._sensors = self._read_json(self.root / "sensors.json")
        return self._sensors

    def _read_json(self, path: Path) -> Any:
        _existing(path)
        return read_json(path, CaptureError, obj=True)

    def _frame(self, frame: int) -> Path:
        d = frame_dir(self.root, frame)
        if not d.is_dir():
            raise CaptureError(f"{d}: frame {frame} missing from the capture")
        return d

    def ego(self, frame: int) -> dict[str, Any]:
        """``ego.json`` of a frame (CARLA transforms at t-1 and t, velocity, acceleration); a
        missing or non-finite field raises `CaptureError` naming the file and field."""
        path = self._frame(frame) / "ego.json"
        ego = self._read_json(path)
        if not isinstance(ego, dict):
            raise CaptureError(f"{path}: field '<root>': expected an object")
        for key in ("transform_prev", "transform"):
            _check_transform(ego, key, path, key)
        for key in ("velocity", "acceleration", "angular_velocity"):
            _check_vector(ego, key, path, key)
        for key in ("timestamp_s", "timestamp_prev_s"):
            if not _is_number(ego.get(key)):
                raise CaptureError(f"{path}: field '{key}': expected a finite number, got {ego.get(key)!r}")
        return ego

    def actors(self, frame: int) -> list[dict[str, Any]]:
        """The actors of a frame (``actors.json``); a malformed record (missing or non-finite pose
        or box, negative or zero-size box, repeated id) raises `CaptureError` naming the file, the
        actor and the field."""
        path = self._frame(frame) / "actors.json"
        doc = self._read_json(path)
        if not isinstance(doc, dict) or not isinstance(doc.get("actors"), list):
            raise CaptureError(f"{path}: field 'actors': expected a list of actor records")
        _check_actors(doc["actors"], path)
        return doc["actors"]

    def face(self, frame: int, camera: str, face: str, instant: str = "curr", *, actor_ids: bool = True,
             out: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> CameraImages:
        """One cube face's images at ``"prev"`` (t-1) or ``"curr"`` (t) (``actor_ids``, ``out``:
        see `read_images`)."""
        reuse = None if self._reuse_key is None else self._reuse_key + (camera, face)
        size = self.meta.get("face_size")
        return read_images(self._frame(frame) / "cameras" / camera / face, instant, actor_ids=actor_ids, reuse=reuse,
                           size=None if size is None else (size, size), out=out)

    def faces_stack(self, frame: int, camera: str, instant: str = "curr", *, actor_ids: bool = True) -> CameraImages:
        """All faces of a camera stacked on a leading face axis (the `CubeRig` order of `faces`);
        ``actor_ids=False`` skips the instance PNGs (`CameraImages.actor_id` None). See
        `faces_stacks`."""
        return self.faces_stacks(frame, [(camera, instant)], actor_ids=actor_ids)[(camera, instant)]

    def faces_stacks(self, frame: int, views: Sequence[tuple[str, str]], *,
                     actor_ids: bool = True) -> dict[tuple[str, str], CameraImages]:
        """`faces_stack` of every ``(camera, instant)`` in ``views``, all faces decoded in one pool
        of `decode_threads` threads (PNG decoding releases the GIL). With ``capture.json``'s
        ``face_size`` the RGB, depth and semantic images are decoded straight into the stacks, which
        are returned read-only (JAX programs read these aligned arrays in place, without a copy, so
        they must not change while a computation on them may still run); without it each face is
        decoded alone, then stacked. With ``reuse_decoded``, a ``prev`` view whose RGB, depth and
        semantic files are all byte copies of the ``curr`` files this reader last decoded into a
        camera's stacks returns those stacks themselves (the same read-only arrays, nothing
        decoded or copied)."""
        size = self.meta.get("face_size")
        n = len(self.faces)
        kept: dict[tuple[str, str], tuple[np.ndarray, np.ndarray, np.ndarray] | None] = {}
        owner = sequence_owner()  # the sequence these decodes continue, whichever thread decodes them
        prev = [v for v in views if v[1] == "prev"] if size is not None and self._reuse_key is not None else []
        if prev:  # a camera whose prev files are byte copies of the curr files it last decoded: its curr stacks
            def check(view: tuple[str, str]):
                camera = view[0]
                with acting_for(owner):
                    return _kept_stacks(self._reuse_key + (camera,),
                                        [self._frame(frame) / "cameras" / camera / f for f in self.faces])
            with concurrent.futures.ThreadPoolExecutor(max(1, min(len(prev), decode_threads()))) as pool:
                kept = dict(zip(prev, pool.map(check, prev), strict=True))
        todo = [v for v in views if kept.get(v) is None]
        stacks = {v: None if size is None else face_stacks(n, int(size)) for v in todo}
        jobs = [(v, i) for v in todo for i in range(n)]

        def read(job: tuple[tuple[str, str], int]) -> CameraImages:
            (camera, instant), i = job
            out = stacks[(camera, instant)]
            with acting_for(owner):
                return self.face(frame, camera, self.faces[i], instant, actor_ids=actor_ids,
                                 out=None if out is None else tuple(a[i] for a in out))

        with concurrent.futures.ThreadPoolExecutor(max(1, min(len(jobs) or 1, decode_threads()))) as pool:
            imgs = dict(zip(jobs, pool.map(read, jobs), strict=True))
            reused = [(v, i) for v in views if kept.get(v) is not None for i in range(n)] if actor_ids else []
            ids_of = dict(zip(reused, pool.map(  # the instance PNGs of the views handed on
                lambda job: _actor_ids(self._frame(frame) / "cameras" / job[0][0] / self.faces[job[1]], "prev",
                                       (int(size), int(size))), reused), strict=True))
        result = {}
        for v in views:
            faces = [imgs[(v, i)] for i in range(n)] if v in stacks else []
            out = kept.get(v) or stacks[v]
            if out is None:
                out = tuple(np.stack([getattr(f, k) for f in faces]) for k in ("rgb", "depth_m", "semantic"))
            elif v in stacks:  # kept for later readers with ``reuse_decoded`` (`read_images`'s ``reuse``); read in place by JAX
                for a in out:
                    a.setflags(write=False)
                if v[1] == "curr" and self._reuse_key is not None:
                    _LAST_STACKS.put(self._reuse_key + (v[0],), out)
            if v in stacks:
                ids = None if faces[0].actor_id is None else np.stack([f.actor_id for f in faces])
            else:
                ids = np.stack([ids_of[(v, i)] for i in range(n)]) if actor_ids else None
            result[v] = CameraImages(*out, ids)
        return result

    def dvs(self, frame: int, camera: str, face: str, *, defer: bool = False) -> np.ndarray | DeferredEvents:
        """DVS events of a face between t-1 and t (`DVS_EVENT_DTYPE`, t in ns); an event outside
        the face (``x`` or ``y`` >= ``face_size``) raises `CaptureError` naming the file and field.
        ``defer``: a `DeferredEvents` instead, the file's header checked now and its events read
        and checked when it is converted (``np.asarray``); a file whose header it cannot read
        that way (a version 3.0 ``.npy`` header) is read now."""
        path = self._frame(frame) / "cameras" / camera / face / "dvs.npy"
        size = self.meta.get("face_size")
        if defer:
            _existing(path)
            try:
                with open(path, "rb") as fh:
                    layout = npy_layout(fh)
            except (ValueError, OSError, EOFError) as e:
                raise CaptureError(f"{path}: not a readable .npy array ({e})") from None
            if layout is not None:
                dtype, shape, offset = layout
                _check_events_array(path, dtype, shape)
                return DeferredEvents(path, shape[0], offset, size)
        ev = self._npy(path)
        _check_events_array(path, ev.dtype, ev.shape)
        _check_events_range(path, ev, size)
        return ev

    def view(self, frame: int, name: str, instant: str = "curr", *, actor_ids: bool = True) -> CameraImages:
        """The ``"bev"`` or ``"front"`` camera's images (``actor_ids``: see `read_images`)."""
        reuse = None if self._reuse_key is None else self._reuse_key + (name,)
        spec = self.sensors().get(name)
        size = None
        if isinstance(spec, dict) and "width" in spec and "height" in spec:
            try:
                size = (int(spec["height"]), int(spec["width"]))
            except (TypeError, ValueError):
                raise CaptureError(f"{self.root / 'sensors.json'}: field '{name}.width/height': expected whole numbers, "
                                   f"got {spec['width']!r} x {spec['height']!r}") from None
        return read_images(self._frame(frame) / name, instant, actor_ids=actor_ids, reuse=reuse, size=size)

    def height(self, frame: int, name: str = "bev") -> np.ndarray:
        """Height map (metres above the ground, float32) of the ``"bev"`` or ``"front"`` view at t; a
        NaN or infinite height raises `CaptureError` naming the file and the first such pixel."""
        path = self._frame(frame) / name / "height_curr.exr"
        h = read_image(path)[..., 0]
        bad = ~np.isfinite(h)
        if bad.any():
            row, col = (int(i) for i in np.argwhere(bad)[0])
            raise CaptureError(f"{path}: {int(bad.sum())} height(s) are not finite numbers, the first {h[row, col]} "
                               f"at pixel (u={col}, v={row})")
        return h

    def _npy(self, path: Path, dtype=None, columns: int | None = None) -> np.ndarray:
        _existing(path)
        try:
            a = load_npy(path)
        except (ValueError, OSError, EOFError) as e:
            raise CaptureError(f"{path}: not a readable .npy array ({e})") from None
        if dtype is not None and a.dtype != np.dtype(dtype):
            raise CaptureError(f"{path}: expected dtype {np.dtype(dtype)}, got {a.dtype}")
        if columns is not None and (a.ndim != 2 or a.shape[1] != columns):
            raise CaptureError(f"{path}: expected an (N, {columns}) array, got shape {a.shape}")
        return a

    def _finite(self, path: Path, a: np.ndarray) -> np.ndarray:
        """``a``, after checking that its floating-point values (every float field of a structured
        array) are finite: a NaN would reach the dataset's ``lidar_data`` as is."""
        fields = a.dtype.names or (None,)
        for name in fields:
            values = a if name is None else a[name]
            if values.dtype.kind == "f" and not np.all(np.isfinite(values)):
                where = "" if name is None else f" field '{name}':"
                raise CaptureError(f"{path}:{where} {int(np.sum(~np.isfinite(values)))} value(s) are not finite numbers")
        return a

    def lidar(self, frame: int) -> np.ndarray:
        """Lidar points ``(N, 4)`` float32 ``x, y, z, intensity`` (sensor frame, Unreal axes)."""
        path = self._frame(frame) / "lidar.npy"
        return self._finite(path, self._npy(path, columns=4))

    def semantic_lidar(self, frame: int) -> np.ndarray:
        """Semantic lidar points (CARLA's ``SemanticLidarDetection`` dtype)."""
        path = self._frame(frame) / "semantic_lidar.npy"
        return self._finite(path, self._npy(path))

    def radar(self, frame: int) -> np.ndarray:
        """Radar detections (``velocity, azimuth, altitude, depth``)."""
        path = self._frame(frame) / "radar.npy"
        return self._finite(path, self._npy(path))

    def imu(self, frame: int) -> dict[str, Any]:
        """IMU reading at t."""
        return self._read_json(self._frame(frame) / "imu.json")

    def gnss(self, frame: int) -> dict[str, Any]:
        """GNSS fix at t."""
        return self._read_json(self._frame(frame) / "gnss.json")


DECODE_THREADS = 4
"""The most threads `CaptureReader.faces_stacks` decodes a frame's faces with. A face's decode is
mostly inflating and unfiltering into fresh memory: beyond a few threads they contend for memory
bandwidth and the GIL, and more threads add CPU time without shortening the decode
(docs/performance.md, "On a GPU")."""


def decode_threads() -> int:
    """Threads `CaptureReader.faces_stacks` decodes with: `DECODE_THREADS`, or fewer where this
    process may run on fewer cores (its CPU affinity: a pinned dask worker's share)."""
    return min(DECODE_THREADS, usable_cores())

