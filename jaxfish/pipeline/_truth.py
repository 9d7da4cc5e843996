"""One entry point from a `Frame` to every ground truth of its sample: `sample_truth`."""

from __future__ import annotations

import concurrent.futures
import functools
from collections.abc import Hashable, Sequence
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int, UInt8

from .. import bev as jbev
from .. import groundtruth as gt
from .._sequences import KeptByOwner, sequence_slots, usable_cores
from ..cameras import AbstractCamera, Orthographic
from ..groundtruth._rig import resolve_batch_mode
from ..transforms import Pose
from ._constants import RigConstants
from ._events import camera_events
from ._frame import Frame, Motion, SensorRecords, box_slots
from ._render import depth_to_color, events_color
from ._sensors import SensorTruth, sensor_truth


class GroundTruthOptions(eqx.Module):
    """What `sample_truth` computes (every field static).

    - `backward_flow`: also the backward flow (t -> t-1 on the t grid);
    - `motion_threshold_m`: an actor moves when its box is displaced by more than this (metres);
    - `margin_m`, `fallback_m`, `max_candidates`, `surface_samples`: the instance segmentation's
      and full 2D boxes' settings (`jaxfish.groundtruth.fisheye_ground_truth`);
    - `batch`: how cameras and frames are mapped (``"auto"``: a loop of per-camera programs on
      CPU, `jax.vmap` elsewhere; `jaxfish.groundtruth.rig_ground_truth`);
    - `bev`: compute the BEV top view's ground truth when the frame has one;
    - `occupancy_min_height_m`: BEV occupancy threshold above the ground (metres).
    """

    backward_flow: bool = eqx.field(static=True, default=False)
    motion_threshold_m: float = eqx.field(static=True, default=gt.MOTION_THRESHOLD_M)
    margin_m: float = eqx.field(static=True, default=gt.BOX_MARGIN_M)
    fallback_m: float = eqx.field(static=True, default=gt.FALLBACK_DISTANCE_M)
    max_candidates: int | None = eqx.field(static=True, default=None)
    surface_samples: int = eqx.field(static=True, default=gt.SURFACE_SAMPLES)
    batch: str = eqx.field(static=True, default="auto")
    bev: bool = eqx.field(static=True, default=True)
    occupancy_min_height_m: float = eqx.field(static=True, default=jbev.OCCUPANCY_MIN_HEIGHT_M)

    def ground_truth_keywords(self) -> dict:
        """The keyword arguments of `jaxfish.groundtruth.rig_ground_truth` and
        `jaxfish.groundtruth.view_ground_truth` these options set."""
        return {"motion_threshold_m": self.motion_threshold_m, "backward_flow": self.backward_flow,
                "margin_m": self.margin_m, "fallback_m": self.fallback_m, "max_candidates": self.max_candidates,
                "surface_samples": self.surface_samples}

    def __check_init__(self) -> None:
        if self.batch not in ("auto", "loop", "vmap"):
            raise ValueError(f"GroundTruthOptions.batch must be 'auto', 'loop' or 'vmap', got {self.batch!r}")


class CameraTruth(eqx.Module):
    """Every ground truth of one camera of a sample, with the renderings the dataset stores.

    - `name`: the camera's name (``"BEV"`` for the top view);
    - `camera`: its lens model (float32);
    - `truth`: `jaxfish.groundtruth.CameraGroundTruth` (images at t-1 and t, range, semantics,
      instances, motion, flow, 2D boxes, displacements);
    - `z_depth_m` ``(H, W)``: planar depth along the optical axis (far 1000, no ray 0);
    - `depth_rgb`, `semantic_rgb`, `instance_rgb`, `flow_rgb` ``(H, W, 3)`` uint8: renderings
      (`depth_to_color`, SynWoodScape palette, `instance_colors`, `flow_to_color`);
      `flow_backward_rgb` likewise or None;
    - `events`: fisheye DVS events (CARLA dtype, t in ns, time order) or None (the BEV);
      `events_rgb`: their rendering or None.
    """

    name: str = eqx.field(static=True)
    camera: AbstractCamera
    truth: gt.CameraGroundTruth
    z_depth_m: Float[Array, "H W"]
    depth_rgb: UInt8[np.ndarray, "H W 3"]
    semantic_rgb: UInt8[Array, "H W 3"]
    instance_rgb: UInt8[Array, "H W 3"]
    flow_rgb: UInt8[Array, "H W 3"]
    flow_backward_rgb: UInt8[Array, "H W 3"] | None
    events: np.ndarray | None
    events_rgb: UInt8[np.ndarray, "H W 3"] | None


