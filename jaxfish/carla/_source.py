"""A live CARLA session as a source of `jaxfish.pipeline.Frame`\\ s for the dataset builder (the
capture program's online mode): the frames the offline mode's capture would give, read in order
while the simulation runs."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from ..calibration import Calibration
from ..pipeline import Frame
from ..scene import CaptureConfig, bev_camera
from ..transforms import Pose
from ._version import CarlaCaptureError, carla_semantic_tags


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _json_copy(obj: Any) -> Any:
    from ..io._json import to_json_text

    return json.loads(to_json_text("<memory>", obj, error=CarlaCaptureError))


class CarlaSource:
    """The frames ``0 .. frames - 1`` of a live CARLA session, as the dataset builder reads a source
    (`jaxfish.dataset.FrameSource`: ``build_dataset(CarlaSource(...), out_dir)``).

    - ``rig``: the fisheye calibrations as the capture stores them (moved onto the ego actor,
      `rig_on_actor`), in the capture header's order;
    - ``config``: the capture settings (face size and faces, BEV size and scale);
    - ``bev_camera_to_vehicle``: the BEV camera's mount as the capture's ``sensors.json`` states it
      (`with_bev_altitude`);
    - ``carla_version``: the server's (its semantic tag table, `carla_semantic_tags`);
    - ``next_frame(k)``: ticks the world and returns frame ``k`` (`carla_frame`), called once per
      frame with ``k = 0, 1, ...`` in order;
    - ``settings``: what else identifies the session (town, weather, seed, ...), JSON values;
      ``seed``, ``dt_s``: as the capture header records them.

    Everything but the frames is what `jaxfish.dataset.CaptureSource` gives for the offline
    capture of the same session (calibrations and the BEV as their files give them back, the
    cameras in dataset order), so both builds write the same sample files. A live session cannot be
    replayed: `read` returns frames in order, keeping the last ``keep`` frames for a builder that
    reads a batch again; an earlier frame raises `CarlaCaptureError`. Its fingerprint names the
    session, so a dataset folder holding samples of another build is refused (no resume)."""

    carla_tags: str
    """The session's semantic tag table (``"0.9.10"`` or ``"0.9.14"``)."""

    def __init__(self, rig: Mapping[str, Calibration], *, config: CaptureConfig, bev_camera_to_vehicle: Pose,
                 carla_version: str, frames: int, next_frame: Callable[[int], Frame],
                 settings: Mapping[str, Any] | None = None, seed: int | None = 0, dt_s: float = 0.1, keep: int = 2):
        from ..dataset import FISHEYE_CAMERAS
        from ..io._calibration_json import calibration_from_dict, calibration_to_dict

        if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or int(frames) < 1:
            raise CarlaCaptureError(f"CarlaSource: frames must be a positive integer, got {frames!r}")
        self.config = config
        self.carla_tags = carla_semantic_tags(carla_version)
        self.frames = list(range(int(frames)))
        self.header_cameras = list(rig)
        self.cameras = [c for c in FISHEYE_CAMERAS if c in rig] + [c for c in rig if c not in FISHEYE_CAMERAS]
        self._calib_json = {n: _json_copy(calibration_to_dict(rig[n])) for n in self.cameras}
        self._rig = {n: calibration_from_dict(self._calib_json[n], source=f"<{n} calibration>") for n in self.cameras}
        self._bev_pose = bev_camera_to_vehicle
        self._next_frame = next_frame
        self._settings = _json_copy({"source": "carla", "carla_version": str(carla_version), "seed": seed, "dt_s": dt_s,
                                     "config": _config_dict(config), **dict(settings or {})})
        self._seed, self._dt_s = seed, float(dt_s)
        self._keep = max(1, int(keep))
        self._read: dict[int, Frame] = {}
        self._next = 0
        self._broken: str | None = None
        what = " ".join(str(self._settings[k]) for k in ("town", "weather") if k in self._settings)
        self.where = f"<CARLA {carla_version} session{' ' + what if what else ''}>"  # names the source in errors

    @property
    def faces(self) -> tuple[str, ...]:
        """The cube faces rendered per camera."""
        return tuple(self.config.faces)

    @property
    def face_size(self) -> int:
        """The cube faces' side in pixels."""
        return int(self.config.face_size)

    def rig(self) -> dict[str, Calibration]:
        """The calibrations as their JSON files give them back, in `cameras` order."""
        return dict(self._rig)

    def has_bev(self) -> bool:
        """A CARLA capture always has its BEV top view."""
        return True

    def bev_sensor(self):
        """The BEV's `Orthographic` camera (float32) and mount as the capture's ``sensors.json`` gives them back."""
        from ..io._bev import bev_from_metadata

        bev, pose = bev_camera(self.config), self._bev_pose
        doc = _json_copy({"metres_per_pixel": float(bev.metres_per_pixel), "width": bev.width, "height": bev.height,
                          "cx": float(bev.cx), "cy": float(bev.cy),
                          "camera_to_vehicle": {"rotation_matrix": np.asarray(pose.rotation_matrix, np.float64).tolist(),
                                                "translation": np.asarray(pose.translation, np.float64).tolist()}})
        return bev_from_metadata(doc, self.where)

    def calibration_bytes(self, camera: str) -> bytes:
        """The calibration file of ``camera`` as the capture holds it."""
        from ..io._json import to_json_text

        return to_json_text(f"<{camera} calibration>", self._calib_json[camera], indent=2).encode()

    def _settings_sha(self) -> str:
        from ..io._json import to_json_text

        return _sha(to_json_text("<memory>", self._settings, sort_keys=True).encode())

    def fingerprint(self) -> dict[str, str]:
        """SHA-256 of the session settings (``carla``: server version, capture settings, town,
        weather, seed, the session's id) and of each calibration's JSON."""
        parts = {"carla": self._settings_sha()}
        for n in sorted(self.cameras):
            parts[f"calibration/{n}.json"] = _sha(self.calibration_bytes(n))
        return parts

    def frame_fingerprint(self, index: int) -> str:
        """A frame of the session is a function of the session and its number."""
        return _sha(f"{self._settings_sha()} frame {int(index)}".encode())

    def constants_key(self) -> tuple:
        """What the rig constants depend on: the calibrations, the capture settings and the BEV mount."""
        pose = self._bev_pose
        bev = (tuple(np.asarray(pose.rotation_matrix, np.float64).ravel().tolist()),
               tuple(np.asarray(pose.translation, np.float64).tolist()))
        return ("carla", tuple(_sha(self.calibration_bytes(n)) for n in self.cameras), self.face_size, self.faces,
                json.dumps(_config_dict(self.config), sort_keys=True), bev)

    def describe(self) -> dict[str, Any]:
        """``dataset.json``'s ``capture`` block: what the offline capture's header would say."""
        from ..io._capture import CAPTURE_FORMAT, CAPTURE_VERSION

        return {"format": CAPTURE_FORMAT, "version": CAPTURE_VERSION, "source": "carla", "seed": self._seed,
                "dt_s": self._dt_s, "carla_semantic_tags": self.carla_tags, "face_size": self.face_size,
                "faces": list(self.faces), "cameras": list(self.header_cameras)}

    def read(self, index: int, *, bev: bool = True) -> Frame:
        """Frame ``index`` of the session: the world ticks on to it (frames skipped on the way are
        dropped); one of the last ``keep`` frames is returned again; an earlier one raises
        `CarlaCaptureError` (a live session cannot be replayed). Without ``bev`` the frame's BEV is
        None. Once ``next_frame`` has raised (a lost server, a missing reading), every later frame
        raises `CarlaCaptureError` with that reason at once."""
        index = int(index)
        if index not in self.frames:
            raise CarlaCaptureError(f"{self.where}: frame {index} is not one of its {len(self.frames)} frames")
        if index not in self._read:
            if index < self._next:
                raise CarlaCaptureError(f"{self.where}: frame {index} was read before and is gone (a live session "
                                        "gives its frames once, in order)")
            if self._broken is not None:
                raise CarlaCaptureError(f"{self.where}: the session stopped at frame {self._next}: {self._broken}")
            while self._next <= index:
                try:
                    frame = self._next_frame(self._next)
                except Exception as e:  # a lost server fails every later frame at once, without waiting again
                    self._broken = f"{type(e).__name__}: {e}"
                    raise
                if frame.index != self._next:
                    raise CarlaCaptureError(f"{self.where}: asked for frame {self._next}, got frame {frame.index}")
                self._read[self._next] = frame
                self._next += 1
                for old in [k for k in self._read if k < self._next - self._keep]:
                    del self._read[old]
        frame = self._read[index]
        if frame.sensors is not None and frame.sensors.lidar_to_vehicle is None:
            frame = self._with_mounts(frame)
        if not bev and frame.bev is not None:
            frame = Frame(index=frame.index, carla_tags=frame.carla_tags, cameras=frame.cameras,
                          camera_frames=frame.camera_frames, motion=frame.motion, bev=None, sensors=frame.sensors)
        return frame

    def _with_mounts(self, frame: Frame) -> Frame:
        """The frame with the lidar and radar mounts its ``sensors.json`` records
        (`jaxfish.scene.sensor_mounts` of the rig and config) when the frame came without them."""
        from ..pipeline import sensor_to_vehicle_matrix
        from ..scene import sensor_mounts

        ct = sensor_mounts(self._rig, self.config).carla_transforms()
        m = {f"{k}_to_vehicle": sensor_to_vehicle_matrix(ct[k]["location"], ct[k]["rotation"]) for k in ("lidar", "radar")}
        s = frame.sensors
        sensors = type(s)(ego=s.ego, lidar=s.lidar, semantic_lidar=s.semantic_lidar, radar=s.radar, imu=s.imu,
                          gnss=s.gnss, **m)
        return Frame(index=frame.index, carla_tags=frame.carla_tags, cameras=frame.cameras,
                     camera_frames=frame.camera_frames, motion=frame.motion, bev=frame.bev, sensors=sensors)

    def __repr__(self) -> str:
        return f"CarlaSource({self.where}, frames={len(self.frames)}, face_size={self.face_size})"


def _config_dict(config: CaptureConfig) -> dict[str, Any]:
    import dataclasses

    return dataclasses.asdict(config)
