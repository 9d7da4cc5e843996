"""`open`: a map-style reader over a jaxfish-built dataset and over SynWoodScape's released layout
(``docs/reader.md``). NumPy out; typed, immutable sample records; picklable (paths and parsed JSON
only: no open file, no JAX array; camera models are built lazily in each process)."""

from __future__ import annotations

import builtins
import json
import os
import pickle
import re
import warnings
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import equinox as eqx
import numpy as np
from jaxtyping import Bool, Float, Int, Shaped, UInt

from .._errors import JaxfishError
from ..io import (
    calibration_from_dict,
    load_bev_calibration,
    load_npy,
    read_boxes_2d_csv,
    read_events_npy,
    read_flo,
    read_image,
)
from ..io._calibration_json import SYNWOODSCAPE_TRANSLATION_KEY
from ._layout import BEV_CAMERA, FISHEYE_CAMERAS
from ._manifest import DATASET_FORMAT

LAYOUT_JAXFISH = "jaxfish"
"""`SynWoodScapeDataset.layout` of a dataset built by jaxfish (it has a ``dataset.json``)."""
LAYOUT_RELEASE = "synwoodscape-release"
"""`SynWoodScapeDataset.layout` of SynWoodScape's released layout (no ``dataset.json``)."""

CAMERA_FIELDS = ("rgb", "rgb_prev", "depth", "z_depth", "semantics", "instances", "motion", "flow", "flow_valid",
                 "flow_occlusion", "events", "boxes_2d", "boxes_2d_full", "camera", "pose")
"""Fields of a `CameraSample` that ``open(..., fields=)`` selects."""
SAMPLE_FIELDS = ("timestamp_s", "boxes_3d", "bev", "lidar", "semantic_lidar", "radar", "imu", "gnss", "ego")
"""Fields of a `Sample` that ``open(..., fields=)`` selects."""
FIELDS = CAMERA_FIELDS + SAMPLE_FIELDS
"""Every selectable field (the default selection)."""

SEMANTIC_LIDAR_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("cos_inc_angle", "<f4"),
                                 ("object_idx", "<u4"), ("object_tag", "<u4")])
"""Semantic lidar points as the reader returns them (CARLA's field names ``CosAngle, ObjIdx,
ObjTag`` of a ``lidar_data`` pickle are renamed to these)."""
LIDAR_FRAME_VEHICLE = "vehicle"
"""`Sample.lidar_frame` of points in the ISO 8855 vehicle frame (``lidar_vehicle/``)."""
LIDAR_FRAME_SENSOR = "sensor-unreal"
"""`Sample.lidar_frame` of points in the lidar's own Unreal frame (x forward, y right, z up;
``lidar_data/{id}.pkl``, when the dataset has no ``lidar_vehicle/``)."""


class DatasetReadError(JaxfishError):
    """A dataset file is missing, unreadable or malformed; the message names its path and field."""


# ----------------------------------------------------------------------------- records


class Boxes2D(eqx.Module):
    """2D boxes of one camera (``box_2d_annotations`` lines): inclusive pixel-centre corners."""

    class_name: tuple[str, ...]
    class_id: Int[np.ndarray, " B"]
    xyxy: Int[np.ndarray, "B 4"]


class Boxes3D(eqx.Module):
    """3D boxes of a sample at t, in actor-id order. Corner order: index = 4 ix + 2 iy + iz over the
    signs (-, +) of the box axes. Without ``box_3d_annotations_ext`` (the release): ``class_id``
    -1, ``class_name`` ``"unknown"``, ``corners_vehicle`` (ISO 8855 vehicle frame) computed from
    the ego pose in ``vehicle_data`` (None without it)."""

    actor_id: Int[np.ndarray, " K"]
    class_id: Int[np.ndarray, " K"]
    class_name: tuple[str, ...]
    corners_vehicle: Float[np.ndarray, "K 8 3"] | None
    corners_world: Float[np.ndarray, "K 8 3"]


class BevSample(eqx.Module):
    """The BEV's extra maps: height above the ground (m), occupancy, semantics (the BEV camera's
    class ids) and the grid: ``[x, y] = pixel_to_vehicle_xy @ [u, v, 1]`` (ISO vehicle, metres)."""

    height: Float[np.ndarray, "H W"]
    occupancy: Bool[np.ndarray, "H W"]
    semantics: UInt[np.ndarray, "H W"] | None
    metres_per_pixel: float
    pixel_to_vehicle_xy: Float[np.ndarray, "2 3"]


class Imu(eqx.Module):
    """IMU reading at t (CARLA's IMU sensor)."""

    accelerometer_mps2: Float[np.ndarray, " 3"]
    gyroscope_radps: Float[np.ndarray, " 3"]
    compass_rad: float


class Gnss(eqx.Module):
    """GNSS reading at t."""

    latitude_deg: float
    longitude_deg: float
    altitude_m: float


class Ego(eqx.Module):
    """The ego vehicle at t: ``vehicle_to_world`` (4 x 4, ISO 8855 vehicle -> world), velocity,
    acceleration, angular velocity; ``frame`` says in which frame the vectors are (``sensor_data``:
    as that file states; the ``vehicle_data`` fallback: CARLA world, angular velocity converted from
    deg/s); ``previous_timestamp_s``: the instant t-1."""

    vehicle_to_world: Float[np.ndarray, "4 4"]
    velocity_mps: Float[np.ndarray, " 3"]
    acceleration_mps2: Float[np.ndarray, " 3"]
    angular_velocity_radps: Float[np.ndarray, " 3"]
    previous_timestamp_s: float | None
    frame: str


class CameraSample(eqx.Module):
    """One camera of a sample (``docs/reader.md`` lists each field's file, dtype and unit). Fields
    not selected, or absent from the dataset, are None."""

    rgb: Shaped[np.ndarray, "H W 3"] | None = None
    rgb_prev: Shaped[np.ndarray, "H W 3"] | None = None
    depth: Float[np.ndarray, "H W"] | None = None
    z_depth: Float[np.ndarray, "H W"] | None = None
    semantics: UInt[np.ndarray, "H W"] | None = None
    instances: UInt[np.ndarray, "H W"] | None = None
    motion: Bool[np.ndarray, "H W"] | None = None
    flow: Float[np.ndarray, "H W 2"] | None = None
    flow_valid: Bool[np.ndarray, "H W"] | None = None
    flow_occlusion: Bool[np.ndarray, "H W"] | None = None
    events: Shaped[np.ndarray, " N"] | None = None
    boxes_2d: Boxes2D | None = None
    boxes_2d_full: Boxes2D | None = None
    camera: Any = None
    pose: Any = None


