"""One CARLA frame assembled in memory: what a capture reader would decode from the files
`write_carla_frame` writes, without writing them (the capture program's online mode)."""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any

import numpy as np

from ..io._capture import actor_to_dict, ego_record
from ..io._json import to_json_text
from ..pipeline import CameraFrame, CubeFaces, Frame, SensorRecords, ViewFrame, ViewImages, motion_from_records
from ..scene import RADAR_DTYPE, SEMANTIC_LIDAR_DTYPE, StreetFrame
from ._images import CarlaImages
from ._readings import checked_events
from ._version import CarlaCaptureError


def _as_read(what: str, doc: Any) -> Any:
    """``doc`` as a JSON reader returns it after a writer wrote it (lists, floats, strict JSON: a NaN
    raises `CarlaCaptureError` naming ``what`` and the field)."""
    return json.loads(to_json_text(what, doc, error=CarlaCaptureError))


def carla_frame_records(street: StreetFrame) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """``(actors, ego)`` of a CARLA frame (`carla_street_frame`): the records of ``actors.json`` and
    the content of ``ego.json``, equal to what `jaxfish.io.CaptureReader.actors` and ``ego`` return
    for the frame `write_carla_frame` writes (JSON types: lists and floats)."""
    if not street.actors or street.actors[0].category != "ego":
        raise CarlaCaptureError(f"frame {street.frame}: the first actor must be the ego vehicle")
    ego_doc = ego_record(street)
    actors = [actor_to_dict(a) for a in street.actors]
    where = f"frame {street.frame}"
    return _as_read(f"{where} actors.json", actors), _as_read(f"{where} ego.json", ego_doc)


def carla_frame_sensors(
    street: StreetFrame,
    *,
    lidar: np.ndarray,
    semantic_lidar: np.ndarray,
    radar: np.ndarray,
    imu: Mapping[str, Any],
    gnss: Mapping[str, Any],
) -> dict[str, Any]:
    """The other sensors of a CARLA frame as a capture reader returns them (``lidar`` float32
    ``(N, 4)``, ``semantic_lidar`` / ``radar`` in `jaxfish.scene.SEMANTIC_LIDAR_DTYPE` /
    `jaxfish.scene.RADAR_DTYPE`, ``imu`` / ``gnss`` as their JSON files read back); a lidar array
    that is not ``(N, 4)`` or a non-finite value raises `CarlaCaptureError`."""
    where = f"frame {street.frame}"
    points = np.asarray(lidar, np.float32)
    if points.ndim != 2 or points.shape[1] != 4:
        raise CarlaCaptureError(f"{where}: lidar must be (N, 4) x, y, z, intensity, got shape {points.shape}")
    out = {"lidar": np.ascontiguousarray(points),
           "semantic_lidar": np.ascontiguousarray(np.asarray(semantic_lidar).astype(SEMANTIC_LIDAR_DTYPE)),
           "radar": np.ascontiguousarray(np.asarray(radar).astype(RADAR_DTYPE))}
    for name, a in out.items():
        for field in a.dtype.names or (None,):
            values = a if field is None else a[field]
            if values.dtype.kind == "f" and not np.all(np.isfinite(values)):
                label = name if field is None else f"{name} field '{field}'"
                raise CarlaCaptureError(f"{where}: {label}: {int(np.sum(~np.isfinite(values)))} value(s) are not finite")
    out["imu"] = _as_read(f"{where} imu.json", dict(imu))
    out["gnss"] = _as_read(f"{where} gnss.json", dict(gnss))
    return out


def carla_frame(
    street: StreetFrame,
    *,
    tag_table: str,
    faces: Mapping[str, Mapping[str, tuple[CarlaImages, CarlaImages, np.ndarray]]],
    bev: tuple[CarlaImages, CarlaImages, np.ndarray] | None,
    lidar: np.ndarray,
    semantic_lidar: np.ndarray,
    radar: np.ndarray,
    imu: Mapping[str, Any],
    gnss: Mapping[str, Any],
) -> Frame:
    """One CARLA frame as a `jaxfish.pipeline.Frame`, from the same arrays `write_carla_frame` takes:
    ``faces[camera][face] = (prev, curr, dvs events)`` with the faces of every camera in the
    capture's face order and the cameras in the order the frame lists them (`jaxfish.dataset`'s
    sources use the dataset order FV, RV, MVL, MVR), ``bev = (prev, curr, height map at t)`` (or
    None), raw BGRA images.

    The Frame equals, array for array, the one `jaxfish.dataset.CaptureSource` reads from the frame
    `write_carla_frame` writes from these arrays: the images decoded with `jaxfish.io`'s CARLA codecs
    (`CarlaImages.decoded`: RGB, 24-bit depth in metres, semantic tags), the records as their JSON
    files read back (`carla_frame_records`, `carla_frame_sensors`). ``tag_table`` is the capture's
    ``carla_semantic_tags`` (`carla_semantic_tags` of the server version)."""
    actors, ego = carla_frame_records(street)
    sensors = carla_frame_sensors(street, lidar=lidar, semantic_lidar=semantic_lidar, radar=radar, imu=imu, gnss=gnss)
    camera_frames = []
    for cam, per_face in faces.items():
        stacks = {}
        for instant, i in (("prev", 0), ("curr", 1)):
            imgs = [images[i].decoded(f"{cam}/{face}", instant) for face, images in per_face.items()]
            stacks[instant] = CubeFaces(rgb=np.stack([m.rgb for m in imgs]), depth_m=np.stack([m.depth_m for m in imgs]),
                                        semantic=np.stack([m.semantic for m in imgs]))
        events = tuple(checked_events(images[2], f"{cam}/{face}") for face, images in per_face.items())
        camera_frames.append(CameraFrame(faces_prev=stacks["prev"], faces=stacks["curr"], events=events))
    view = None
    if bev is not None:
        prev, curr, height = bev
        images = [im.decoded("bev", instant) for im, instant in ((prev, "prev"), (curr, "curr"))]
        hm = np.asarray(height, np.float32)
        if hm.shape != images[1].rgb.shape[:2]:
            raise CarlaCaptureError(f"bev: height map {hm.shape} does not match the image {images[1].rgb.shape[:2]}")
        view = ViewFrame(*(ViewImages(im.rgb, im.depth_m, im.semantic) for im in images), hm)
    return Frame(index=int(street.frame), carla_tags=str(tag_table), cameras=tuple(faces),
                 camera_frames=tuple(camera_frames), motion=motion_from_records(actors, ego), bev=view,
                 sensors=SensorRecords(ego=ego, **sensors))
