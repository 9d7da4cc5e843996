"""The SynWoodScape layout writer: the one sink of `jaxfish.pipeline.SampleTruth`\\ s.

`LayoutSink.jobs` lists the writes of one sample (each a function returning the paths it wrote),
so that the builder runs them inline or in a pool of threads; every file is written atomically and
deterministically (`docs/dataset.md` lists the layout)."""

from __future__ import annotations

import io
import os
import pickle
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import equinox as eqx
import numpy as np

from .._constants import FAR_DEPTH_M
from .._errors import ImageError
from .._sequences import KeptByOwner, acting_for, sequence_owner
from ..groundtruth import SYNWOODSCAPE_CLASSES, SYNWOODSCAPE_PALETTE
from ..io import (
    atomic_write_bytes,
    atomic_write_text,
    write_boxes_2d_csv,
    write_boxes_3d_ext_json,
    write_boxes_3d_pickle,
    write_color_png,
    write_depth_exr,
    write_depth_npy,
    write_displacements,
    write_events_npy,
    write_events_tonic,
    write_flo,
    write_image,
    write_kitti_flow,
    write_label_png,
    write_png_with_metadata,
)
from ..io._images import png_image_bytes
from ..pipeline import (
    RADAR_VEHICLE_DTYPE,
    SEMANTIC_LIDAR_VEHICLE_DTYPE,
    BevTruth,
    CameraTruth,
    SampleTruth,
    SensorRecords,
    SensorTruth,
)
from ._layout import BEV_CAMERA

RANGE_DEPTH_DEFINITION = {"quantity": "Euclidean range along the pixel's ray (not planar z-depth)", "unit": "m",
                          "sky_m": FAR_DEPTH_M, "no_ray": 0.0, "instant": "t"}
"""What the dataset's depth EXRs hold (their `jaxfish.io.DEPTH_ATTRIBUTE` metadata)."""

def synwoodscape_palette_dict() -> dict[str, Any]:
    """The SynWoodScape palette as metadata: ``{"classes": names, "colors": [[r, g, b], ...]}``
    (also the content of a ``seg_annotation_info.json``)."""
    return {"classes": list(SYNWOODSCAPE_CLASSES), "colors": SYNWOODSCAPE_PALETTE.astype(int).tolist()}


def boxes_2d_rows(xyxy: np.ndarray, present: np.ndarray, class_id: np.ndarray) -> list[tuple[str, int, int, int, int, int]]:
    """WoodScape 2D box rows ``(class_name, class_id, x1, y1, x2, y2)`` of the present boxes."""
    rows = []
    for b, c, p in zip(np.asarray(xyxy), np.asarray(class_id), np.asarray(present), strict=True):
        if p and 0 <= int(c) < len(SYNWOODSCAPE_CLASSES):
            rows.append((SYNWOODSCAPE_CLASSES[int(c)], int(c), *(int(v) for v in b)))
    return rows  # type: ignore[return-value]