class Sample(eqx.Module):
    """One sample (the instants t and t-1 of every camera). Fields not selected, or absent from the
    dataset, are None."""

    id: str
    timestamp_s: float | None = None
    cameras: dict[str, CameraSample] = eqx.field(default_factory=dict)
    boxes_3d: Boxes3D | None = None
    bev: BevSample | None = None
    lidar: Float[np.ndarray, "N 4"] | None = None
    lidar_frame: str | None = None
    semantic_lidar: Shaped[np.ndarray, " M"] | None = None
    radar: Shaped[np.ndarray, " R"] | None = None
    imu: Imu | None = None
    gnss: Gnss | None = None
    ego: Ego | None = None


# ----------------------------------------------------------------------------- helpers


def _fail(path: Path | str, field: str, sample: str | None, message: str) -> DatasetReadError:
    where = f"field '{field}'" + (f" of sample {sample}" if sample is not None else "")
    return DatasetReadError(f"{path}: {where}: {message}")


def _guard(path: Path, field: str, sample: str | None, fn):
    """``fn(path)`` with every failure turned into a `DatasetReadError` naming path and field."""
    try:
        return fn(path)
    except DatasetReadError:
        raise
    except FileNotFoundError:
        raise _fail(path, field, sample, "file missing") from None
    except JaxfishError as e:
        text = str(e)
        prefix = f"{path}: "
        raise _fail(path, field, sample, text[len(prefix):] if text.startswith(prefix) else text) from e
    except (OSError, ValueError, TypeError, KeyError, IndexError, EOFError, AttributeError,
            pickle.UnpicklingError, UnicodeDecodeError) as e:
        raise _fail(path, field, sample, f"cannot read ({type(e).__name__}: {e})") from e


def _json(path: Path) -> Any:
    return json.loads(path.read_bytes().decode("utf-8"))


def _pickle(path: Path) -> Any:
    with builtins.open(path, "rb") as fh:
        return pickle.load(fh)  # trusted dataset files only: pickle runs code


def _image(path: Path, channels: int | None = None, *, lossless: bool = False) -> np.ndarray:
    """The pixels of ``path`` with ``channels`` channels (None: as stored; 1: ``(H, W)``). A
    lossless one-channel read (labels, masks) takes a palette PNG's indices and a grey image stored
    in colour channels (all equal); other colours raise `DatasetReadError` naming the file."""
    a = read_image(path, lossless=lossless)
    if channels == 1:
        if lossless and a.shape[-1] > 1 and not all(np.array_equal(a[..., 0], a[..., c]) for c in range(1, min(3, a.shape[-1]))):
            raise DatasetReadError(f"{path}: expected labels (one grey channel or palette indices), got "
                                   f"{a.shape[-1]} channels of different colours")
        return a[..., 0]
    if channels is not None:
        if a.shape[-1] < channels:
            raise DatasetReadError(f"{path}: expected {channels} channels, got {a.shape[-1]}")
        return a[..., :channels]
    return a


def _mask(path: Path) -> np.ndarray:
    return _image(path, 1, lossless=True) > 0


def _array(value: Any, shape: tuple[int, ...], dtype=np.float64) -> np.ndarray:
    a = np.asarray(value, dtype)
    if a.shape != shape:
        raise ValueError(f"expected shape {shape}, got {a.shape}")
    if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
        raise ValueError("not finite")
    return a


def _boxes_2d(path: Path) -> Boxes2D:
    rows = read_boxes_2d_csv(path)
    return Boxes2D(class_name=tuple(r[0] for r in rows), class_id=np.asarray([r[1] for r in rows], np.int64),
                   xyxy=np.asarray([r[2:] for r in rows], np.int64).reshape(len(rows), 4))


def _vehicle_text(path: Path) -> dict[str, list[float]]:
    out = {}
    for i, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        name, *vals = line.split()
        try:
            out[name] = [float(v) for v in vals]
        except ValueError as e:
            raise DatasetReadError(f"{path}:{i}: field '{name}': not a number ({e})") from None
    return out


def _events(path: Path) -> np.ndarray:
    return read_events_npy(path)


def _sample_ids(names: Iterable[str], pattern: re.Pattern) -> list[str]:
    return sorted({m.group(1) for n in names if (m := pattern.fullmatch(n))})


# ----------------------------------------------------------------------------- the dataset