class BevTruth(eqx.Module):
    """The BEV top view's ground truth: `view` (`CameraTruth` named ``"BEV"``), its `camera`
    and `camera_to_vehicle`, `height_m` ``(H, W)`` metres above the ground, `occupancy`
    ``(H, W)`` (top surface above `occupancy_min_height_m`), `height_rgb` (viridis rendering,
    `jaxfish.bev.colorize_height`), `pixel_to_vehicle_xy` ``(2, 3)`` (`jaxfish.bev.bev_pixel_to_vehicle`) and
    `box_class_id` ``(B,)``: the class of each box slot of its ground truth (its 2D boxes' classes)."""

    view: CameraTruth
    camera: Orthographic
    camera_to_vehicle: Pose
    height_m: Float[np.ndarray, "H W"]
    occupancy: Bool[np.ndarray, "H W"]
    occupancy_min_height_m: float = eqx.field(static=True)
    height_rgb: UInt8[np.ndarray, "H W 3"]
    pixel_to_vehicle_xy: Float[np.ndarray, "2 3"]
    box_class_id: Int[np.ndarray, " B"]


class SampleTruth(eqx.Module):
    """Every ground truth of one sample (a `Frame` through `sample_truth`).

    - `index`: the frame number; `cameras`: one `CameraTruth` per fisheye camera (the frame's
      order); `bev`: `BevTruth` or None;
    - `motion`: the frame's `Motion` (boxes padded as computed);
    - `displacement_m` ``(B,)``: every box's displacement between t-1 and t (metres);
    - `corners_world` / `corners_vehicle` ``(B, 8, 3)`` float64: box corners in the CARLA world
      and in the ISO 8855 vehicle frame at t;
    - `sensors`: the frame's `SensorRecords`, unchanged (None when the source read none);
    - `vehicle_sensors`: the same sensors in the ISO 8855 vehicle frame at t (`SensorTruth`:
      ego state, IMU, GNSS, lidar, semantic lidar, radar; `sensor_truth`), None with `sensors`.
    """

    index: int = eqx.field(static=True)
    cameras: tuple[CameraTruth, ...]
    bev: BevTruth | None
    motion: Motion
    displacement_m: Float[np.ndarray, " B"]
    corners_world: Float[np.ndarray, "B 8 3"]
    corners_vehicle: Float[np.ndarray, "B 8 3"]
    sensors: SensorRecords | None
    vehicle_sensors: SensorTruth | None = None

    @property
    def names(self) -> tuple[str, ...]:
        """Every camera's name: the fisheyes, then ``"BEV"`` when present."""
        return tuple(c.name for c in self.cameras) + (() if self.bev is None else ("BEV",))

    def camera_truths(self) -> tuple[CameraTruth, ...]:
        """The fisheye `CameraTruth`\\ s, then the BEV's view when present."""
        return self.cameras + (() if self.bev is None else (self.bev.view,))


@functools.cache
def _jitted() -> dict:
    return {"colorize": jax.jit(gt.colorize_labels), "instance_colors": jax.jit(gt.instance_colors),
            "z_depth": jax.jit(gt.range_to_z_depth), "height_rgb": jax.jit(jbev.colorize_height),
            "occupancy": jax.jit(jbev.occupancy_map, static_argnames="min_height_m"),
            "flow_color": jax.jit(gt.flow_to_color, static_argnames="max_radius")}


