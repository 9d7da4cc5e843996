"""The embedded street scene rendered to a capture directory (``docs/capture_layout.md``): the
embedded scene as a capture source writes it, frame by frame, through `jaxfish.io`'s capture writer."""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np

from ..calibration import Calibration
from ..io import CaptureError, check_capture_folder, write_capture_header, write_frame
from ..io._folder import folder_lock, remove_temporaries
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


def synthesize_capture(
    root: str | os.PathLike,
    rig: Mapping[str, Calibration],
    *,
    frames: int = 1,
    seed: int = 0,
    config: CaptureConfig | None = None,
    progress: Callable[[str], None] | None = None,
) -> Path:
    """Render ``frames`` frames of the embedded street scene with ``rig`` and write the capture.

    ``root`` must be new, empty or a jaxfish capture (`check_capture_folder`); it is locked while
    the capture is written (a second writer meanwhile raises `CaptureError`) and the temporary
    files a killed run left in it are removed first (only jaxfish's own). An existing capture's
    files are overwritten with the new ones; files jaxfish does not write there are kept.
    ``progress`` is called with a short description after every step (a camera, a view, ...).
    """
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= int(seed) < 2**63:
        raise CaptureError(f"synthesize_capture: seed must be an integer from 0 to 2**63 - 1, got {seed!r}")
    if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or int(frames) < 1:
        raise CaptureError(f"synthesize_capture: frames must be a positive integer, got {frames!r}")
    config = config or CaptureConfig()
    mounts = sensor_mounts(rig, config)
    root = check_capture_folder(root)
    root.mkdir(parents=True, exist_ok=True)
    with folder_lock(root, CaptureError, "capture writer"):
        remove_temporaries(root)
        _synthesize_locked(root, rig, int(frames), int(seed), config, mounts, progress)
    return root


def _synthesize_locked(root: Path, rig: Mapping[str, Calibration], frames: int, seed: int, config: CaptureConfig,
                       mounts: SensorMounts, progress: Callable[[str], None] | None) -> None:
    write_capture_header(root, rig, config, mounts, seed=seed)
    bev, front = bev_camera(config), front_camera(config)
    tick = progress or (lambda _msg: None)
    for k in range(frames):
        frame = generate_street(seed, frame=k, rig=rig, textured=config.textured)
        cams = {}
        for name, calib in rig.items():
            cams[name] = simulate_camera(frame, calib, config)
            tick(f"frame {k}: camera {name}")
        views = {"bev": simulate_view(frame, bev, mounts.bev_camera_to_vehicle, config)}
        tick(f"frame {k}: bev")
        views["front"] = simulate_view(frame, front, mounts.front_camera_to_vehicle, config)
        tick(f"frame {k}: front")
        lidar, sem = simulate_lidar(frame, mounts.lidar_location, config)
        radar = simulate_radar(frame, mounts.radar_location, config)
        write_frame(root, frame, cameras=cams, views=views, lidar=lidar, semantic_lidar=sem, radar=radar,
                    imu=simulate_imu(frame), gnss=simulate_gnss(frame))
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