def write_camera_files(root: Path, sample: str, cam: CameraTruth, *, motion_threshold_m: float,
                       png_level: int) -> list[Path]:
    """One camera's files with stem ``{sample}_{camera}`` (layout in ``docs/dataset.md``):
    RGB at t and t-1, range (``.npy`` and EXR), z-depth, depth colour map, semantic / instance /
    motion label and colour PNGs, forward flow (``.flo``, KITTI PNG, colour), DVS events (raw,
    tonic, colour; not for the BEV), visible and full 2D boxes."""
    t = cam.truth
    stem = f"{sample}_{cam.name}"
    out: list[Path] = []
    add = out.append
    h, w = np.asarray(t.images.valid).shape
    # t-1 first: it may be the kept image at t of the previous sample, which t then replaces.
    prev = _LAST_RGB.write(root / "previous_images" / f"{stem}_prev.png", cam.name, t.images_prev.rgb, png_level)
    add(_LAST_RGB.write(root / "rgb_images" / f"{stem}.png", cam.name, t.images.rgb, png_level, keep=True))
    add(prev)
    rng = np.asarray(t.images.range_m, np.float32)
    add(write_depth_npy(root / "depth_maps" / "raw_data" / f"{stem}.npy", rng))
    add(write_depth_exr(root / "depth_maps" / "exr" / f"{stem}.exr", rng, RANGE_DEPTH_DEFINITION))
    add(write_depth_npy(root / "depth_maps" / "z_depth" / f"{stem}.npy", np.asarray(cam.z_depth_m)))
    add(write_image(root / "depth_maps" / "colormap" / f"{stem}.png", cam.depth_rgb, png_level=png_level))
    pal = synwoodscape_palette_dict()
    add(write_label_png(root / "semantic_annotations" / "gtLabels" / f"{stem}.png", np.asarray(t.semantic),
                        png_level=png_level))
    add(write_color_png(root / "semantic_annotations" / "rgbLabels" / f"{stem}.png", np.asarray(cam.semantic_rgb), pal,
                        png_level=png_level))
    add(write_label_png(root / "instance_annotations" / "gtLabels" / f"{stem}.png", np.asarray(t.instances.actor_id),
                        png_level=png_level))
    add(write_color_png(root / "instance_annotations" / "rgbLabels" / f"{stem}.png", np.asarray(cam.instance_rgb),
                        {"colors": "jaxfish.groundtruth.instance_colors(actor_id)", "background": [0, 0, 0]},
                        png_level=png_level))
    mot = np.asarray(t.motion).astype(np.uint8) * 255
    add(write_label_png(root / "motion_annotations" / "gtLabels" / f"{stem}.png", mot, png_level=png_level))
    add(write_color_png(root / "motion_annotations" / "rgbLabels" / f"{stem}.png", np.repeat(mot[..., None], 3, -1),
                        {"classes": ["static", "moving"], "colors": [[0, 0, 0], [255, 255, 255]],
                         "threshold_m": motion_threshold_m}, png_level=png_level))
    fl, fv = np.asarray(t.flow.flow), np.asarray(t.flow.valid)
    add(write_flo(root / "optical_flow" / "raw_data" / f"{stem}.flo", np.where(fv[..., None], fl, 0.0)))
    add(write_kitti_flow(root / "optical_flow" / "kitti" / f"{stem}.png", fl, fv, png_level=png_level))
    add(write_image(root / "optical_flow" / "color_coded" / f"{stem}.png", np.asarray(cam.flow_rgb), png_level=png_level))
    out += write_flow_masks(root / "optical_flow", stem, t.flow, png_level=png_level)
    if cam.events is not None:
        ev = cam.events
        add(write_events_npy(root / "dvs_signals" / "raw_data" / f"{stem}.npy", ev))
        add(write_events_tonic(root / "dvs_signals" / "tonic" / f"{stem}.npz", ev, width=w, height=h))
        add(write_image(root / "dvs_signals" / "color_coded" / f"{stem}.png", cam.events_rgb, png_level=png_level))
    return out


class _LastRgb:
    """Each camera's last RGB image at t with its PNG bytes, so that the next sample of a sequence,
    whose images at t-1 are those images (the same array object: `jaxfish.pipeline.sample_truth`
    hands a sequence's images at t on), writes them as its ``previous_images`` file without
    encoding them again: the bytes `write_image` would write. One entry per camera name and
    sequence (`jaxfish._sequences`: the thread building it, which the writing threads act for);
    thread-safe."""

    def __init__(self) -> None:
        self._kept = KeptByOwner()

    def write(self, path: Path, camera: str, rgb, png_level: int, *, keep: bool = False) -> Path:
        """Write ``rgb`` as the PNG ``path`` (atomic), from the kept bytes when ``rgb`` is a kept
        image of the camera at this level; ``keep``: keep ``rgb`` and its bytes for the next sample."""
        data = next((k[2] for k in self._kept.values(camera) if k[0] is rgb and k[1] == png_level), None)
        if data is None:
            data = png_image_bytes(path, np.asarray(rgb), png_level=png_level)
        if keep:
            self._kept.put(camera, (rgb, png_level, data))
        return atomic_write_bytes(path, data)

    def clear(self) -> None:
        self._kept.clear()


