"""Sources of `jaxfish.pipeline.Frame`\\ s: a capture directory on disk and the embedded street
scene rendered in memory. Both hand the pipeline the same arrays for the same scene (CARLA's
encodings and quantisation applied, calibrations as their JSON files give them), so a dataset built
from either has the same bytes. A source is picklable: dask workers read their own frames."""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from .._errors import JaxfishError
from .._sequences import KeptByOwner
from ..calibration import Calibration
from ..pipeline import (
    CameraFrame,
    CubeFaces,
    Frame,
    SensorRecords,
    ViewFrame,
    ViewImages,
    motion_from_records,
)
from ._layout import FISHEYE_CAMERAS

MAX_FRAMES = 10_000_000
"""The most frames an embedded source (`EmbeddedSource`, ``jaxfish synth``) renders: far beyond
any dataset, and a bound on the frame lists a run holds."""


class FrameSource(Protocol):  # the builder's view of a source
    """What the builder needs of a source of frames.

    - `frames`: the frame numbers it can give; `cameras`: fisheye names (in dataset order);
    - `rig()`: their calibrations; `faces`, `face_size`: the cube faces rendered per camera;
    - `bev_sensor()`: the BEV camera and mount, or None; `carla_tags`: the tag table;
    - `fingerprint()`: ``{name: sha256}`` of everything all its frames are made of;
      `frame_fingerprint(index)`: sha256 of one frame's own inputs;
    - `read(index, bev=...)`: the `Frame` (its errors name the file and field);
    - `describe()`: what the dataset's ``dataset.json`` records of the source.
    """

    frames: list[int]
    cameras: list[str]

    def read(self, index: int, *, bev: bool = True) -> Frame:
        """The `Frame` of frame ``index`` (with the BEV view when ``bev`` and the source has one)."""
        ...


def _dataset_order(names) -> list[str]:
    names = list(names)
    return [c for c in FISHEYE_CAMERAS if c in names] + [c for c in names if c not in FISHEYE_CAMERAS]


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def as_source(source) -> FrameSource:
    """A `FrameSource` of ``source``: itself, a `CaptureSource` of a capture directory path, or of
    an open `jaxfish.io.CaptureReader` (reading through that reader)."""
    from ..io import CaptureReader

    if isinstance(source, (str, os.PathLike)):
        return CaptureSource(source)
    if isinstance(source, CaptureReader):
        return CaptureSource.of_reader(source)
    return source


def sensor_mount_matrices(sensors: Mapping[str, Any], where: str) -> dict[str, np.ndarray]:
    """``lidar_to_vehicle`` and ``radar_to_vehicle`` (`jaxfish.pipeline.SensorRecords`) of a
    ``sensors.json`` document from each sensor's ``carla_transform``; a sensor without one maps to
    None. A malformed mount raises `jaxfish.io.CaptureError` naming ``where`` and the field."""
    from ..io import CaptureError
    from ..pipeline import sensor_to_vehicle_matrix

    out = {}
    for name in ("lidar", "radar"):
        entry = sensors.get(name) if isinstance(sensors, Mapping) else None
        ct = entry.get("carla_transform") if isinstance(entry, Mapping) else None
        if ct is None:
            out[f"{name}_to_vehicle"] = None
            continue
        try:
            loc, rot = np.asarray(ct["location"], np.float64), np.asarray(ct["rotation"], np.float64)
            if loc.shape != (3,) or rot.shape != (3,) or not (np.all(np.isfinite(loc)) and np.all(np.isfinite(rot))):
                raise ValueError("location and rotation must be 3 finite numbers each")
        except (KeyError, TypeError, ValueError) as e:
            raise CaptureError(f"{where}: {name}.carla_transform: malformed ({e})") from e
        out[f"{name}_to_vehicle"] = sensor_to_vehicle_matrix(loc.tolist(), rot.tolist())
    return out


def file_key(path: Path) -> str:
    """Content hash of a file (an empty string when missing)."""
    return _sha(path.read_bytes()) if path.is_file() else ""


def _capture_block(meta: Mapping[str, Any]) -> dict[str, Any]:
    return {k: meta.get(k) for k in ("format", "version", "source", "seed", "dt_s", "carla_semantic_tags", "face_size",
                                     "faces", "cameras")}