class SynWoodScapeDataset:
    """A map-style dataset: ``len(ds)``, ``ds[i]`` (a `Sample`; negative ``i`` counts from the end),
    ``ds[a:b:c]`` (a `SynWoodScapeDataset` over those samples: a view, no file read), ``ds.samples``
    (ids), ``ds.cameras``, ``ds.layout``, ``ds.fields``, ``ds.notes`` / ``ds.corrections`` (what the
    reader changed or could not know), ``ds.window(i, n)``. Made by `open`; picklable (for
    worker processes): it holds paths and parsed JSON only."""

    def __init__(self, root: Path, *, layout: str, samples: tuple[str, ...], all_samples: tuple[str, ...],
                 cameras: tuple[str, ...], fields: frozenset[str], manifest: Mapping[str, Any] | None,
                 calibrations: Mapping[str, Any], corrections: tuple[str, ...], notes: tuple[str, ...],
                 sequences: Mapping[str, Any] | None):
        self.root = root
        self.layout = layout
        self.samples = samples
        self.cameras = cameras
        self.fields = fields
        self.manifest = manifest
        self.corrections = corrections
        self.notes = notes
        self._all_samples = all_samples
        self._calibrations = dict(calibrations)  # camera -> parsed JSON (fisheyes) or path (BEV)
        self._sequences = sequences
        self._models: dict[str, tuple[Any, Any]] = {}

    # ---- pickling: no camera model (JAX arrays) travels; each process builds its own
    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["_models"] = {}
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)

    def __repr__(self) -> str:
        return (f"SynWoodScapeDataset({str(self.root)!r}, layout={self.layout!r}, {len(self)} samples, "
                f"cameras={list(self.cameras)})")

    def __len__(self) -> int:
        return len(self.samples)

    def __getitem__(self, index):
        if isinstance(index, slice):
            return self._view(self.samples[index])
        if isinstance(index, (bool, np.bool_)) or not isinstance(index, (int, np.integer)):
            raise TypeError(f"dataset indices are integers or slices, got {type(index).__name__}")
        n = len(self.samples)
        i = int(index)
        if not -n <= i < n:
            raise IndexError(f"sample index {i} out of range for {n} samples")
        return self.read(self.samples[i])

    def _view(self, samples: Sequence[str]) -> SynWoodScapeDataset:
        view = object.__new__(SynWoodScapeDataset)
        view.__dict__.update(self.__dict__)  # shares this process's camera models
        view.samples = tuple(samples)
        return view

    # ---- sequences
    def window(self, i: int, n: int) -> list[Sample]:
        """``n`` consecutive samples of one sequence starting at ``ds[i]``. The sequence comes from
        ``sequence.json`` when present, else from consecutive frame numbers (sample ids). Raises
        `DatasetReadError` naming the reason when the window would cross the end of the sequence
        or a gap (a missing sample)."""
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise ValueError(f"window: n must be a positive integer, got {n!r}")
        m = len(self.samples)
        if isinstance(i, bool) or not isinstance(i, (int, np.integer)) or not -m <= int(i) < m:
            raise IndexError(f"window: sample index {i!r} out of range for {m} samples")
        return [self.read(s) for s in self.window_ids(self.samples[int(i)], int(n))]

    def window_ids(self, start: str, n: int) -> list[str]:
        """The ids of the window of ``n`` samples starting at sample id ``start`` (see `window`)."""
        if self._sequences is not None:
            where = self.root / "sequence.json"
            for seq in self._sequences.get("sequences", []):
                members = [str(s) for s in seq.get("samples", [])]
                if start in members:
                    k = members.index(start)
                    if k + n > len(members):
                        raise DatasetReadError(
                            f"{where}: window of {n} samples from {start} crosses the end of sequence "
                            f"{seq.get('name')!r} ({len(members) - k} sample(s) left)")
                    ids = members[k:k + n]
                    missing = [s for s in ids if s not in self._all_samples]
                    if missing:
                        raise DatasetReadError(f"{where}: window of {n} samples from {start} crosses a gap: sample "
                                               f"{missing[0]} of sequence {seq.get('name')!r} is not in the dataset")
                    return ids
            raise DatasetReadError(f"{where}: sample {start} is in no sequence")
        ids = []
        have = set(self._all_samples)
        width = len(start)
        for k in range(n):
            sid = f"{int(start) + k:0{width}d}"
            if sid not in have:
                last = self._all_samples[-1] if self._all_samples else start
                reason = "the end of the dataset" if int(sid) > int(last) else f"a gap (sample {sid} is missing)"
                raise DatasetReadError(f"{self.root}: window of {n} samples from {start} crosses {reason} "
                                       "(no sequence.json: consecutive frame numbers)")
            ids.append(sid)
        return ids

    # ---- calibrations (lazy, per process)
    def calibration(self, camera: str) -> tuple[Any, Any]:
        """``(camera model, camera_to_vehicle Pose)`` of ``camera`` (None, None when the dataset has
        no calibration for it, e.g. the release's BEV); built once per process."""
        if camera not in self._models:
            src = self._calibrations.get(camera)
            if src is None:
                self._models[camera] = (None, None)
            elif camera == BEV_CAMERA:
                path = self.root / "calibration_data" / f"{BEV_CAMERA}.json"
                self._models[camera] = _guard(path, "camera", None, load_bev_calibration)
            else:
                path = self.root / "calibration_data" / f"{camera}.json"
                errata = self.layout == LAYOUT_RELEASE and _carla_key(src)
                calib = _guard(path, "camera", None,
                               lambda p: calibration_from_dict(src, source=str(p), apply_errata=errata))
                self._models[camera] = (calib.camera, calib.camera_to_vehicle)
        return self._models[camera]

    # ---- reading
    def _path(self, rel: str) -> Path:
        return self.root / rel

    def read(self, sample: str) -> Sample:
        """The `Sample` of sample id ``sample`` (its selected fields)."""
        f = self.fields
        cams = {c: self._camera(sample, c) for c in self.cameras}
        out: dict[str, Any] = {"id": sample, "cameras": cams}
        sensor = None
        if f & {"timestamp_s", "imu", "gnss", "ego"}:
            p = self._path(f"sensor_data/{sample}.json")
            if p.is_file():
                first = next(x for x in ("timestamp_s", "ego", "imu", "gnss") if x in f)
                sensor = _guard(p, first, sample, _json)
                if not isinstance(sensor, dict):
                    raise _fail(p, first, sample, "expected a JSON object")
        if "timestamp_s" in f:
            out["timestamp_s"] = self._timestamp(sample, sensor)
        if "ego" in f:
            out["ego"] = self._ego(sample, sensor)
        if "imu" in f and sensor is not None:
            out["imu"] = self._imu(sample, sensor)
        if "gnss" in f and sensor is not None:
            out["gnss"] = self._gnss(sample, sensor)
        if "boxes_3d" in f:
            out["boxes_3d"] = self._boxes_3d(sample)
        if "bev" in f and self.layout == LAYOUT_JAXFISH and BEV_CAMERA in self._calibrations:
            bev_sem = cams[BEV_CAMERA].semantics if BEV_CAMERA in cams else None
            out["bev"] = self._bev(sample, bev_sem)
        if f & {"lidar", "semantic_lidar", "radar"}:
            out.update(self._lidar(sample))
        return Sample(**out)

    def _camera(self, s: str, c: str) -> CameraSample:
        f, stem, jax_layout = self.fields, f"{s}_{c}", self.layout == LAYOUT_JAXFISH
        v: dict[str, Any] = {}
        p = self._path
        if "rgb" in f:
            v["rgb"] = _guard(p(f"rgb_images/{stem}.png"), "rgb", s, lambda q: _image(q, 3))
        if "rgb_prev" in f:
            v["rgb_prev"] = _guard(p(f"previous_images/{stem}_prev.png"), "rgb_prev", s, lambda q: _image(q, 3))
        if "depth" in f:
            v["depth"] = _guard(p(f"depth_maps/raw_data/{stem}.npy"), "depth", s, load_npy)
        if "z_depth" in f and jax_layout:
            v["z_depth"] = _guard(p(f"depth_maps/z_depth/{stem}.npy"), "z_depth", s, load_npy)
        if "semantics" in f:
            v["semantics"] = _guard(p(f"semantic_annotations/gtLabels/{stem}.png"), "semantics", s,
                                    lambda q: _image(q, 1, lossless=True))
        if "instances" in f:
            v["instances"] = _guard(p(f"instance_annotations/gtLabels/{stem}.png"), "instances", s,
                                    lambda q: _image(q, 1, lossless=True))
        if "motion" in f:
            v["motion"] = _guard(p(f"motion_annotations/gtLabels/{stem}.png"), "motion", s, _mask)
        if "flow" in f:
            v["flow"] = _guard(p(f"optical_flow/raw_data/{stem}.flo"), "flow", s, read_flo)
        if "flow_valid" in f:
            q = p(f"optical_flow/valid_mask/{stem}.png")
            if q.is_file():
                v["flow_valid"] = _guard(q, "flow_valid", s, _mask)
            elif jax_layout:
                v["flow_valid"] = _guard(p(f"optical_flow/kitti/{stem}.png"), "flow_valid", s,
                                         lambda r: _kitti_valid(r))
        if "flow_occlusion" in f:
            q = p(f"optical_flow/occlusion_mask/{stem}.png")
            if q.is_file():
                v["flow_occlusion"] = _guard(q, "flow_occlusion", s, _mask)
        if "events" in f and c != BEV_CAMERA:
            v["events"] = _guard(p(f"dvs_signals/raw_data/{stem}.npy"), "events", s, _events)
        if "boxes_2d" in f:
            v["boxes_2d"] = _guard(p(f"box_2d_annotations/{stem}.txt"), "boxes_2d", s, _boxes_2d)
        if "boxes_2d_full" in f and jax_layout:
            v["boxes_2d_full"] = _guard(p(f"box_2d_full_annotations/{stem}.txt"), "boxes_2d_full", s, _boxes_2d)
        if f & {"camera", "pose"}:
            model, pose = self.calibration(c)
            if "camera" in f:
                v["camera"] = model
            if "pose" in f:
                v["pose"] = pose
        self._check_shapes(s, c, v)
        return CameraSample(**v)

    def _check_shapes(self, s: str, c: str, v: Mapping[str, Any]) -> None:
        """Every per-pixel array of a camera has the camera's image size (``dataset.json``'s
        ``image_size_wh``; in the release: the first array read) and its documented rank and dtype."""
        size = None
        if self.manifest is not None:
            wh = self.manifest.get("image_size_wh", {}).get(c)
            if isinstance(wh, list) and len(wh) == 2:
                size = (int(wh[1]), int(wh[0]))
        for field, (kinds, trailing) in _PIXEL_FIELDS.items():
            a = v.get(field)
            if a is None:
                continue
            stem = f"{s}_{c}"
            path = self._path(_PIXEL_FILES[field].format(stem=stem))
            if field == "flow_valid" and not path.is_file():
                path = self._path(f"optical_flow/kitti/{stem}.png")
            if a.dtype.kind not in kinds or a.ndim != 2 + len(trailing) or a.shape[2:] != trailing:
                raise _fail(path, field, s, f"expected {'x'.join(['H', 'W', *map(str, trailing)])} values of kind "
                                            f"{kinds!r}, got {a.dtype} {a.shape}")
            if size is None:
                size = a.shape[:2]
            elif a.shape[:2] != size:
                raise _fail(path, field, s, f"image size {a.shape[1]} x {a.shape[0]} differs from the camera's "
                                            f"{size[1]} x {size[0]}")

    def _timestamp(self, s: str, sensor: Mapping[str, Any] | None) -> float:
        if sensor is not None:
            path = self._path(f"sensor_data/{s}.json")
            return _guard(path, "timestamp_s", s, lambda _: float(_array(sensor["timestamp_s"], ())))
        path = self._path(f"vehicle_data/rgb_images/{s}.txt")
        rec = _guard(path, "timestamp_s", s, _vehicle_text)
        if len(rec.get("timestamp_s", [])) != 1:
            raise _fail(path, "timestamp_s", s, "line 'timestamp_s' with one number missing")
        return rec["timestamp_s"][0]

    def _ego(self, s: str, sensor: Mapping[str, Any] | None) -> Ego:
        if sensor is not None:
            path = self._path(f"sensor_data/{s}.json")

            def parse(_):
                e = sensor["ego"]
                prev = sensor.get("previous_timestamp_s")
                return Ego(vehicle_to_world=_array(e["vehicle_to_world"], (4, 4)),
                           velocity_mps=_array(e["velocity_mps"], (3,)),
                           acceleration_mps2=_array(e["acceleration_mps2"], (3,)),
                           angular_velocity_radps=_array(e["angular_velocity_radps"], (3,)),
                           previous_timestamp_s=None if prev is None else float(prev),
                           frame=str(e.get("frame", "as stated in sensor_data")))

            return _guard(path, "ego", s, parse)
        path = self._path(f"vehicle_data/rgb_images/{s}.txt")
        prev_path = self._path(f"vehicle_data/previous_images/{s}.txt")

        def parse_text(q):
            rec = _vehicle_text(q)
            return (_array(rec["location_m"], (3,)), _array(rec["rotation_deg"], (3,)),
                    _array(rec["velocity_mps"], (3,)), _array(rec["acceleration_mps2"], (3,)),
                    _array(rec["angular_velocity_degps"], (3,)))

        loc, rot, vel, acc, ang = _guard(path, "ego", s, parse_text)
        prev = None
        if prev_path.is_file():
            prev_rec = _guard(prev_path, "ego", s, _vehicle_text)
            if len(prev_rec.get("timestamp_s", [])) == 1:
                prev = prev_rec["timestamp_s"][0]
        return Ego(vehicle_to_world=vehicle_to_world_matrix(loc, rot), velocity_mps=vel, acceleration_mps2=acc,
                   angular_velocity_radps=np.deg2rad(ang), previous_timestamp_s=prev,
                   frame="CARLA world (vehicle_data): vehicle_to_world maps the ISO 8855 vehicle frame to the CARLA "
                         "world; velocity, acceleration and angular velocity in the CARLA world frame")

    def _imu(self, s: str, sensor: Mapping[str, Any]) -> Imu | None:
        path = self._path(f"sensor_data/{s}.json")
        if sensor.get("imu") is None:
            return None
        return _guard(path, "imu", s, lambda _: Imu(
            accelerometer_mps2=_array(sensor["imu"]["accelerometer_mps2"], (3,)),
            gyroscope_radps=_array(sensor["imu"]["gyroscope_radps"], (3,)),
            compass_rad=float(_array(sensor["imu"]["compass_rad"], ()))))

    def _gnss(self, s: str, sensor: Mapping[str, Any]) -> Gnss | None:
        path = self._path(f"sensor_data/{s}.json")
        if sensor.get("gnss") is None:
            return None
        g = sensor["gnss"]
        return _guard(path, "gnss", s, lambda _: Gnss(
            latitude_deg=float(_array(g["latitude_deg"], ())), longitude_deg=float(_array(g["longitude_deg"], ())),
            altitude_m=float(_array(g["altitude_m"], ()))))

    def _boxes_3d(self, s: str) -> Boxes3D:
        ext = self._path(f"box_3d_annotations_ext/{s}.json")
        if self.layout == LAYOUT_JAXFISH or ext.is_file():
            def parse(q):
                rows = _json(q)["boxes"]
                k = len(rows)
                return Boxes3D(actor_id=np.asarray([int(r["actor_id"]) for r in rows], np.int64),
                               class_id=np.asarray([int(r["class_id"]) for r in rows], np.int64),
                               class_name=tuple(str(r["class_name"]) for r in rows),
                               corners_vehicle=_array([r["corners_vehicle"] for r in rows] or np.zeros((0, 8, 3)),
                                                      (k, 8, 3)),
                               corners_world=_array([r["corners_world"] for r in rows] or np.zeros((0, 8, 3)),
                                                    (k, 8, 3)))

            return _guard(ext, "boxes_3d", s, parse)

        def parse_pkl(q):
            d = _pickle(q)
            if not isinstance(d, Mapping):
                raise ValueError(f"expected a dict {{actor_id: (8, 3) corners}}, got {type(d).__name__}")
            keys = sorted(int(a) for a in d)
            k = len(keys)
            world = np.stack([_array(d[a], (8, 3)) for a in keys]) if k else np.zeros((0, 8, 3))
            return Boxes3D(actor_id=np.asarray(keys, np.int64), class_id=np.full(k, -1, np.int64),
                           class_name=("unknown",) * k, corners_vehicle=None, corners_world=world)

        boxes = _guard(self._path(f"box_3d_annotations/{s}.pkl"), "boxes_3d", s, parse_pkl)
        ego_path = self._path(f"vehicle_data/rgb_images/{s}.txt")
        if not ego_path.is_file():
            return boxes
        rec = _guard(ego_path, "boxes_3d", s, _vehicle_text)
        if len(rec.get("location_m", ())) != 3 or len(rec.get("rotation_deg", ())) != 3:
            return boxes
        m = vehicle_to_world_matrix(np.asarray(rec["location_m"]), np.asarray(rec["rotation_deg"]))
        inv = np.linalg.inv(m)
        return eqx.tree_at(lambda b: b.corners_vehicle, boxes, boxes.corners_world @ inv[:3, :3].T + inv[:3, 3],
                           is_leaf=lambda x: x is None)

    def _bev(self, s: str, semantics: np.ndarray | None) -> BevSample:
        grid = self._calibrations[BEV_CAMERA]
        stem = f"{s}_{BEV_CAMERA}"
        height = _guard(self._path(f"bev_height/raw_data/{stem}.npy"), "bev", s, load_npy)
        occ = _guard(self._path(f"bev_occupancy/{stem}.png"), "bev", s, _mask)
        if semantics is None:
            semantics = _guard(self._path(f"semantic_annotations/gtLabels/{stem}.png"), "bev", s,
                               lambda q: _image(q, 1, lossless=True))
        where = self._path(f"calibration_data/{BEV_CAMERA}.json")
        mpp = _guard(where, "bev", None, lambda _: float(_array(grid["metres_per_pixel"], ())))
        a = _guard(where, "bev", None, lambda _: _array(grid["pixel_to_vehicle_xy"], (2, 3)))
        return BevSample(height=height, occupancy=occ, semantics=semantics, metres_per_pixel=mpp,
                         pixel_to_vehicle_xy=a)

    def _lidar(self, s: str) -> dict[str, Any]:
        f, out = self.fields, {}
        veh = self._path(f"lidar_vehicle/{s}.npy")
        sem = self._path(f"semantic_lidar_vehicle/{s}.npy")
        rad = self._path(f"radar_data/{s}.npy")
        pkl = self._path(f"lidar_data/{s}.pkl")
        raw: dict[str, Any] | None = None

        def raw_record() -> dict[str, Any]:
            nonlocal raw
            if raw is None:
                d = _guard(pkl, "lidar", s, _pickle)
                if isinstance(d, np.ndarray) and d.dtype.names is None:
                    d = {"points": d}  # a bare (N, 4) array of points
                if not isinstance(d, Mapping):
                    raise _fail(pkl, "lidar", s, f"expected a dict with 'points', got {type(d).__name__}")
                raw = dict(d)
            return raw

        if "lidar" in f:
            if veh.is_file():
                pts = _guard(veh, "lidar", s, load_npy)
                out["lidar_frame"] = LIDAR_FRAME_VEHICLE
            else:
                pts = raw_record().get("points")
                out["lidar_frame"] = LIDAR_FRAME_SENSOR
            pts_path = veh if veh.is_file() else pkl
            pts = _guard(pts_path, "lidar", s, lambda _: np.asarray(pts))
            if pts.ndim != 2 or pts.shape[1] != 4 or pts.dtype.kind != "f":
                raise _fail(pts_path, "lidar", s, f"expected float (N, 4) points, got {pts.dtype} {pts.shape}")
            out["lidar"] = pts
        if "semantic_lidar" in f:
            if sem.is_file():
                arr = _guard(sem, "semantic_lidar", s, load_npy)
                where = sem
            else:
                arr, where = raw_record().get("semantic_lidar"), pkl
            out["semantic_lidar"] = _guard(where, "semantic_lidar", s, lambda _: _semantic_lidar(arr))
        if "radar" in f:
            if rad.is_file():
                out["radar"] = _guard(rad, "radar", s, load_npy)
            else:
                r = raw_record().get("radar")
                out["radar"] = None if r is None else _guard(pkl, "radar", s, lambda _: _structured(r))
        return out