def _camera_truth(name: str, camera, rays, truth: gt.CameraGroundTruth, events: np.ndarray | None,
                  backward: bool) -> CameraTruth:
    jit = _jitted()
    h, w = np.asarray(truth.images.valid).shape
    rng = np.asarray(truth.images.range_m, np.float32)

    def flow_rgb(field: gt.FlowField):
        # Device arrays as they are: a NumPy copy would be copied back into the program.
        return jit["flow_color"](jnp.asarray(field.flow, jnp.float32), valid=jnp.asarray(field.valid), max_radius=None)

    return CameraTruth(
        name=name, camera=camera, truth=truth,
        z_depth_m=jit["z_depth"](camera, truth.images.range_m, rays=rays),
        depth_rgb=depth_to_color(rng),
        semantic_rgb=jit["colorize"](jnp.asarray(truth.semantic)),
        instance_rgb=jit["instance_colors"](jnp.asarray(truth.instances.actor_id)),
        flow_rgb=flow_rgb(truth.flow),
        flow_backward_rgb=flow_rgb(truth.flow_backward) if backward and truth.flow_backward is not None else None,
        events=events, events_rgb=None if events is None else events_color(events, width=w, height=h))


def _fisheye_truths(frames: Sequence[Frame], constants: RigConstants, options: GroundTruthOptions,
                    motions: Sequence[Motion]) -> list[list[CameraTruth]]:
    """Every fisheye camera of every frame, in one `rig_ground_truth` call; in loop mode one call
    per frame, in order (the loop's results are each frame's alone either way, and a frame whose
    faces at t-1 are the previous frame's at t takes its images at t-1 from it)."""
    cams = constants.cameras
    n, c = len(frames), len(cams)
    if n > 1 and resolve_batch_mode(options.batch) == "loop":
        return [_fisheye_truths([f], constants, options, [m])[0] for f, m in zip(frames, motions, strict=True)]

    def stack(instant: str, key: str) -> np.ndarray | list:
        """One sample: the cameras' arrays as they are (a list); several: one copy into an
        ``(N, C, F, S, S[, 3])`` array."""
        parts = [getattr(getattr(cf, instant), key) for f in frames for cf in f.camera_frames]
        return parts if n == 1 else np.stack(parts).reshape((n, c) + parts[0].shape)

    prev, curr = ({k: stack(inst, k) for k in ("rgb", "depth_m", "semantic")} for inst in ("faces_prev", "faces"))
    c2v = Pose(np.stack([np.asarray(k.camera_to_vehicle.rotation_matrix, np.float32) for k in cams]),
               np.stack([np.asarray(k.camera_to_vehicle.translation, np.float32) for k in cams]))
    per_sample = jax.tree_util.tree_map(
        lambda *xs: np.asarray(xs[0]) if n == 1 else np.stack([np.asarray(x) for x in xs]),
        *[(m.boxes_prev, m.boxes, m.vehicle_to_world_prev, m.vehicle_to_world) for m in motions])
    sequential = n == 1 and resolve_batch_mode(options.batch) == "loop"
    if _events_beside_programs():
        with concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="jaxfish-events") as pool:
            mapped = pool.submit(_mapped_events, frames, cams)
            rows = _rig_rows(frames, constants, options, cams, prev, curr, c2v, per_sample, sequential)
            events = mapped.result()
    else:
        rows = _rig_rows(frames, constants, options, cams, prev, curr, c2v, per_sample, sequential)
        events = _mapped_events(frames, cams)
    return [[_camera_truth(k.name, k.camera, k.rays, truth, ev, options.backward_flow)
             for k, truth, ev in zip(cams, row, evs, strict=True)]
            for row, evs in zip(rows, events, strict=True)]


def _events_beside_programs() -> bool:
    """Whether `sample_truths` maps the fisheye cameras' face events (`camera_events`, NumPy on
    the host) in a thread of its own while the cameras' compiled programs run: when this process
    builds fewer sequences at once (`jaxfish.pipeline.sequence_slots`: one for a serial build) than
    it may use cores (its CPU affinity), so that a core the programs leave idle maps them. Otherwise
    (thread workers on every core, a process pinned to one core) the events are mapped after the
    programs, in the calling thread: a further thread would only contend for busy cores. The
    events are the same either way."""
    return sequence_slots() < usable_cores()


def _mapped_events(frames: Sequence[Frame], cams) -> list[list[np.ndarray]]:
    """Every camera's face events of every frame mapped to its fisheye (`camera_events`)."""
    return [[camera_events(cf.events, k.event_table) for k, cf in zip(cams, f.camera_frames, strict=True)]
            for f in frames]


