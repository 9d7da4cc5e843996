"""``dataset.json``: every convention SynWoodScape's release left undocumented, stated in the dataset
itself, plus the layout, the capture's provenance and the sample list; and the other dataset-level
files (``calibration_data``, ``seg_annotation_info.json``).

Deterministic: no timestamps, hosts or paths; the same capture and options give the same bytes.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from .._constants import FAR_DEPTH_M
from ..io._events import TONIC_EVENT_DTYPE
from ._layout import BEV_CAMERA, DATASET_FILES, LAYOUT, LAYOUT_VERSION, sample_id
from ._options import DONE_DIR, BuildOptions, DatasetError

DATASET_FORMAT = "jaxfish-synwoodscape"
"""Format name stored in ``dataset.json``."""


def _complete_samples(out: Path) -> list[str]:
    d = out / DONE_DIR
    return sorted(p.stem for p in d.glob("*.json")) if d.is_dir() else []


def sequences_doc(samples, dt_s: float) -> dict[str, Any]:
    """The content of ``sequence.json`` for the complete ``samples`` (ids ``{frame:05d}``):
    consecutive capture frames form one sequence, a gap in the frame numbers (a sample missing or
    failed) starts the next; ``{"sequences": [{"name": "seq_00000", "samples": [...], "dt_s"}],
    "neighbours": {sample: {"previous": id or None, "next": id or None}}}`` (previous / next within
    its sequence). Deterministic: sorted by frame."""
    frames = sorted({int(s) for s in samples})
    runs: list[list[int]] = []
    for f in frames:
        if runs and f == runs[-1][-1] + 1:
            runs[-1].append(f)
        else:
            runs.append([f])
    ids = [[sample_id(f) for f in run] for run in runs]
    neighbours = {}
    for run in ids:
        for i, sid in enumerate(run):
            neighbours[sid] = {"previous": run[i - 1] if i > 0 else None, "next": run[i + 1] if i + 1 < len(run) else None}
    return {"sequences": [{"name": f"seq_{k:05d}", "samples": run, "dt_s": None if dt_s is None else float(dt_s)} for k, run in enumerate(ids)],
            "neighbours": neighbours}


def dataset_manifest(source, out_dir: str | os.PathLike, options: BuildOptions | None = None) -> dict[str, Any]:
    """The content of ``dataset.json`` for a source of frames (`jaxfish.dataset.CaptureSource`,
    `EmbeddedSource`, or a capture directory) built into ``out_dir`` with ``options``:
    conventions (flow direction, depth definition, event time units, BEV scale and axes,
    coordinate frames, pixel convention), the class table and palette, the corrected SynWoodScape
    extrinsics, the layout (`LAYOUT`), the capture's provenance (``capture``) and fingerprint
    (``source``: `FrameSource.fingerprint`; each sample's marker adds its frame's), the build
    options, the jaxfish version and the complete samples (those with a marker)."""
    import numpy as np

    from .. import SYNWOODSCAPE_CORRECTED_TRANSLATIONS_CARLA, __version__
    from ..groundtruth import MOTION_THRESHOLD_M, OCCLUSION_REL_TOL, SYNWOODSCAPE_CLASSES, SYNWOODSCAPE_PALETTE
    from ..pipeline import DEPTH_COLOR_RANGE_M
    from ._sources import as_source

    options = options or BuildOptions()
    source = as_source(source)
    out = Path(out_dir)
    meta = source.describe()
    fisheye = list(source.cameras)
    rig = source.rig()
    sizes = {c: [int(rig[c].camera.width), int(rig[c].camera.height)] for c in fisheye}
    bev = None
    if options.bev and source.has_bev():
        bev = _bev_block(source)
        sizes[BEV_CAMERA] = [bev["width"], bev["height"]]
    cameras = fisheye + ([BEV_CAMERA] if bev else [])
    return {
        "format": DATASET_FORMAT,
        "layout_version": LAYOUT_VERSION,
        "generator": {"name": "jaxfish", "version": __version__},
        "capture": {k: meta.get(k) for k in ("format", "version", "source", "seed", "dt_s", "carla_semantic_tags",
                                              "face_size", "faces", "cameras")},
        "source": source.fingerprint(),
        "options": options.to_dict(),
        "cameras": cameras,
        "fisheye_cameras": fisheye,
        "image_size_wh": sizes,
        "samples": _complete_samples(out),
        "sample_id": "sample {id:05d} = capture frame id; every sample holds t (files) and t-1 (previous_images)",
        "time": {"dt_s": meta.get("dt_s", 0.1), "prev": "t-1 = t - dt_s",
                 "timestamps": "sensor_data/{sample}.json 'timestamp_s' (t) and 'previous_timestamp_s' (t-1), "
                               "also vehicle_data/*/{sample}.txt 'timestamp_s' (simulation time, seconds)",
                 "sequences": "sequence.json: consecutive capture frames form one sequence; a gap in the frame "
                              "numbers (a missing or failed sample) starts the next; 'neighbours' gives each "
                              "sample's previous and next sample in its sequence (null at its ends)"},
        "conventions": {
            "pixels": "(u, v) = (column, row); integer coordinates are pixel centres; (0, 0) is the centre of the "
                      "top-left pixel (WoodScape's projection.py)",
            "frames": {
                "world": "CARLA / Unreal world: x forward, y right, z up, left-handed, metres; rotations "
                         "(pitch, yaw, roll) in degrees",
                "vehicle": "ISO 8855 ego vehicle frame: x forward, y left, z up, right-handed, metres; origin = "
                           "the CARLA ego actor origin (the CARLA actor frame with y flipped)",
                "camera": "OpenCV camera frame: x right, y down, z forward (optical axis)",
                "calibration": "calibration_data/{camera}.json: WoodScape JSON, quaternion (x, y, z, w) scalar-last, "
                               "(quaternion, translation) = pose camera -> vehicle",
            },
            "depth": {"raw_data": "Euclidean range along each pixel's ray, metres, float32 (not planar z-depth)",
                      "exr": "depth_maps/exr: the raw_data range as a one-channel (Z) float32 OpenEXR",
                      "z_depth": "planar depth along the camera's optical axis = range x ray_z, metres, float32",
                      "sky_m": FAR_DEPTH_M, "no_ray": 0.0, "colormap_range_m": list(DEPTH_COLOR_RANGE_M)},
            "optical_flow": {"direction": "forward: from t-1 to t", "grid": "defined on the t-1 pixel grid",
                             "definition": "flow = uv_t - uv_(t-1) in pixels, u right, v down",
                             "valid": "the point stays in the image and is not occluded at t; invalid pixels "
                                      "store 0 in .flo and valid = 0 in KITTI PNGs",
                             "valid_mask": "optical_flow/valid_mask: 255 where the t-1 pixel has a ray and its point "
                                           "lands inside the image at t and is seen there (the flow's validity), "
                                           "0 elsewhere",
                             "occlusion_mask": "optical_flow/occlusion_mask: 255 where the t-1 pixel's point lands "
                                               "inside the image at t but is hidden there (all 4 nearest ranges at "
                                               f"t are shorter than its predicted range by more than "
                                               f"{OCCLUSION_REL_TOL:.0%}), 0 "
                                               "elsewhere; valid_mask and occlusion_mask never overlap, pixels in "
                                               "neither leave the image (or have no ray)",
                             "backward": "optical_flow_backward (t -> t-1 on the t grid) when built with "
                                         "backward_flow", "color_wheel": "Baker et al. 2007 (Middlebury)"},
            "events": {"raw_data": {"dtype": "[('x', '<u2'), ('y', '<u2'), ('t', '<i8'), ('pol', '?')]",
                                    "time_unit": "ns", "time": "absolute simulation time, within [t-1, t]",
                                    "polarity": "True = brighter"},
                       "tonic": {"dtype": str(TONIC_EVENT_DTYPE),
                                 "time_unit": "us", "t": "t_ns // 1000"},
                       "mapping": "a face event goes to every fisheye pixel whose centre ray lands on its face pixel",
                       "color_coded": "blue = net positive, red = net negative polarity, white = none",
                       "cameras": "fisheye cameras only (the BEV has no DVS)"},
            "bev": bev,
            "sensors": {
                "frame": "every vehicle-frame quantity is in the ISO 8855 vehicle frame at t (x forward, y left, "
                         "z up, right-handed; origin = the CARLA ego actor origin)",
                "handedness": "CARLA / Unreal coordinates are left-handed: S = diag(1, -1, 1) maps them to ISO "
                              "coordinates. Points and vectors map as S v; angular velocities (axial vectors, "
                              "Unreal z positive = yaw increasing = turning right) as -S w = (-wx, wy, -wz) "
                              "(ISO z positive = turning left)",
                "vehicle_to_world": "sensor_data ego.vehicle_to_world: 4 x 4, column vectors, ISO vehicle at t -> "
                                    "CARLA world = CARLA ego transform matrix @ diag(1, -1, 1, 1) (determinant -1)",
                "ego": "sensor_data ego: velocity_mps, acceleration_mps2 (without gravity), angular_velocity_radps "
                       "(rad/s): the capture's world quantities rotated into the ISO vehicle frame at t",
                "imu": "sensor_data imu: accelerometer_mps2 (gravity included: +9.81 on z at rest), gyroscope_radps "
                       "in the ISO vehicle frame; compass_rad as CARLA (radians from north, clockwise); null "
                       "when the capture has no IMU",
                "gnss": "sensor_data gnss: latitude_deg, longitude_deg, altitude_m of the ego origin; null when "
                        "the capture has no GNSS",
                "lidar": "lidar_vehicle, semantic_lidar_vehicle: points of the sweep at t in the ISO vehicle frame "
                         "(the lidar mount of sensors.json applied); lidar_data keeps the raw sensor frame",
                "radar": "radar_data: CARLA's velocity, azimuth, altitude, depth (sensor frame) plus x, y, z of "
                         "each detection in the ISO vehicle frame = the radar mount applied to depth (cos(alt) "
                         "cos(az), cos(alt) sin(az), sin(alt)) (Unreal axes, azimuth positive to the right)",
            },
            "semantic": {"table": "SynWoodScape 25 classes: CARLA 0.9.10 ids 0-18, then 19 water, 20 terrain, "
                                  "21 two-wheeler, 22 static, 23 dynamic, 24 ego vehicle"},
            "instances": "gtLabels = CARLA actor id (0 = none); rgbLabels colour = hash of the actor id",
            "motion": {"threshold_m": options.motion_threshold_m, "default_threshold_m": MOTION_THRESHOLD_M,
                       "rule": "255 where the pixel's actor moved more than threshold_m between t-1 and t "
                               "(distances_traveled lists every actor's displacement for re-thresholding)"},
            "boxes_2d": "lines 'class_name,class_id,x1,y1,x2,y2', inclusive pixel-centre coordinates of the extreme "
                        "pixels, class_id = SynWoodScape class; empty file when no box",
            "boxes_3d": "box_3d_annotations: pickle {actor_id: (8, 3) float64 corners, CARLA world, at t}; corner "
                        "index = 4 ix + 2 iy + iz over the box axes' signs (-, +); class and vehicle-frame corners "
                        "in box_3d_annotations_ext",
        },
        "classes": {"names": list(SYNWOODSCAPE_CLASSES),
                    "palette": np.asarray(SYNWOODSCAPE_PALETTE).astype(int).tolist()},
        "corrected_extrinsics": {
            "synwoodscape_translations_carla": {k: [float(v) for v in t] for k, t in
                                                SYNWOODSCAPE_CORRECTED_TRANSLATIONS_CARLA.items()},
            "note": "the released SynWoodScape MVL / MVR translations are wrong; these corrections (WoodScape issue "
                    "#113; CARLA frame, metres) apply to the release's files (jaxfish.load_calibration(path, "
                    "apply_errata=True)). This dataset's calibration_data is the capture's own rig, "
                    "already consistent.",
        },
        "layout": [dict(e) for e in LAYOUT],
        "dataset_files": [dict(e) for e in DATASET_FILES],
    }


def _bev_block(source) -> dict[str, Any]:
    from ..bev import bev_metadata

    cam, c2v = source.bev_sensor()
    return bev_metadata(cam, c2v, origin="the ego body centre on the ground (sensors.json bev.camera_to_vehicle)")


def write_dataset_files(source, out_dir: str | os.PathLike, options: BuildOptions | None = None) -> list[Path]:
    """Write the dataset-level files: ``dataset.json`` (`dataset_manifest`),
    ``calibration_data/{camera}.json`` (the source's calibration files, byte for byte),
    ``calibration_data/BEV.json`` (BEV scale and axes; removed when the build has no BEV),
    ``semantic_annotations/seg_annotation_info.json`` (classes and palette) and ``sequence.json``
    (`sequences_doc` of the complete samples). Atomic, deterministic."""
    from ..io import atomic_write_bytes, atomic_write_text
    from ..io._json import to_json_text
    from ._sink import synwoodscape_palette_dict
    from ._sources import as_source

    options = options or BuildOptions()
    source = as_source(source)
    out = Path(out_dir)
    paths = []
    source.rig()  # every calibration valid before one is copied (never a broken file over a good one)
    manifest = dataset_manifest(source, out, options)
    # Every JSON text first (strict: a non-finite number names the file and field), then the files.
    docs: dict[str, Any] = {}
    if manifest["conventions"]["bev"] is not None:
        docs[f"calibration_data/{BEV_CAMERA}.json"] = manifest["conventions"]["bev"]
    docs["semantic_annotations/seg_annotation_info.json"] = synwoodscape_palette_dict()
    docs["sequence.json"] = sequences_doc(manifest["samples"], manifest["time"]["dt_s"])
    docs["dataset.json"] = manifest
    texts = {rel: to_json_text(out / rel, doc, indent=1, error=DatasetError) for rel, doc in docs.items()}
    for cam in source.cameras:
        paths.append(atomic_write_bytes(out / "calibration_data" / f"{cam}.json", source.calibration_bytes(cam)))
    if manifest["conventions"]["bev"] is None:  # a build without the BEV (rebuilt with bev=False) describes no BEV camera
        (out / "calibration_data" / f"{BEV_CAMERA}.json").unlink(missing_ok=True)
    for rel, text in texts.items():
        paths.append(atomic_write_text(out / rel, text))
    return paths