_PIXEL_FIELDS: dict[str, tuple[str, tuple[int, ...]]] = {
    "rgb": ("u", (3,)), "rgb_prev": ("u", (3,)), "depth": ("f", ()), "z_depth": ("f", ()), "semantics": ("u", ()),
    "instances": ("u", ()), "motion": ("b", ()), "flow": ("f", (2,)), "flow_valid": ("b", ()),
    "flow_occlusion": ("b", ())}
_PIXEL_FILES = {"rgb": "rgb_images/{stem}.png", "rgb_prev": "previous_images/{stem}_prev.png",
                "depth": "depth_maps/raw_data/{stem}.npy", "z_depth": "depth_maps/z_depth/{stem}.npy",
                "semantics": "semantic_annotations/gtLabels/{stem}.png",
                "instances": "instance_annotations/gtLabels/{stem}.png",
                "motion": "motion_annotations/gtLabels/{stem}.png", "flow": "optical_flow/raw_data/{stem}.flo",
                "flow_valid": "optical_flow/valid_mask/{stem}.png",
                "flow_occlusion": "optical_flow/occlusion_mask/{stem}.png"}


def _kitti_valid(path: Path) -> np.ndarray:
    a = read_image(path, lossless=True)
    if a.dtype != np.uint16 or a.shape[-1] < 3:
        raise DatasetReadError(f"{path}: a KITTI flow PNG has 3 uint16 channels, got {a.dtype} {a.shape}")
    return a[..., 2] > 0