def _rig_rows(frames: Sequence[Frame], constants: RigConstants, options: GroundTruthOptions, cams, prev, curr, c2v,
              per_sample, sequential: bool) -> list:
    """`rig_ground_truth` of the frames' cameras (one list of `CameraGroundTruth` per frame); a
    sequence's images and labels at t-1 taken from, and its images and labels at t kept for, the
    next sample (`_LAST_IMAGES`)."""
    n = len(frames)
    known = labels = None
    if sequential:
        kept = [_LAST_IMAGES.previous(k.name, k.lut, cf.faces_prev)
                for k, cf in zip(cams, frames[0].camera_frames, strict=True)]
        known = [None if e is None else e.images for e in kept]
        labels = [None if e is None else e.labels_for(
            _LabelInputs(k, per_sample[0], per_sample[2], frames[0].carla_tags, options))
            for k, e in zip(cams, kept, strict=True)]
    rows = gt.rig_ground_truth(
        [k.lut for k in cams], [k.camera for k in cams], c2v, _Faces(**prev), _Faces(**curr), *per_sample,
        rays=[k.rays for k in cams], carla_version=frames[0].carla_tags, batch=options.batch, stacked=False,
        images_prev=known, labels_prev=labels, **options.ground_truth_keywords())
    if n == 1:
        rows = [rows]  # one sample: the list of its cameras
    if sequential:
        for k, cf, truth in zip(cams, frames[0].camera_frames, rows[0], strict=True):
            _LAST_IMAGES.keep(k.name, k.lut, cf.faces, truth.images, (truth.instances, truth.semantic),
                              _LabelInputs(k, per_sample[1], per_sample[3], frames[0].carla_tags, options))
    return rows


class _LabelInputs(NamedTuple):
    """What a camera's labels at one instant depend on besides its images: its constants (camera,
    mount, rays: the same object), the boxes and the ego's vehicle -> world pose at that instant
    (host arrays), the tag table and the options."""

    constants: Any
    boxes: Any
    vehicle_to_world: Any
    carla_tags: str
    options: GroundTruthOptions

    def same(self, other: _LabelInputs) -> bool:
        """Whether ``other`` holds the same values, bit for bit (the same constants object)."""
        if self.constants is not other.constants or (self.carla_tags, self.options) != (other.carla_tags, other.options):
            return False
        mine, theirs = (jax.tree_util.tree_flatten((x.boxes, x.vehicle_to_world)) for x in (self, other))
        return mine[1] == theirs[1] and all(_same_bytes(np.asarray(a), np.asarray(b))
                                            for a, b in zip(mine[0], theirs[0], strict=True))


class _Kept(NamedTuple):
    source: Any  # a fisheye's LUT, the view's rays: the entry is valid for this object only
    arrays: tuple  # the read-only arrays (cube faces, or the view's images) the images came from
    images: Any
    labels: tuple
    inputs: _LabelInputs

    def labels_for(self, inputs_prev: _LabelInputs) -> tuple | None:
        """The kept labels when ``inputs_prev`` equals what they were computed from, else None."""
        return self.labels if self.inputs.same(inputs_prev) else None


class _LastImages:
    """Each camera's last images at t (a fisheye's `FisheyeImages`, or a directly captured view's),
    with the arrays they were computed from (cube faces, or the view's `ViewImages`), and its
    labels at t with what they were computed from, so that the next sample of a sequence, whose
    inputs at t-1 are these arrays (a byte-exact comparison, never a guess), reuses them as its
    images at t-1 (the same program on the same arrays: the same bits as computing them again),
    and its labels at t-1 too when its `_LabelInputs` at t-1 are these. Only read-only arrays are
    kept (a reader's kept decodes, the embedded scene's renders, JAX arrays): a writable array
    could change before the next sample. One entry per camera (its name; `_BEV` for the top
    view) and sequence (`jaxfish._sequences`: the thread that builds it), valid for one ``source``
    object (a fisheye's LUT, the view's rays); thread-safe."""

    def __init__(self) -> None:
        self._kept = KeptByOwner()

    def keep(self, name: Hashable, source, arrays, images, labels: tuple, inputs: _LabelInputs) -> None:
        kept = tuple(np.asarray(getattr(arrays, f)) for f in _FACE_FIELDS)
        if any(a.flags.writeable for a in kept):
            self._kept.pop(name)
        else:
            self._kept.put(name, _Kept(source, kept, images, labels, inputs))

    def previous(self, name: Hashable, source, arrays_prev) -> _Kept | None:
        """The kept entry of ``name`` for ``source`` whose arrays equal ``arrays_prev`` (the same
        objects, else the same bytes), or None."""
        entries = [e for e in self._kept.values(name) if e.source is source]
        if not entries:
            return None
        now = tuple(np.asarray(getattr(arrays_prev, f)) for f in _FACE_FIELDS)
        return next((e for e in entries if all(_same_bytes(a, b) for a, b in zip(e.arrays, now, strict=True))), None)

    def clear(self) -> None:
        self._kept.clear()