# ------------------------------------------------------------------------------ capture directory
class CaptureSource:
    """The frames of a capture directory (``docs/capture_layout.md``), decoded by
    `jaxfish.io.CaptureReader`. ``reuse_decoded``: keep the last decoded ``curr`` images so that a
    frame whose ``*_prev.png`` are byte copies of the previous frame's ``*_curr.png`` decodes them
    once (frames read in order). ``defer_events``: a frame's face events are
    `jaxfish.io.DeferredEvents`, read from their files when the pipeline maps them (each face's
    in turn) instead of held from the read on; else arrays."""

    def __init__(self, root: str | os.PathLike, *, reuse_decoded: bool = True, defer_events: bool = True):
        self.root = Path(root)
        self.reuse_decoded = reuse_decoded
        self.defer_events = defer_events
        self._reader = None
        self._rig = None
        _ = self.reader  # a missing or malformed header raises here

    @classmethod
    def of_reader(cls, reader) -> CaptureSource:
        """The source reading through an open `jaxfish.io.CaptureReader` (its header as read)."""
        source = cls.__new__(cls)
        source.root, source.reuse_decoded, source._reader, source._rig = reader.root, False, reader, None
        source.defer_events = True
        return source

    def __getstate__(self) -> dict[str, Any]:
        return {"root": self.root, "reuse_decoded": self.reuse_decoded, "defer_events": self.defer_events}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.root, self.reuse_decoded = state["root"], state["reuse_decoded"]
        self.defer_events = state["defer_events"]
        self._reader = self._rig = None

    @property
    def reader(self):
        """The `jaxfish.io.CaptureReader` of the capture."""
        if self._reader is None:
            from ..io import CaptureReader

            self._reader = CaptureReader(self.root, reuse_decoded=self.reuse_decoded)
        return self._reader

    @property
    def frames(self) -> list[int]:
        """The frame numbers of the capture (``capture.json`` field ``frames``)."""
        return self.reader.frames

    @property
    def cameras(self) -> list[str]:
        """The fisheye camera names, in dataset order (FV, RV, MVL, MVR, then others)."""
        return _dataset_order(self.reader.cameras)

    @property
    def faces(self) -> tuple[str, ...]:
        """The cube faces rendered per camera, in `jaxfish.reprojection.CubeRig` order."""
        return tuple(self.reader.faces)

    @property
    def face_size(self) -> int:
        """The cube faces' side in pixels (0 when the header does not say)."""
        return int(self.reader.meta.get("face_size", 0))

    @property
    def carla_tags(self) -> str:
        """The capture's semantic tag table (``carla_semantic_tags``)."""
        return str(self.reader.meta.get("carla_semantic_tags", "0.9.10"))

    @property
    def where(self) -> str:
        """The capture's header path (names the source in errors)."""
        return str(self.root / "capture.json")

    def rig(self) -> dict[str, Calibration]:
        """The fisheye calibrations, in `cameras` order (read once)."""
        if self._rig is None:
            rig = self.reader.rig()
            self._rig = {c: rig[c] for c in self.cameras}
        return self._rig

    def has_bev(self) -> bool:
        """Whether the capture has a BEV top view (``sensors.json`` field ``bev``)."""
        return "bev" in self.reader.sensors()

    def bev_sensor(self):
        """The BEV's `Orthographic` camera (float32) and mount from ``sensors.json``, or None."""
        from ..io import bev_sensor

        return bev_sensor(self.reader) if self.has_bev() else None

    def calibration_path(self, camera: str) -> Path:
        """The calibration file of ``camera``."""
        return self.root / "calibration" / f"{camera}.json"

    def fingerprint(self) -> dict[str, str]:
        """SHA-256 of the capture-level inputs of every sample: ``capture.json`` (without its
        ``frames`` list, which grows as frames are written), ``sensors.json`` and
        ``calibration/{camera}.json`` of every listed camera, keyed by those names (an empty string
        for a missing file)."""
        reader = self.reader
        meta = {k: v for k, v in reader.meta.items() if k != "frames"}
        parts = {"capture.json": _sha(json.dumps(meta, sort_keys=True, separators=(",", ":")).encode()),
                 "sensors.json": file_key(self.root / "sensors.json")}
        for cam in sorted(reader.cameras):
            parts[f"calibration/{cam}.json"] = file_key(self.calibration_path(cam))
        return parts

    def frame_fingerprint(self, index: int) -> str:
        """`frame_fingerprint` of the capture's frame ``index``."""
        from ._fingerprint import frame_fingerprint

        return frame_fingerprint(self.root, index)

    def constants_key(self) -> tuple:
        """What the rig constants depend on: the calibrations' and ``sensors.json``'s content, the
        face size and faces."""
        return ("capture", tuple(file_key(self.calibration_path(c)) for c in self.cameras),
                file_key(self.root / "sensors.json"), self.face_size, self.faces)

    def describe(self) -> dict[str, Any]:
        """``dataset.json``'s ``capture`` block: the header's format, version, source, seed, dt,
        CARLA tag table, face size, faces and cameras."""
        return _capture_block(self.reader.meta)

    def calibration_bytes(self, camera: str) -> bytes:
        """The calibration file of ``camera``, byte for byte."""
        return self.calibration_path(camera).read_bytes()

    def read(self, index: int, *, bev: bool = True, cameras: bool = True, sensors: bool = True) -> Frame:
        """The `Frame` of capture frame ``index``: with its BEV when ``bev`` and the capture has
        one, its fisheye cameras unless ``cameras=False`` (then none), its other sensors unless
        ``sensors=False`` (then None). A missing or malformed file raises
        `jaxfish.io.CaptureError` naming it."""
        from ..io import CaptureError

        reader = self.reader
        actors = reader.actors(index)  # names the frame when it is missing
        ego = reader.ego(index)
        try:
            motion = motion_from_records(actors, ego)
        except (KeyError, TypeError, ValueError) as e:
            raise CaptureError(f"{reader.root}: frame {index}: malformed actors.json / ego.json ({e})") from e
        names = self.cameras if cameras else []
        faces = list(reader.faces)
        decoded = reader.faces_stacks(index, [(c, inst) for inst in ("prev", "curr") for c in names], actor_ids=False)

        def cube(c: str, inst: str) -> CubeFaces:
            images = decoded[(c, inst)]
            return CubeFaces(images.rgb, images.depth_m, images.semantic)

        camera_frames = tuple(CameraFrame(cube(c, "prev"), cube(c, "curr"),
                                          tuple(reader.dvs(index, c, f, defer=self.defer_events) for f in faces))
                              for c in names)
        view = self._bev_view(index) if bev and self.has_bev() else None
        records = None
        if sensors:
            records = SensorRecords(ego=ego, lidar=np.ascontiguousarray(reader.lidar(index), np.float32),
                                    semantic_lidar=np.ascontiguousarray(reader.semantic_lidar(index)),
                                    radar=np.ascontiguousarray(reader.radar(index)), imu=reader.imu(index),
                                    gnss=reader.gnss(index),
                                    **sensor_mount_matrices(reader.sensors(), f"{reader.root / 'sensors.json'}"))
        return Frame(index=int(index), carla_tags=self.carla_tags, cameras=tuple(names), camera_frames=camera_frames,
                     motion=motion, bev=view, sensors=records)

    def _bev_view(self, index: int) -> ViewFrame:
        from ..io import CaptureError
        from ..io._capture import frame_dir

        reader = self.reader
        cam, _ = self.bev_sensor()
        d = frame_dir(reader.root, index) / "bev"
        for instant in ("prev", "curr"):
            for kind in ("rgb", "depth", "semantic"):
                p = d / f"{kind}_{instant}.png"
                if not p.is_file():
                    raise CaptureError(f"{p}: file missing (BEV {kind} at {'t-1' if instant == 'prev' else 't'})")
        prev, curr = (reader.view(index, "bev", inst, actor_ids=False) for inst in ("prev", "curr"))
        if curr.depth_m.shape != (cam.height, cam.width):
            raise CaptureError(f"{d / 'depth_curr.png'}: BEV image {curr.depth_m.shape} does not match sensors.json "
                               f"bev width x height {cam.width} x {cam.height}")
        exr = d / "height_curr.exr"
        height = None
        if exr.is_file():
            height = reader.height(index, "bev").astype(np.float32)
            if height.shape != (cam.height, cam.width):
                raise CaptureError(f"{exr}: height map {height.shape} does not match the BEV image {(cam.height, cam.width)}")
        return ViewFrame(ViewImages(prev.rgb, prev.depth_m, prev.semantic), ViewImages(curr.rgb, curr.depth_m, curr.semantic),
                         height)

    def __repr__(self) -> str:
        return f"CaptureSource({str(self.root)!r})"