def _structured(a: Any) -> np.ndarray:
    arr = np.asarray(a)
    if arr.dtype.names is None or arr.ndim != 1:
        raise ValueError(f"expected a 1-D structured array, got {arr.dtype} {arr.shape}")
    return arr


def _semantic_lidar(a: Any) -> np.ndarray | None:
    if a is None:
        return None
    arr = _structured(a)
    if arr.dtype.names == SEMANTIC_LIDAR_DTYPE.names:
        return arr
    if len(arr.dtype.names) != len(SEMANTIC_LIDAR_DTYPE.names):
        raise ValueError(f"expected fields {SEMANTIC_LIDAR_DTYPE.names} (or CARLA's x, y, z, CosAngle, ObjIdx, "
                         f"ObjTag), got {arr.dtype.names}")
    out = np.empty(arr.shape, SEMANTIC_LIDAR_DTYPE)
    for new, old in zip(SEMANTIC_LIDAR_DTYPE.names, arr.dtype.names, strict=True):
        out[new] = arr[old]
    return out


def vehicle_to_world_matrix(location_m: Float[np.ndarray, " 3"], rotation_deg: Float[np.ndarray, " 3"]
                            ) -> Float[np.ndarray, "4 4"]:
    """4 x 4 ISO 8855 vehicle -> CARLA world of an actor with CARLA transform ``(location_m,
    (pitch, yaw, roll) degrees)`` in float64 NumPy (`jaxfish.groundtruth.vehicle_to_world_from_carla`)."""
    p, y, r = np.deg2rad(np.asarray(rotation_deg, np.float64))
    cp, sp, cy, sy, cr, sr = np.cos(p), np.sin(p), np.cos(y), np.sin(y), np.cos(r), np.sin(r)
    rot = np.array([[cp * cy, cy * sp * sr - sy * cr, -cy * sp * cr - sy * sr],
                    [cp * sy, sy * sp * sr + cy * cr, -sy * sp * cr + cy * sr],
                    [sp, -cp * sr, cp * cr]])
    m = np.eye(4)
    m[:3, :3] = rot @ np.diag([1.0, -1.0, 1.0])
    m[:3, 3] = np.asarray(location_m, np.float64)
    return m