_LAST_RGB = _LastRgb()


def forget_last_rgb() -> None:
    """Drop the RGB images and PNG bytes the sink keeps for the next sample of a sequence."""
    _LAST_RGB.clear()


def write_flow_masks(folder: Path, stem: str, field, *, png_level: int) -> list[Path]:
    """A flow field's masks (`jaxfish.groundtruth.FlowField`), uint8 PNGs 0 / 255 on the source
    grid: ``{folder}/valid_mask/{stem}.png`` (`FlowField.valid`: seen at both instants and inside
    the target image) and ``{folder}/occlusion_mask/{stem}.png`` (`FlowField.occluded`: inside the
    target image but hidden there)."""
    valid = np.asarray(field.valid, bool).astype(np.uint8) * 255
    occluded = np.asarray(field.occluded, bool).astype(np.uint8) * 255
    return [write_label_png(folder / "valid_mask" / f"{stem}.png", valid, png_level=png_level),
            write_label_png(folder / "occlusion_mask" / f"{stem}.png", occluded, png_level=png_level)]


def write_box_files(root: Path, sample: str, cam: CameraTruth, class_id: np.ndarray) -> list[Path]:
    """A camera's 2D box files: ``box_2d_annotations`` (visible) and ``box_2d_full_annotations``."""
    t, stem = cam.truth, f"{sample}_{cam.name}"
    return [write_boxes_2d_csv(root / "box_2d_annotations" / f"{stem}.txt",
                               boxes_2d_rows(np.asarray(t.boxes_2d.xyxy), np.asarray(t.boxes_2d.present), class_id)),
            write_boxes_2d_csv(root / "box_2d_full_annotations" / f"{stem}.txt",
                               boxes_2d_rows(np.asarray(t.boxes_2d_full.xyxy), np.asarray(t.boxes_2d_full.present),
                                             class_id))]


def write_backward_flow(root: Path, sample: str, cam: CameraTruth, *, png_level: int) -> list[Path]:
    """``optical_flow_backward/{raw_data .flo, color_coded .png, valid_mask .png, occlusion_mask .png}``
    (t -> t-1 on the t grid)."""
    back = cam.truth.flow_backward
    fl, fv = np.asarray(back.flow), np.asarray(back.valid)
    stem = f"{sample}_{cam.name}"
    return [write_flo(root / "optical_flow_backward" / "raw_data" / f"{stem}.flo", np.where(fv[..., None], fl, 0.0)),
            write_image(root / "optical_flow_backward" / "color_coded" / f"{stem}.png", np.asarray(cam.flow_backward_rgb),
                        png_level=png_level)] + write_flow_masks(root / "optical_flow_backward", stem, back, png_level=png_level)


def write_bev_files(root: Path, sample: str, bev: BevTruth, *, png_level: int) -> list[Path]:
    """The BEV's extra files: ``bev_height/raw_data`` (float32 metres above the ground),
    ``bev_height/colormap`` and ``bev_occupancy`` (0 free / 255 occupied), each PNG with the BEV
    scale and axes (`bev_metadata`) in its metadata."""
    from ..bev import HEIGHT_COLOR_RANGE_M, bev_metadata

    stem = f"{sample}_{BEV_CAMERA}"
    cam, c2v, a = bev.camera, bev.camera_to_vehicle, bev.pixel_to_vehicle_xy
    height, occ = np.asarray(bev.height_m, np.float32), np.asarray(bev.occupancy, bool)
    if height.shape != (cam.height, cam.width) or occ.shape != height.shape:
        raise ImageError(f"{root}: sample {sample!r}: height {height.shape} / occupancy {occ.shape} do not match "
                         f"the BEV image {(cam.height, cam.width)}")
    lo, hi = HEIGHT_COLOR_RANGE_M
    thr = float(bev.occupancy_min_height_m)
    return [write_depth_npy(root / "bev_height" / "raw_data" / f"{stem}.npy", height),
            write_png_with_metadata(root / "bev_height" / "colormap" / f"{stem}.png", bev.height_rgb,
                                    bev_metadata(cam, c2v, pixel_to_vehicle_xy=a, content="height above the ground (m), viridis",
                                                 color_range_m=[lo, hi]), png_level=png_level),
            write_png_with_metadata(root / "bev_occupancy" / f"{stem}.png", occ.astype(np.uint8) * 255,
                                    bev_metadata(cam, c2v, pixel_to_vehicle_xy=a, content="occupancy: 255 = top surface higher than "
                                                 f"{thr:g} m above the ground, 0 = free", occupancy_min_height_m=thr),
                                    png_level=png_level)]