# ------------------------------------------------------------------------------ embedded scene
def _json_copy(obj: Any) -> Any:
    """``obj`` as its JSON file gives it back (tuples become lists; floats exact)."""
    from ..io._json import to_json_text

    return json.loads(to_json_text("<memory>", obj))


def _read_only(a: np.ndarray) -> np.ndarray:
    """``a``, no longer writable: a frame's images are what the source rendered (the ground truth
    keeps read-only faces for the next sample of a sequence: `jaxfish.pipeline.sample_truth`)."""
    a.setflags(write=False)
    return a


class EmbeddedSource:
    """The embedded street scene (`jaxfish.scene`) rendered in memory, frame by frame: the frames
    `synthesize_capture` would write for ``rig``, ``seed`` and ``config``
    (frames ``0 .. frames - 1``), with the same CARLA encodings and quantisation and the
    calibrations as their JSON files give them back, without writing or decoding any file. The
    front perspective view (not part of the dataset) is not rendered."""

    def __init__(self, rig: Mapping[str, Calibration], *, frames: int, seed: int = 0, config=None):
        from ..io._calibration_json import calibration_from_dict, calibration_to_dict
        from ..scene import CaptureConfig

        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= int(seed) < 2**63:
            raise JaxfishError(f"EmbeddedSource: seed must be an integer from 0 to 2**63 - 1, got {seed!r}")
        if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or not 1 <= int(frames) <= MAX_FRAMES:
            raise JaxfishError(f"EmbeddedSource: frames must be an integer from 1 to {MAX_FRAMES}, got {frames!r}")
        self.render_rig = dict(rig)
        self.config = config or CaptureConfig()
        self.seed = int(seed)
        self.frames = list(range(int(frames)))
        self.cameras = _dataset_order(self.render_rig)
        self._calib_json = {n: _json_copy(calibration_to_dict(self.render_rig[n])) for n in self.cameras}
        self._rig = {n: calibration_from_dict(self._calib_json[n], source=f"<{n} calibration>") for n in self.cameras}
        # (frame, {camera: faces at t}, BEV images at t) of each sequence's last read
        self._last = KeptByOwner()

    def __getstate__(self) -> dict[str, Any]:
        return {k: v for k, v in self.__dict__.items() if k != "_last"}  # renders stay in the process that made them

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._last = KeptByOwner()

    @property
    def faces(self) -> tuple[str, ...]:
        """The cube faces rendered per camera (the capture settings')."""
        return tuple(self.config.faces)

    @property
    def face_size(self) -> int:
        """The cube faces' side in pixels."""
        return int(self.config.face_size)

    carla_tags = "0.9.10"
    """The embedded scene's semantic tag table."""
    where = "<embedded scene>"
    """How errors name the source."""

    def rig(self) -> dict[str, Calibration]:
        """The calibrations as their JSON files give them back, in `cameras` order."""
        return dict(self._rig)

    def has_bev(self) -> bool:
        """The embedded scene always has its BEV top view."""
        return True

    def _mounts(self):
        from ..scene import sensor_mounts

        return sensor_mounts(self.render_rig, self.config)

    def bev_sensor(self):
        """The BEV's `Orthographic` camera (float32) and mount as ``sensors.json`` gives them back."""
        from ..io._bev import bev_from_metadata
        from ..scene import bev_camera

        bev = bev_camera(self.config)
        pose = self._mounts().bev_camera_to_vehicle
        doc = _json_copy({"metres_per_pixel": float(bev.metres_per_pixel), "width": bev.width, "height": bev.height,
                          "cx": float(bev.cx), "cy": float(bev.cy),
                          "camera_to_vehicle": {"rotation_matrix": np.asarray(pose.rotation_matrix, np.float64).tolist(),
                                                "translation": np.asarray(pose.translation, np.float64).tolist()}})
        return bev_from_metadata(doc, self.where)

    def fingerprint(self) -> dict[str, str]:
        """SHA-256 of what every frame is made of: the scene settings (seed, capture settings)
        and each calibration's JSON."""
        import dataclasses

        from ..io._json import to_json_text

        config = dataclasses.asdict(self.config)
        if not config["textured"]:  # the smooth scene's settings do not name the option: stable fingerprints
            del config["textured"]
        settings = {"source": "embedded", "seed": self.seed, "config": config}
        parts = {"embedded": _sha(to_json_text("<memory>", _json_copy(settings), sort_keys=True).encode())}
        for n in sorted(self.cameras):
            parts[f"calibration/{n}.json"] = _sha(self.calibration_bytes(n))  # as a capture's file_key
        return parts

    def frame_fingerprint(self, index: int) -> str:
        """A frame of the embedded scene is a function of the settings and its number."""
        return _sha(f"embedded frame {int(index)}".encode())

    def constants_key(self) -> tuple:
        """What the rig constants depend on: the scene settings and calibrations."""
        return ("embedded", tuple(sorted(self.fingerprint().items())))

    def describe(self) -> dict[str, Any]:
        """``dataset.json``'s ``capture`` block: what a capture of the scene would say in its header."""
        from ..io._capture import CAPTURE_FORMAT, CAPTURE_VERSION

        return _capture_block({"format": CAPTURE_FORMAT, "version": CAPTURE_VERSION, "source": "embedded",
                               "seed": self.seed, "carla_semantic_tags": self.carla_tags, "dt_s": 0.1,
                               "face_size": self.face_size, "faces": list(self.faces),
                               "cameras": list(self.render_rig)})

    def calibration_bytes(self, camera: str) -> bytes:
        """The calibration file of ``camera`` as a capture of the scene holds it."""
        from ..io._json import to_json_text

        return to_json_text(f"<{camera} calibration>", self._calib_json[camera], indent=2).encode()

    def read(self, index: int, *, bev: bool = True) -> Frame:
        """Render frame ``index`` of the scene and return it as a capture of it would decode. Read
        right after frame ``index - 1``, its images at t-1 are that frame's images at t (the same
        bits: `jaxfish.scene.simulate_camera`'s ``prev``), not rendered again."""
        from ..io import CaptureError
        from ..io._capture import actor_to_dict, ego_record
        from ..io._carla import DVS_EVENT_DTYPE, decode_depth, decode_semantic, encode_depth, encode_semantic
        from ..scene import (
            RADAR_DTYPE,
            SEMANTIC_LIDAR_DTYPE,
            bev_camera,
            generate_street,
            simulate_camera,
            simulate_gnss,
            simulate_imu,
            simulate_lidar,
            simulate_radar,
            simulate_view,
        )

        if index not in self.frames:
            raise CaptureError(f"{self.where}: frame {index} is not one of its {len(self.frames)} frames")
        street = generate_street(self.seed, frame=int(index), rig=self.render_rig, textured=self.config.textured)
        faces = self.faces

        def quantised(img) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            return (np.asarray(img.rgb, np.uint8), decode_depth(encode_depth(img.depth_m)),
                    decode_semantic(encode_semantic(img.semantic)))

        # a sequence's last frame whose t is this frame's t-1
        before = next((last for last in self._last.values("frame") if last[0] == int(index) - 1), None)
        camera_frames, kept = [], {}
        for name in self.cameras:
            cap = simulate_camera(street, self.render_rig[name], self.config,
                                  prev=None if before is None else before[1][name])
            kept[name] = cap.curr
            prev = [quantised(cap.prev[f]) for f in faces]
            curr = [quantised(cap.curr[f]) for f in faces]
            camera_frames.append(CameraFrame(CubeFaces(*(_read_only(np.stack(x)) for x in zip(*prev, strict=True))),
                                             CubeFaces(*(_read_only(np.stack(x)) for x in zip(*curr, strict=True))),
                                             tuple(np.asarray(cap.dvs[f]).astype(DVS_EVENT_DTYPE) for f in faces)))
        mounts = self._mounts()
        view = kept_bev = None
        if bev:
            p, c, height = simulate_view(street, bev_camera(self.config), mounts.bev_camera_to_vehicle, self.config,
                                         prev=None if before is None else before[2])
            view = ViewFrame(ViewImages(*quantised(p)), ViewImages(*quantised(c)), np.asarray(height, np.float32))
            kept_bev = c
        self._last.put("frame", (int(index), kept, kept_bev))  # a BEV left out (None) is rendered when asked for
        lidar, sem = simulate_lidar(street, mounts.lidar_location, self.config)
        radar = simulate_radar(street, mounts.radar_location, self.config)
        actors = _json_copy([actor_to_dict(a) for a in street.actors])
        ego = _json_copy(ego_record(street))
        sensors = SensorRecords(ego=ego, lidar=np.ascontiguousarray(np.asarray(lidar, np.float32)),
                                semantic_lidar=np.ascontiguousarray(np.asarray(sem).astype(SEMANTIC_LIDAR_DTYPE)),
                                radar=np.ascontiguousarray(np.asarray(radar).astype(RADAR_DTYPE)),
                                imu=_json_copy(dict(simulate_imu(street))), gnss=_json_copy(dict(simulate_gnss(street))),
                                **sensor_mount_matrices(_json_copy({k: {"carla_transform": v} for k, v in
                                                                    mounts.carla_transforms().items()}), self.where))
        return Frame(index=int(index), carla_tags=self.carla_tags, cameras=tuple(self.cameras),
                     camera_frames=tuple(camera_frames), motion=motion_from_records(actors, ego), bev=view,
                     sensors=sensors)

    def __repr__(self) -> str:
        return f"EmbeddedSource(seed={self.seed}, frames={len(self.frames)}, face_size={self.face_size})"