_FACE_FIELDS = ("rgb", "depth_m", "semantic")


def _same_bytes(a: np.ndarray, b: np.ndarray) -> bool:
    if a is b:
        return True
    if a.shape != b.shape or a.dtype != b.dtype:
        return False
    a, b = a.reshape(-1).view(np.uint8), b.reshape(-1).view(np.uint8)
    step = 1 << 22  # a bounded temporary
    return all(np.array_equal(a[i:i + step], b[i:i + step]) for i in range(0, a.size, step))


_LAST_IMAGES = _LastImages()
_BEV = ("top view",)  # the BEV's entry: no camera name (a string) equals it


def forget_last_images() -> None:
    """Drop the images and labels (fisheyes and the BEV view) `sample_truth` keeps for the next
    sample of a sequence."""
    _LAST_IMAGES.clear()


class _Faces(eqx.Module):
    rgb: np.ndarray
    depth_m: np.ndarray
    semantic: np.ndarray


def bev_truth(frame: Frame, constants: RigConstants, options: GroundTruthOptions) -> BevTruth:
    """The BEV top view's ground truth of a frame (`jaxfish.groundtruth.view_ground_truth` with the
    rig's BEV camera and mount), its height map (the frame's, or derived from its depth), occupancy
    and renderings. Raises ``ValueError`` when the frame or the rig has no BEV."""
    if frame.bev is None or constants.bev is None:
        raise ValueError(f"frame {frame.index}: no BEV top view in the {'frame' if frame.bev is None else 'rig constants'}")
    k, view = constants.bev, frame.bev
    m = frame.motion
    # A sequence's next frame reuses the view's images and labels at t-1 (see `_LastImages`).
    kept = _LAST_IMAGES.previous(_BEV, k.rays, view.images_prev)
    known = None if kept is None else kept.images
    labels = None if kept is None else kept.labels_for(
        _LabelInputs(k, m.boxes_prev, m.vehicle_to_world_prev, frame.carla_tags, options))
    truth = gt.view_ground_truth(k.camera, k.camera_to_vehicle, view.images_prev, view.images, m.boxes_prev, m.boxes,
                                 m.vehicle_to_world_prev, m.vehicle_to_world, carla_version=frame.carla_tags,
                                 rays=k.rays, images_prev=known, labels_prev=labels, **options.ground_truth_keywords())
    _LAST_IMAGES.keep(_BEV, k.rays, view.images, truth.images, (truth.instances, truth.semantic),
                      _LabelInputs(k, m.boxes, m.vehicle_to_world, frame.carla_tags, options))
    if view.height_m is not None:
        height = np.asarray(view.height_m, np.float32)
    else:
        height = np.asarray(jbev.height_map(k.camera, k.camera_to_vehicle, jnp.asarray(view.images.depth_m, jnp.float32)))
    thr = float(options.occupancy_min_height_m)
    jit = _jitted()
    occupancy = np.asarray(jit["occupancy"](height, min_height_m=thr))
    return BevTruth(view=_camera_truth("BEV", k.camera, k.rays, truth, None, options.backward_flow), camera=k.camera,
                    camera_to_vehicle=k.camera_to_vehicle, height_m=height, occupancy=occupancy,
                    occupancy_min_height_m=thr, height_rgb=np.asarray(jit["height_rgb"](height)),
                    pixel_to_vehicle_xy=np.asarray(jbev.bev_pixel_to_vehicle(k.camera, k.camera_to_vehicle), np.float64),
                    box_class_id=np.asarray(m.boxes.class_id))