def write_sample_files(root: Path, sample: str, truth: SampleTruth, *, motion_threshold_m: float) -> list[Path]:
    """The per-sample files: ``box_3d_annotations/{sample}.pkl`` (SynWoodScape's format:
    ``{actor_id: (8, 3) CARLA-world corners}``, every actor), ``box_3d_annotations_ext/{sample}.json``
    (class and ISO-vehicle corners) and ``distances_traveled/{sample}.txt`` (displacements)."""
    boxes = truth.motion.boxes
    cls = np.asarray(boxes.class_id)
    act = np.asarray(boxes.active)
    aid = np.asarray(boxes.actor_id)
    world, veh = truth.corners_world, truth.corners_vehicle
    names = SYNWOODSCAPE_CLASSES
    out = [write_boxes_3d_pickle(root / "box_3d_annotations" / f"{sample}.pkl",
                                 {int(a): world[i] for i, a in enumerate(aid) if act[i]})]
    ext = {int(a): {"corners_world": world[i], "corners_vehicle": veh[i], "class_id": int(cls[i]),
                    "class_name": names[int(cls[i])] if 0 <= int(cls[i]) < len(names) else "unknown"}
           for i, a in enumerate(aid) if act[i]}
    out.append(write_boxes_3d_ext_json(root / "box_3d_annotations_ext" / f"{sample}.json", ext))
    disp = np.asarray(truth.displacement_m)
    out.append(write_displacements(root / "distances_traveled" / f"{sample}.txt", aid[act], cls[act], disp[act],
                                   threshold_m=motion_threshold_m))
    return out


def _vehicle_lines(ego: Mapping[str, Any], instant: str) -> str:
    def vec(name, v):
        return f"{name} " + " ".join(f"{float(x):.9g}" for x in v)

    if instant == "t":
        tr = ego["transform"]
        lines = [f"timestamp_s {float(ego['timestamp_s']):.9g}", vec("location_m", tr["location"]),
                 vec("rotation_deg", tr["rotation"]), vec("velocity_mps", ego["velocity"]),
                 vec("acceleration_mps2", ego["acceleration"]), vec("angular_velocity_degps", ego["angular_velocity"])]
    else:
        tr = ego["transform_prev"]
        lines = [f"timestamp_s {float(ego['timestamp_prev_s']):.9g}", vec("location_m", tr["location"]),
                 vec("rotation_deg", tr["rotation"])]
    header = ("# ego vehicle (CARLA world: x forward, y right, z up, metres; rotation pitch yaw roll, degrees; "
              "velocity / acceleration in the world frame, angular velocity deg/s)")
    return header + "\n" + "\n".join(lines) + "\n"


def write_sensor_files(root: Path, sample: str, sensors: SensorRecords, where: str) -> list[Path]:
    """``vehicle_data/{rgb_images, previous_images}/{sample}.txt`` (the ego at t and t-1) and
    ``lidar_data/{sample}.pkl`` (lidar, semantic lidar, radar in CARLA's raw frames); ``where``
    names the source of the ego record in errors."""
    from ..io import CaptureError

    try:
        t_text, p_text = _vehicle_lines(sensors.ego, "t"), _vehicle_lines(sensors.ego, "t-1")
    except (KeyError, TypeError, ValueError) as e:
        raise CaptureError(f"{where}: malformed ({e!r})") from e
    paths = [atomic_write_text(root / "vehicle_data" / "rgb_images" / f"{sample}.txt", t_text),
             atomic_write_text(root / "vehicle_data" / "previous_images" / f"{sample}.txt", p_text)]
    lidar = {"points": np.ascontiguousarray(sensors.lidar, np.float32),
             "semantic_lidar": np.ascontiguousarray(sensors.semantic_lidar),
             "radar": np.ascontiguousarray(sensors.radar),
             "frame": "lidar sensor's local Unreal frame (x forward, y right, z up), metres; radar: m/s, rad, rad, m"}
    paths.append(atomic_write_bytes(root / "lidar_data" / f"{sample}.pkl", pickle.dumps(lidar, protocol=4)))
    return paths


