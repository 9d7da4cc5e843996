"""The embedded street scene rendered to a capture directory (``docs/capture_layout.md``): the
embedded scene as a capture source writes it, frame by frame, through `jaxfish.io`'s capture writer."""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np

from .._errors import JaxfishError
from ..calibration import Calibration
from ..cameras import MAX_IMAGE_SIDE
from ..io import CaptureError, check_capture_folder, write_capture_header, write_frame
from ..io._folder import folder_lock, remove_temporaries, shard_lock
from ..scene import (
    CaptureConfig,
    SensorMounts,
    bev_camera,
    front_camera,
    generate_street,
    sensor_mounts,
    simulate_camera,
    simulate_gnss,
    simulate_imu,
    simulate_lidar,
    simulate_radar,
    simulate_view,
)
from ._sources import MAX_FRAMES


def synthesize_capture(
    root: str | os.PathLike,
    rig: Mapping[str, Calibration],
    *,
    frames: int = 1,
    seed: int = 0,
    config: CaptureConfig | None = None,
    progress: Callable[[str], None] | None = None,
    shard=None,
) -> Path:
    """Render ``frames`` frames of the embedded street scene with ``rig`` and write the capture.

    ``root`` must be new, empty or a jaxfish capture (`check_capture_folder`); it is locked while
    the capture is written (a second writer meanwhile raises `CaptureError`) and the temporary
    files a killed run left in it are removed first (only jaxfish's own). An existing capture's
    files are overwritten with the new ones; files jaxfish does not write there are kept.
    ``progress`` is called with a short description after every step (a camera, a view, ...).
    A ``config`` image side (face, BEV, front camera) beyond `jaxfish.cameras.MAX_IMAGE_SIDE`
    raises `CaptureError` before ``root`` is created or written.

    ``shard=(I, N)`` (a `jaxfish.dataset.Shard`) renders only shard I of N of the frames (frame k
    when k mod N = I; every frame is a function of ``seed`` and its number alone, so any split
    renders the same frames): N runs, on as many machines sharing ``root``, each lock only their
    shard (`jaxfish.io._folder.shard_lock`), remove only their own frames' temporary files, write
    the same header files, leave ``capture.json``'s frame list empty and write, last, their record
    ``.shards/{I}-of-{N}.json``; `jaxfish.dataset.merge_shards` (``jaxfish merge``) then lists the
    frames, giving the bytes of one run.
    """
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= int(seed) < 2**63:
        raise CaptureError(f"synthesize_capture: seed must be an integer from 0 to 2**63 - 1, got {seed!r}")
    if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or not 1 <= int(frames) <= MAX_FRAMES:
        raise CaptureError(f"synthesize_capture: frames must be an integer from 1 to {MAX_FRAMES}, got {frames!r}")
    config = config or CaptureConfig()
    from ._shards import SHARDS_DIR, as_shard

    try:
        shard = as_shard(shard)
    except JaxfishError as e:
        raise CaptureError(f"synthesize_capture: {e}") from None
    for name in ("face_size", "bev_size", "front_width", "front_height"):  # refused before anything is written
        if int(getattr(config, name)) > MAX_IMAGE_SIDE:
            raise CaptureError(f"synthesize_capture: CaptureConfig.{name} {getattr(config, name)} exceeds "
                               f"{MAX_IMAGE_SIDE} pixels per side")
    mounts = sensor_mounts(rig, config)
    root = check_capture_folder(root)
    root.mkdir(parents=True, exist_ok=True)
    if shard is None:
        with folder_lock(root, CaptureError, "capture writer"):
            remove_temporaries(root)
            _synthesize_locked(root, rig, list(range(int(frames))), int(seed), config, mounts, progress)
        return root
    own = shard.select(range(int(frames)))
    owned = {Path("frames") / f"{k:06d}" for k in own}
    with shard_lock(root, root / SHARDS_DIR, shard.index, shard.count, CaptureError, "capture writer"):
        shard.record_path(root).unlink(missing_ok=True)  # written again once this shard is complete
        remove_temporaries(root, owned=lambda dest: dest == Path(SHARDS_DIR) / shard.name
                           or Path(*dest.parts[:2]) in owned)
        _synthesize_locked(root, rig, own, int(seed), config, mounts, progress, list_frames=False)
        _write_capture_shard_record(root, rig, int(frames), int(seed), config, shard, own)
    return root