def _check(frames: Sequence[Frame], constants: RigConstants) -> None:
    if not frames:
        raise ValueError("sample_truths: no frame")
    for f in frames:
        if f.cameras != constants.names:
            raise ValueError(f"frame {f.index}: cameras {f.cameras} differ from the rig constants' {constants.names}")
        if f.carla_tags != frames[0].carla_tags:
            raise ValueError(f"frame {f.index}: tag table {f.carla_tags} differs from frame {frames[0].index}'s "
                             f"{frames[0].carla_tags} (one batch, one tag table)")


def sample_truths(frames: Sequence[Frame], constants: RigConstants,
                  options: GroundTruthOptions | None = None) -> list[SampleTruth]:
    """`sample_truth` of several frames, their boxes padded to one size. With ``batch="vmap"``
    their fisheye cameras are computed in one batched call (`jaxfish.groundtruth.rig_ground_truth`
    over frames and cameras) and values agree with `sample_truth` to float32 rounding; with
    ``batch="loop"`` (CPU) the frames are computed one after the other, in order, so that
    consecutive frames share their common instant (see `sample_truth`), and each result equals
    `sample_truth` of its frame alone. When this process builds fewer sequences at once
    (`sequence_slots`) than it may use cores, the face events are mapped to the fisheyes in a
    thread of its own while the cameras' compiled programs run; the results are the same."""
    options = options or GroundTruthOptions()
    frames = list(frames)
    _check(frames, constants)
    pad = box_slots(max(len(f.motion.actors) for f in frames))
    motions = [f.motion.padded(pad) for f in frames]
    rows = _fisheye_truths(frames, constants, options, motions) if constants.cameras else [[] for _ in frames]
    out = []
    for f, m, row in zip(frames, motions, rows, strict=True):
        bev = bev_truth(f, constants, options) if options.bev and f.bev is not None and constants.bev is not None else None
        first = row[0].truth if row else (None if bev is None else bev.view.truth)
        if first is None:
            raise ValueError(f"frame {f.index}: no camera to compute (no fisheye camera and no BEV)")
        boxes = m.boxes if row else f.motion.boxes
        world = np.asarray(boxes.corners(), np.float64)
        vehicle = np.asarray(gt.boxes_in_frame(boxes, m.vehicle_to_world.inverse()), np.float64)
        out.append(SampleTruth(index=f.index, cameras=tuple(row), bev=bev, motion=m if row else f.motion,
                               displacement_m=np.asarray(first.displacement_m), corners_world=world,
                               corners_vehicle=vehicle, sensors=f.sensors, vehicle_sensors=_vehicle_sensors(f)))
    return out


def _vehicle_sensors(frame: Frame) -> SensorTruth | None:
    if frame.sensors is None:
        return None
    try:
        return sensor_truth(frame.sensors)
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"frame {frame.index}: sensor records: {e}") from e


def sample_truth(frame: Frame, constants: RigConstants, options: GroundTruthOptions | None = None) -> SampleTruth:
    """Every ground truth of one frame's sample: each fisheye camera (`CameraTruth`: images,
    range and z-depth, semantics, instances, motion, flow, events, 2D boxes and their renderings),
    the BEV top view when the frame has one and ``options.bev`` (`BevTruth`), the 3D box corners
    and displacements. ``constants``: the rig's `RigConstants` (cameras in the frame's order).

    Frames of a sequence computed in order share work: with ``batch="loop"`` (the CPU default)
    each camera's fisheye images and labels at t are kept (one sample's worth per process,
    `forget_last_images` drops them), and a next frame whose cube faces at t-1 are those faces,
    byte for byte and read-only (`jaxfish.dataset.CaptureSource` and `jaxfish.dataset.EmbeddedSource`
    give such frames), takes them as its images at t-1 instead of resampling them; when its boxes
    and ego pose at t-1 are also those at t of the kept frame (bit for bit) and the options the
    same, it takes the kept instances and semantics as its labels at t-1 as well. The BEV top
    view's images and labels are kept and reused the same way. The results are the same bits
    either way."""
    return sample_truths([frame], constants, options)[0]