def _carla_key(calibration: Any) -> bool:
    return isinstance(calibration, Mapping) and isinstance(calibration.get("extrinsic"), Mapping) and \
        SYNWOODSCAPE_TRANSLATION_KEY in calibration["extrinsic"]


# ----------------------------------------------------------------------------- open


def _check_fields(fields: Iterable[str] | None) -> frozenset[str]:
    if fields is None:
        return frozenset(FIELDS)
    if isinstance(fields, str):
        raise TypeError(f"fields must be a collection of field names, got the string {fields!r}")
    sel = frozenset(fields)
    unknown = sorted(str(x) for x in sel - set(FIELDS))
    if unknown:
        raise ValueError(f"open: unknown field(s) {', '.join(map(repr, unknown))}; the fields are "
                         f"{', '.join(FIELDS)}")
    return sel


def open(path: str | os.PathLike, *, fields: Iterable[str] | None = None,  # noqa: A001 (the public name)
         cameras: Iterable[str] | None = None) -> SynWoodScapeDataset:
    """Open a dataset: a jaxfish-built one (``dataset.json``) or SynWoodScape's released layout.

    ``fields``: the field names to read (default `FIELDS`, all); the others are None in every
    sample and their files are never opened. ``cameras``: the cameras to read (default every
    camera of the dataset, fisheyes then BEV). Unknown names raise `ValueError`; a missing or
    malformed dataset-level file raises `DatasetReadError` naming it. For the released layout,
    SynWoodScape's CARLA-key calibrations get the author's corrected translations
    (`jaxfish.SYNWOODSCAPE_CORRECTED_TRANSLATIONS_CARLA`, WoodScape #113): listed in
    ``corrections`` and warned about once (`UserWarning`)."""
    root = Path(path)
    sel = _check_fields(fields)
    if not root.is_dir():
        raise DatasetReadError(f"{root}: not a dataset folder (not a directory)")
    manifest_path = root / "dataset.json"
    notes: list[str] = []
    corrections: list[str] = []
    manifest = None
    if manifest_path.exists():
        manifest = _guard(manifest_path, "format", None, _json)
        if not isinstance(manifest, dict) or manifest.get("format") != DATASET_FORMAT:
            got = manifest.get("format") if isinstance(manifest, dict) else type(manifest).__name__
            raise _fail(manifest_path, "format", None, f"expected {DATASET_FORMAT!r}, got {got!r}")
        layout = LAYOUT_JAXFISH
        samples = manifest.get("samples")
        if not isinstance(samples, list) or not all(isinstance(x, str) and x.isascii() and x.isdigit() for x in samples):
            raise _fail(manifest_path, "samples", None, "expected a list of sample ids (strings of digits)")
        found = manifest.get("cameras")
        if not isinstance(found, list) or not all(isinstance(x, str) for x in found):
            raise _fail(manifest_path, "cameras", None, "expected a list of camera names")
        all_cams = tuple(found)
    elif (root / "rgb_images").is_dir():
        layout = LAYOUT_RELEASE
        names = os.listdir(root / "rgb_images")
        pat = re.compile(r"(\d+)_(FV|RV|MVL|MVR|BEV)\.png")
        samples = _sample_ids(names, pat)
        present = {m.group(2) for n in names if (m := pat.fullmatch(n))}
        all_cams = tuple(c for c in (*FISHEYE_CAMERAS, BEV_CAMERA) if c in present)
        notes += ["released SynWoodScape layout (no dataset.json): depth_maps/raw_data is returned as stored (the "
                  "release does not say whether it is range or z-depth; jaxfish writes range)",
                  "box_3d_annotations carry no class: Boxes3D.class_id is -1; corners_vehicle is computed from "
                  "the ego's location_m / rotation_deg in vehicle_data (None without them)",
                  "no z_depth, boxes_2d_full, flow_valid (no KITTI PNG), BEV maps or BEV calibration in the release",
                  "lidar: lidar_data/{id}.pkl points in the lidar's Unreal frame (lidar_frame 'sensor-unreal')"]
    else:
        raise DatasetReadError(f"{root}: not a dataset: neither dataset.json nor rgb_images/ found")
    if cameras is None:
        cams = all_cams
    else:
        if isinstance(cameras, str):
            raise TypeError(f"cameras must be a collection of camera names, got the string {cameras!r}")
        cams = tuple(cameras)
        unknown = [c for c in cams if c not in all_cams]
        if unknown:
            raise ValueError(f"open: camera(s) {unknown} not in the dataset {root} (it has {list(all_cams)})")
    calibrations: dict[str, Any] = {}
    for c in all_cams:
        p = root / "calibration_data" / f"{c}.json"
        if c == BEV_CAMERA:
            if p.is_file():
                calibrations[c] = _guard(p, "camera", None, _json)
            elif layout == LAYOUT_JAXFISH:
                raise _fail(p, "camera", None, "file missing")
            continue
        calibrations[c] = _guard(p, "camera", None, _json)
        if layout == LAYOUT_RELEASE and _carla_key(calibrations[c]):
            corrections.append(_correction(p, c, calibrations[c]))
    sequences = None
    seq_path = root / "sequence.json"
    if seq_path.exists():
        sequences = _guard(seq_path, "sequences", None, _json)
        if not isinstance(sequences, dict) or not isinstance(sequences.get("sequences"), list):
            raise _fail(seq_path, "sequences", None, "expected an object with a list 'sequences'")
    corrections = [x for x in corrections if x]
    if corrections:
        warnings.warn(f"{root}: SynWoodScape's released calibrations corrected (WoodScape #113): "
                      + "; ".join(corrections), UserWarning, stacklevel=2)
    samples = tuple(samples)
    return SynWoodScapeDataset(root, layout=layout, samples=samples, all_samples=samples, cameras=cams, fields=sel,
                               manifest=manifest, calibrations=calibrations, corrections=tuple(corrections),
                               notes=tuple(notes), sequences=sequences)