def _write_capture_shard_record(root: Path, rig: Mapping[str, Calibration], frames: int, seed: int,
                                config: CaptureConfig, shard, own: list[int]) -> Path:
    """A capture shard's record: the rule, the requested and its own frames, the settings every
    shard must share (seed, frame count, capture settings, calibrations) and each of its frames'
    `frame_fingerprint` (what `merge_shards` checks the frame folders against)."""
    import dataclasses
    import hashlib

    from ..io._calibration_json import calibration_to_dict
    from ..io._json import to_json_text, write_json
    from ._fingerprint import frame_fingerprint
    from ._shards import SHARD_FORMAT, SHARD_RULE

    calibrations = {n: hashlib.sha256(to_json_text("<calibration>", calibration_to_dict(c), sort_keys=True)
                                      .encode()).hexdigest() for n, c in rig.items()}
    settings = {"seed": seed, "frames": frames, "config": dataclasses.asdict(config), "calibrations": calibrations}
    record = {"format": SHARD_FORMAT, "kind": "capture", "shard": [shard.index, shard.count], "rule": SHARD_RULE,
              "requested": list(range(frames)), "samples": list(own),
              "settings": json.loads(to_json_text("<settings>", settings)),
              "frame_fingerprints": {str(k): frame_fingerprint(root, k) for k in own}}
    path = shard.record_path(root)
    write_json(path, record, indent=1, error=CaptureError)
    return path


def _synthesize_locked(root: Path, rig: Mapping[str, Calibration], frames: list[int], seed: int, config: CaptureConfig,
                       mounts: SensorMounts, progress: Callable[[str], None] | None, *, list_frames: bool = True) -> None:
    write_capture_header(root, rig, config, mounts, seed=seed)
    bev, front = bev_camera(config), front_camera(config)
    tick = progress or (lambda _msg: None)
    last = None  # (frame number, cameras, views) of the frame rendered before
    for k in frames:
        frame = generate_street(seed, frame=k, rig=rig, textured=config.textured)
        before = last if last is not None and last[0] == k - 1 else None  # its t is this frame's t-1
        cams = {}
        for name, calib in rig.items():
            cams[name] = simulate_camera(frame, calib, config, prev=None if before is None else before[1][name].curr)
            tick(f"frame {k}: camera {name}")
        views = {}
        for view, camera, mount in (("bev", bev, mounts.bev_camera_to_vehicle),
                                    ("front", front, mounts.front_camera_to_vehicle)):
            views[view] = simulate_view(frame, camera, mount, config, prev=None if before is None else before[2][view][1])
            tick(f"frame {k}: {view}")
        last = (k, cams, views)
        lidar, sem = simulate_lidar(frame, mounts.lidar_location, config)
        radar = simulate_radar(frame, mounts.radar_location, config)
        write_frame(root, frame, cameras=cams, views=views, lidar=lidar, semantic_lidar=sem, radar=radar,
                    imu=simulate_imu(frame), gnss=simulate_gnss(frame), list_frame=list_frames,
                    prev_written=before is not None)
        tick(f"frame {k}: lidar, radar, imu, gnss written")


def rig_names(directory: str | os.PathLike) -> tuple[str, ...]:
    """Camera names of the ``*.json`` calibrations in a directory: the standard ones first, in
    ``FV, MVL, MVR, RV`` order, then any others alphabetically."""
    from ..calibration import CAMERA_NAMES

    stems = {p.stem for p in Path(directory).glob("*.json")}
    return tuple(n for n in CAMERA_NAMES if n in stems) + tuple(sorted(stems - set(CAMERA_NAMES)))


def steps_per_frame(rig: Mapping[str, Calibration]) -> int:
    """How many times `synthesize_capture` calls ``progress`` per frame."""
    return len(rig) + 3
