"""One CARLA frame written in the capture layout (``docs/capture_layout.md``), and the CARLA parts
of the capture's header."""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..io import (
    atomic_write_text,
    write_events_npy,
    write_frame,
    write_image,
)
from ..io._atomic import atomic_copy_file
from ..io._capture import frame_dir
from ..io._json import to_json_text, write_json
from ..scene import CaptureConfig, StreetFrame
from ._images import CarlaImages
from ._mounts import CarlaMount, bev_pinhole_fov_deg
from ._readings import checked_events
from ._version import CarlaCaptureError, carla_semantic_tags, has_instance_camera


def _write_raw_images(directory: Path, images: CarlaImages, instant: str, reuse: Path | None = None) -> None:
    """Write checked images (`CarlaImages.checked`) as ``{kind}_{instant}.png``."""
    for kind in CarlaImages.KINDS:
        source = reuse / f"{kind}_curr.png" if reuse is not None else None
        if source is not None and source.is_file():  # the same tick, already encoded: copy its bytes
            atomic_copy_file(source, directory / f"{kind}_{instant}.png")
        else:
            write_image(directory / f"{kind}_{instant}.png", getattr(images, kind))


def write_carla_frame(
    root: str | os.PathLike,
    frame: StreetFrame,
    *,
    faces: Mapping[str, Mapping[str, tuple[CarlaImages, CarlaImages, np.ndarray]]],
    views: Mapping[str, tuple[CarlaImages, CarlaImages, np.ndarray]],
    lidar: np.ndarray,
    semantic_lidar: np.ndarray,
    radar: np.ndarray,
    imu: Mapping[str, Any],
    gnss: Mapping[str, Any],
    prev_from_frame: int | None = None,
    dvs_missing: Sequence[str] = (),
) -> Path:
    """Write one CARLA frame in the capture layout: ``faces[camera][face] = (prev, curr, dvs events)``
    and ``views[name] = (prev, curr, height map at t)`` with raw BGRA images (written unchanged);
    lidar, radar, IMU, GNSS, ego and actors through `jaxfish.io.write_frame`, which lists the frame
    in ``capture.json`` last (a frame is listed only once complete).

    ``prev_from_frame``: a frame already written whose t is this frame's t-1 (consecutive ticks): its
    ``*_curr.png`` files are copied as this frame's ``*_prev.png`` instead of encoding the same
    pixels again (half the PNG encoding of a sequence); the caller guarantees they are the same tick.

    ``dvs_missing``: the faces (``"camera/face"``) whose DVS sent no reading for t within the wait,
    written sorted to the frame's ``carla_frame.json`` as ``{"dvs_missing": [...]}`` (their
    ``dvs.npy`` is empty: no pixel changed, or the reading came too late)."""
    d = frame_dir(root, frame.frame)
    known = {f"{cam}/{face}" for cam, per_face in faces.items() for face in per_face}
    unknown = sorted(set(dvs_missing) - known)
    if unknown:
        raise CarlaCaptureError(f"frame {frame.frame}: dvs_missing names faces {unknown} that are not written "
                                f"(faces are 'camera/face': {sorted(known)})")
    # Every input is checked before the first file is written: a bad one leaves no frame directory.
    faces = {cam: {face: (prev.checked(f"{cam}/{face}", "prev"), curr.checked(f"{cam}/{face}", "curr"),
                          checked_events(events, f"{cam}/{face}"))
                   for face, (prev, curr, events) in per_face.items()} for cam, per_face in faces.items()}
    checked_views = {}
    for name, (prev, curr, height) in views.items():
        prev, curr = prev.checked(name, "prev"), curr.checked(name, "curr")
        hm = np.asarray(height, np.float32)
        if hm.shape != curr.rgb.shape[:2]:
            raise CarlaCaptureError(f"{name}: height map {hm.shape} does not match the image {curr.rgb.shape[:2]}")
        checked_views[name] = (prev, curr, hm)
    before = frame_dir(root, prev_from_frame) if prev_from_frame is not None else None
    for cam, per_face in faces.items():
        for face, (prev, curr, events) in per_face.items():
            fd = d / "cameras" / cam / face
            _write_raw_images(fd, prev, "prev", before / "cameras" / cam / face if before is not None else None)
            _write_raw_images(fd, curr, "curr")
            write_events_npy(fd / "dvs.npy", events)
    for name, (prev, curr, hm) in checked_views.items():
        _write_raw_images(d / name, prev, "prev", before / name if before is not None else None)
        _write_raw_images(d / name, curr, "curr")
        write_image(d / name / "height_curr.exr", hm)
    write_json(d / "carla_frame.json", {"dvs_missing": sorted(set(dvs_missing))}, indent=1, error=CarlaCaptureError)
    return write_frame(root, frame, cameras={}, views={}, lidar=lidar, semantic_lidar=semantic_lidar, radar=radar,
                       imu=imu, gnss=gnss)


def finish_carla_header(
    root: str | os.PathLike,
    *,
    carla_version: str,
    mounts: Mapping[str, CarlaMount],
    bev_altitude_m: float,
    config: CaptureConfig,
    geo: Mapping[str, float] | None = None,
    extra: Mapping[str, Any] | None = None,
) -> None:
    """Complete the files `jaxfish.io.write_capture_header` wrote for a CARLA capture:
    ``capture.json`` gets ``carla_semantic_tags`` of the release, ``carla_version``,
    ``instance_ids`` (False before 0.9.14: instance PNGs then carry actor id 0) and ``extra``;
    ``sensors.json`` gets the exact CARLA mounts, the BEV's stand-in pinhole and the geo-reference."""
    root = Path(root)
    header = json.loads((root / "capture.json").read_text())
    header.update({"carla_semantic_tags": carla_semantic_tags(carla_version), "carla_version": str(carla_version),
                   "instance_ids": has_instance_camera(carla_version)})
    header.update(dict(extra or {}))
    sensors = json.loads((root / "sensors.json").read_text())
    for name, mount in mounts.items():
        if name in sensors:
            sensors[name]["carla_transform"] = mount.as_dict()
    sensors["bev"]["carla_camera"] = {"model": "pinhole", "fov_deg": bev_pinhole_fov_deg(config, bev_altitude_m),
                                      "altitude_m": float(bev_altitude_m)}
    if geo is not None:
        sensors["gnss"]["geo_reference"] = {k: float(geo[k]) for k in ("latitude", "longitude", "altitude")}
    texts = {name: to_json_text(root / name, doc, indent=2, error=CarlaCaptureError)  # both valid before either is written
             for name, doc in (("sensors.json", sensors), ("capture.json", header))}
    for name, text in texts.items():
        atomic_write_text(root / name, text)