def _npy_bytes(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(arr), allow_pickle=False)
    return buf.getvalue()


def _floats(v) -> list[float]:
    return [float(x) + 0.0 for x in np.asarray(v, np.float64).reshape(-1)]  # + 0.0: no "-0.0" in the JSON


def sensor_data_doc(sample: str, frame: int, sensors: SensorTruth) -> dict[str, Any]:
    """The content of ``sensor_data/{sample}.json``: timestamps, the ego state (``vehicle_to_world``
    4 x 4 ISO vehicle at t -> CARLA world; velocity, acceleration, angular velocity in the ISO
    vehicle frame at t), the IMU (ISO vehicle frame) and the GNSS fix (null when absent)."""
    ego, imu, gnss = sensors.ego, sensors.imu, sensors.gnss
    return {
        "sample": sample, "frame": int(frame), "timestamp_s": float(ego.timestamp_s),
        "previous_timestamp_s": float(ego.previous_timestamp_s),
        "ego": {"vehicle_to_world": [_floats(row) for row in np.asarray(ego.vehicle_to_world)],
                "velocity_mps": _floats(ego.velocity_mps), "acceleration_mps2": _floats(ego.acceleration_mps2),
                "angular_velocity_radps": _floats(ego.angular_velocity_radps)},
        "imu": None if imu is None else {"accelerometer_mps2": _floats(imu.accelerometer_mps2),
                                         "gyroscope_radps": _floats(imu.gyroscope_radps),
                                         "compass_rad": float(imu.compass_rad)},
        "gnss": None if gnss is None else {"latitude_deg": float(gnss.latitude_deg),
                                           "longitude_deg": float(gnss.longitude_deg),
                                           "altitude_m": float(gnss.altitude_m)},
    }


def write_vehicle_sensor_files(root: Path, sample: str, frame: int, sensors: SensorTruth) -> list[Path]:
    """The sensors in the ISO 8855 vehicle frame at t (`jaxfish.pipeline.SensorTruth`):
    ``sensor_data/{sample}.json`` (`sensor_data_doc`), ``lidar_vehicle/{sample}.npy`` (float32
    ``(N, 4)``), ``semantic_lidar_vehicle/{sample}.npy`` and ``radar_data/{sample}.npy``
    (structured ``(N,)``)."""
    from ..io._json import to_json_text
    from ._options import DatasetError

    path = root / "sensor_data" / f"{sample}.json"
    text = to_json_text(path, sensor_data_doc(sample, frame, sensors), indent=1, error=DatasetError)
    return [atomic_write_text(path, text),
            atomic_write_bytes(root / "lidar_vehicle" / f"{sample}.npy",
                               _npy_bytes(np.asarray(sensors.lidar_vehicle, np.float32).reshape(-1, 4))),
            atomic_write_bytes(root / "semantic_lidar_vehicle" / f"{sample}.npy",
                               _npy_bytes(np.asarray(sensors.semantic_lidar_vehicle, SEMANTIC_LIDAR_VEHICLE_DTYPE))),
            atomic_write_bytes(root / "radar_data" / f"{sample}.npy",
                               _npy_bytes(np.asarray(sensors.radar_vehicle, RADAR_VEHICLE_DTYPE)))]


Job = Callable[[], Sequence[Path]]