def _correction(path: Path, camera: str, data: Mapping[str, Any]) -> str:
    from .. import SYNWOODSCAPE_CORRECTED_TRANSLATIONS_CARLA

    KEY = SYNWOODSCAPE_TRANSLATION_KEY

    published = _guard(path, f"extrinsic.{KEY}", None, lambda _: _array(data["extrinsic"][KEY], (3,)))
    fixed = SYNWOODSCAPE_CORRECTED_TRANSLATIONS_CARLA.get(camera)
    if fixed is None or np.allclose(published, fixed, atol=1e-9, rtol=0):
        return ""
    return (f"calibration_data/{camera}.json: translation (CARLA frame) {published.tolist()} replaced by "
            f"{list(fixed)}")


# ----------------------------------------------------------------------------- collate

PAD_INT = -1
"""Pad value of collated integer ids (box class ids, actor ids) and 2D box coordinates."""
PAD_FLOAT = 0.0
"""Pad value of collated point clouds, 3D box corners and (zero-filled records) events, radar and
semantic lidar."""


def _pad(arrays: Sequence[np.ndarray], fill) -> tuple[np.ndarray, np.ndarray]:
    counts = np.asarray([len(a) for a in arrays], np.int64)
    n = int(counts.max(initial=0))
    first = arrays[0]
    out = np.zeros((len(arrays), n) + first.shape[1:], first.dtype)
    if first.dtype.names is None:
        out[...] = fill
    for i, a in enumerate(arrays):
        out[i, : len(a)] = a
    return out, counts