def _written_camera(cam: CameraTruth) -> CameraTruth:
    """``cam`` with the arrays `write_camera_files` and `write_backward_flow` make no file of
    replaced by None (`written_part`)."""
    def unwritten(c: CameraTruth) -> list:
        g = c.truth
        nodes = [g.images_prev.range_m, g.images_prev.tag, g.images_prev.valid, g.semantic_prev, g.instances_prev,
                 g.flow.target_uv, g.flow.target_range_m]
        if g.flow_backward is not None:
            nodes += [g.flow_backward.target_uv, g.flow_backward.target_range_m]
        return nodes

    return eqx.tree_at(unwritten, cam, replace=[None] * len(unwritten(cam)))


def written_part(truth: SampleTruth) -> SampleTruth:
    """``truth`` as much of it as `LayoutSink` writes: each camera's images at t-1 but the RGB
    image, its labels at t-1 (semantics and instances) and its flows' target positions and ranges
    replaced by None, so that a build holds none of them while the sample's files are written (a
    sequence's next sample takes its images and labels at t-1 from the pipeline's own kept
    frame). For the sink only: what it returns is not a complete `SampleTruth`."""
    cams = tuple(_written_camera(c) for c in truth.cameras)
    bev = truth.bev if truth.bev is None else eqx.tree_at(lambda b: b.view, truth.bev, _written_camera(truth.bev.view))
    return eqx.tree_at(lambda t: (t.cameras, t.bev), truth, (cams, bev), is_leaf=lambda x: x is None)


class LayoutSink:
    """Writes `SampleTruth`\\ s in SynWoodScape's layout under ``root``: ``png_level`` is the zlib
    level of every PNG, ``motion_threshold_m`` is recorded in the motion PNGs and the displacement
    file, ``backward_flow`` also writes ``optical_flow_backward``."""

    def __init__(self, root: str | os.PathLike, *, png_level: int = 1, motion_threshold_m: float = 0.5,
                 backward_flow: bool = False):
        self.root = Path(root)
        self.png_level = int(png_level)
        self.motion_threshold_m = float(motion_threshold_m)
        self.backward_flow = bool(backward_flow)

    def camera_jobs(self, sample: str, cam: CameraTruth, class_id: np.ndarray) -> list[Job]:
        """The writes of one camera's files (and its backward flow)."""
        root, png, thr = self.root, self.png_level, self.motion_threshold_m
        owner = sequence_owner()  # the sequence these files continue, whichever thread writes them

        def files() -> list[Path]:
            with acting_for(owner):
                return write_camera_files(root, sample, cam, motion_threshold_m=thr, png_level=png) + \
                    write_box_files(root, sample, cam, class_id)

        jobs: list[Job] = [files]
        if self.backward_flow:
            jobs.append(lambda: write_backward_flow(root, sample, cam, png_level=png))
        return jobs

    def jobs(self, sample: str, truth: SampleTruth, *, ego_where: str = "<ego record>") -> list[Job]:
        """Every write of a sample, in order: each fisheye camera, the BEV (its camera files and
        extras), the per-sample files, the sensors in the vehicle frame (`write_vehicle_sensor_files`),
        and last the raw sensor files (`write_sensor_files`). Each job returns the paths it wrote."""
        root = self.root
        jobs: list[Job] = []
        for cam in truth.cameras:
            jobs += self.camera_jobs(sample, cam, np.asarray(truth.motion.boxes.class_id))
        if truth.bev is not None:
            bev = truth.bev
            jobs += self.camera_jobs(sample, bev.view, bev.box_class_id)
            jobs.append(lambda: write_bev_files(root, sample, bev, png_level=self.png_level))
        jobs.append(lambda: write_sample_files(root, sample, truth, motion_threshold_m=self.motion_threshold_m))
        if truth.vehicle_sensors is not None:
            jobs.append(lambda: write_vehicle_sensor_files(root, sample, truth.index, truth.vehicle_sensors))
        jobs.append(lambda: write_sensor_files(root, sample, truth.sensors, ego_where))
        return jobs

    def write(self, sample: str, truth: SampleTruth) -> list[Path]:
        """Write every file of a sample inline; returns the paths."""
        return [p for job in self.jobs(sample, truth) for p in job()]