def _stack(name: str, values: Sequence[Any]) -> Any:
    if all(v is None for v in values):
        return None
    if any(v is None for v in values):
        raise ValueError(f"collate: field {name!r} is None in some samples and not in others")
    shapes = {np.shape(v) for v in values}
    if len(shapes) != 1:
        raise ValueError(f"collate: field {name!r} has different shapes {sorted(shapes)} across the batch")
    return np.stack(values)


def _boxes2d_batch(name: str, values: Sequence[Boxes2D | None]) -> dict[str, np.ndarray] | None:
    if all(v is None for v in values):
        return None
    if any(v is None for v in values):
        raise ValueError(f"collate: field {name!r} is None in some samples and not in others")
    xyxy, count = _pad([v.xyxy for v in values], PAD_INT)
    cid, _ = _pad([v.class_id for v in values], PAD_INT)
    return {"xyxy": xyxy, "class_id": cid, "count": count}


def collate(samples: Sequence[Sample]) -> dict[str, Any]:
    """Stack a list of `Sample`\\ s into a batch of NumPy arrays (leading axis B), e.g. as a
    DataLoader's ``collate_fn``. Returns a dict:

    - ``"id"``: list of ids; ``"timestamp_s"``: ``(B,)`` float64 (or None);
    - ``"cameras"``: ``{camera: {field: (B, ...) array}}`` for the images and maps; ragged fields
      are padded: ``"events"`` ``(B, N_max)`` (zero records) with ``"events_count"`` ``(B,)``;
      ``"boxes_2d"`` / ``"boxes_2d_full"`` ``{"xyxy" (B, K_max, 4), "class_id" (B, K_max)}``
      padded with `PAD_INT` and ``"count"`` ``(B,)``; ``"camera"``: the list of B camera models
      (per-sample calibrations kept, not stacked); ``"camera_to_vehicle"``: ``(B, 4, 4)``;
    - ``"boxes_3d"``: ``{"actor_id", "class_id" (B, K_max) padded with PAD_INT, "corners_vehicle",
      "corners_world" (B, K_max, 8, 3) padded with PAD_FLOAT, "count" (B,)}``;
    - ``"lidar"`` ``(B, N_max, 4)`` padded with PAD_FLOAT, ``"lidar_count"``; likewise
      ``"semantic_lidar"`` / ``"radar"`` (zero records) with their counts;
    - ``"bev"``: ``{"height", "occupancy", "semantics", "pixel_to_vehicle_xy", "metres_per_pixel"}``
      stacked; ``"ego"``: ``{"vehicle_to_world" (B, 4, 4), "velocity_mps", ...}``; ``"imu"``,
      ``"gnss"``: stacked fields.

    A field that is None in every sample is None; None in some samples only, or of different
    shapes across samples, raises `ValueError`."""
    samples = list(samples)
    if not samples:
        raise ValueError("collate: no samples")
    out: dict[str, Any] = {"id": [s.id for s in samples],
                           "timestamp_s": _stack("timestamp_s", [s.timestamp_s for s in samples])}
    names = list(samples[0].cameras)
    if any(list(s.cameras) != names for s in samples):
        raise ValueError("collate: samples have different cameras")
    cams: dict[str, Any] = {}
    for c in names:
        cs = [s.cameras[c] for s in samples]
        d: dict[str, Any] = {}
        for f in ("rgb", "rgb_prev", "depth", "z_depth", "semantics", "instances", "motion", "flow", "flow_valid",
                  "flow_occlusion"):
            d[f] = _stack(f"{c}.{f}", [getattr(x, f) for x in cs])
        ev = [x.events for x in cs]
        if all(e is not None for e in ev):
            d["events"], d["events_count"] = _pad(ev, 0)
        else:
            d["events"] = _stack(f"{c}.events", ev)
            d["events_count"] = None
        d["boxes_2d"] = _boxes2d_batch(f"{c}.boxes_2d", [x.boxes_2d for x in cs])
        d["boxes_2d_full"] = _boxes2d_batch(f"{c}.boxes_2d_full", [x.boxes_2d_full for x in cs])
        d["camera"] = None if all(x.camera is None for x in cs) else [x.camera for x in cs]
        d["camera_to_vehicle"] = _stack(f"{c}.pose", [None if x.pose is None else np.asarray(x.pose.as_matrix())
                                                      for x in cs])
        cams[c] = d
    out["cameras"] = cams
    b3 = [s.boxes_3d for s in samples]
    if all(b is None for b in b3):
        out["boxes_3d"] = None
    else:
        if any(b is None for b in b3):
            raise ValueError("collate: field 'boxes_3d' is None in some samples and not in others")
        aid, count = _pad([b.actor_id for b in b3], PAD_INT)
        cid, _ = _pad([b.class_id for b in b3], PAD_INT)
        world, _ = _pad([b.corners_world for b in b3], PAD_FLOAT)
        veh = None if any(b.corners_vehicle is None for b in b3) else _pad([b.corners_vehicle for b in b3],
                                                                            PAD_FLOAT)[0]
        out["boxes_3d"] = {"actor_id": aid, "class_id": cid, "corners_vehicle": veh, "corners_world": world,
                           "count": count}
    for name in ("lidar", "semantic_lidar", "radar"):
        vals = [getattr(s, name) for s in samples]
        if all(v is not None for v in vals):
            out[name], out[f"{name}_count"] = _pad(vals, PAD_FLOAT)
        else:
            out[name], out[f"{name}_count"] = _stack(name, vals), None
    out["lidar_frame"] = [s.lidar_frame for s in samples]
    for name, keys in (("bev", ("height", "occupancy", "semantics", "pixel_to_vehicle_xy", "metres_per_pixel")),
                       ("ego", ("vehicle_to_world", "velocity_mps", "acceleration_mps2", "angular_velocity_radps")),
                       ("imu", ("accelerometer_mps2", "gyroscope_radps", "compass_rad")),
                       ("gnss", ("latitude_deg", "longitude_deg", "altitude_m"))):
        recs = [getattr(s, name) for s in samples]
        if all(r is None for r in recs):
            out[name] = None
        elif any(r is None for r in recs):
            raise ValueError(f"collate: field {name!r} is None in some samples and not in others")
        else:
            out[name] = {k: _stack(f"{name}.{k}", [getattr(r, k) for r in recs]) for k in keys}
    return out
