"""The dataset's file layout as data: every folder, its file pattern, format, dtype, shape and unit.

`LAYOUT` is written into ``dataset.json`` (``"layout"``) so that a loader needs nothing but that file
(and NumPy / pickle / an image reader) to find and decode every file; ``docs/dataset.md`` renders
the same table for people.
"""

from __future__ import annotations

from typing import Any

FISHEYE_CAMERAS = ("FV", "RV", "MVL", "MVR")
"""The fisheye cameras in SynWoodScape's order of the release's figure columns: front, rear, left, right."""
BEV_CAMERA = "BEV"
"""Name of the top-view (bird's-eye view) camera in file names."""
SAMPLE_DIGITS = 5
"""Digits of a sample id: sample ``k`` is the capture's frame ``k`` (``{k:05d}``)."""
LAYOUT_VERSION = 4
"""Version of this layout (bumped on any change of folder, name, dtype or meaning; 2: depth EXR;
3: flow masks, ``sensor_data``, lidar / semantic lidar / radar in the vehicle frame; 4: tonic
events in int16 / int64 / int8 instead of four int64 columns). Completion markers of another
version do not count as complete: resuming rebuilds them."""


def sample_id(frame: int) -> str:
    """The sample id of a capture frame: ``f"{frame:05d}"`` (SynWoodScape's ``{id:05d}``)."""
    if int(frame) < 0:
        raise ValueError(f"sample_id: frame must be non-negative, got {frame}")
    return f"{int(frame):0{SAMPLE_DIGITS}d}"


def _e(key: str, pattern: str, fmt: str, dtype: str, shape: str, unit: str, cameras: str, what: str,
       origin: str = "synwoodscape") -> dict[str, Any]:
    return {"key": key, "pattern": pattern, "format": fmt, "dtype": dtype, "shape": shape, "unit": unit,
            "cameras": cameras, "description": what, "origin": origin}


LAYOUT: tuple[dict[str, Any], ...] = (
    _e("rgb", "rgb_images/{sample}_{camera}.png", "png", "uint8", "(H, W, 3)", "sRGB-less linear albedo x shading, 0..255",
       "all", "RGB image at t"),
    _e("rgb_prev", "previous_images/{sample}_{camera}_prev.png", "png", "uint8", "(H, W, 3)", "as rgb", "all",
       "RGB image at t-1 (the previous frame, 0.1 s earlier)"),
    _e("depth", "depth_maps/raw_data/{sample}_{camera}.npy", "npy", "float32", "(H, W)", "metres", "all",
       "Euclidean range along each pixel's ray at t; sky / beyond 1000 m = 1000; 0 = pixel without a ray"),
    _e("depth_exr", "depth_maps/exr/{sample}_{camera}.exr", "exr", "float32", "(H, W, 1) channel Z", "metres", "all",
       "the range of depth_maps/raw_data as an uncompressed OpenEXR; definition in attribute 'jaxfish:depth'", "jaxfish"),
    _e("depth_z", "depth_maps/z_depth/{sample}_{camera}.npy", "npy", "float32", "(H, W)", "metres", "all",
       "planar z-depth along the camera's optical axis at t (range x ray_z); sky = 1000", "jaxfish"),
    _e("depth_color", "depth_maps/colormap/{sample}_{camera}.png", "png", "uint8", "(H, W, 3)", "-", "all",
       "depth rendering: magma ramp on log range over 0.5..100 m (near bright); sky and no-ray black"),
    _e("semantic", "semantic_annotations/gtLabels/{sample}_{camera}.png", "png", "uint8", "(H, W)", "class id",
       "all", "SynWoodScape class (0..24, table in dataset.json 'classes') at t"),
    _e("semantic_color", "semantic_annotations/rgbLabels/{sample}_{camera}.png", "png", "uint8", "(H, W, 3)", "-",
       "all", "class colours (palette in dataset.json and in the PNG attribute 'jaxfish:palette')"),
    _e("instance", "instance_annotations/gtLabels/{sample}_{camera}.png", "png", "uint8 or uint16", "(H, W)",
       "CARLA actor id", "all", "actor id of the box holding each pixel at t (0 = none); uint16 when an id > 255"),
    _e("instance_color", "instance_annotations/rgbLabels/{sample}_{camera}.png", "png", "uint8", "(H, W, 3)", "-",
       "all", "instance colours: a hash of the actor id (same actor, same colour in every sample)"),
    _e("motion", "motion_annotations/gtLabels/{sample}_{camera}.png", "png", "uint8", "(H, W)", "0 / 255", "all",
       "255 where the pixel's actor moved more than the motion threshold between t-1 and t"),
    _e("motion_color", "motion_annotations/rgbLabels/{sample}_{camera}.png", "png", "uint8", "(H, W, 3)", "-", "all",
       "motion mask as a grey image"),
    _e("flow", "optical_flow/raw_data/{sample}_{camera}.flo", "flo", "float32", "(H, W, 2)", "pixels", "all",
       "Middlebury .flo: forward flow t-1 -> t on the t-1 pixel grid, (u right, v down); 0 where invalid"),
    _e("flow_kitti", "optical_flow/kitti/{sample}_{camera}.png", "png", "uint16", "(H, W, 3)", "pixels",
       "all", "KITTI flow PNG: (u, v) = (value - 2**15) / 64, channel 2 = valid", "jaxfish"),
    _e("flow_color", "optical_flow/color_coded/{sample}_{camera}.png", "png", "uint8", "(H, W, 3)", "-", "all",
       "Baker et al. colour wheel rendering of the flow"),
    _e("flow_valid", "optical_flow/valid_mask/{sample}_{camera}.png", "png", "uint8", "(H, W)", "0 / 255", "all",
       "255 where the t-1 pixel has a ray, its point lands inside the image at t and is seen there "
       "(not occluded): the flow's validity; 0 elsewhere", "jaxfish"),
    _e("flow_occlusion", "optical_flow/occlusion_mask/{sample}_{camera}.png", "png", "uint8", "(H, W)", "0 / 255",
       "all", "255 where the t-1 pixel's point lands inside the image at t but is hidden there by a nearer "
       "surface (occluded); 0 elsewhere", "jaxfish"),
    _e("events", "dvs_signals/raw_data/{sample}_{camera}.npy", "npy", "[x <u2, y <u2, t <i8, pol ?]", "(N,)",
       "t in nanoseconds (absolute simulation time)", "fisheye",
       "DVS events between t-1 and t on fisheye pixels, time order, CARLA's dtype"),
    _e("events_tonic", "dvs_signals/tonic/{sample}_{camera}.npz", "npz", "[x <i2, y <i2, t <i8, p i1]", "(N,)",
       "t in microseconds", "fisheye",
       "tonic-compatible events ('events'), with 'time_unit' = 'us' and 'sensor_size' = (W, H, 2)", "jaxfish"),
    _e("events_color", "dvs_signals/color_coded/{sample}_{camera}.png", "png", "uint8", "(H, W, 3)", "-", "fisheye",
       "event rendering: blue net positive, red net negative polarity, white none"),
    _e("boxes_2d", "box_2d_annotations/{sample}_{camera}.txt", "csv", "text", "(B, 6)", "pixels", "all",
       "visible 2D boxes: lines 'class_name,class_id,x1,y1,x2,y2' (inclusive pixel-centre coordinates)"),
    _e("boxes_2d_full", "box_2d_full_annotations/{sample}_{camera}.txt", "csv", "text", "(B, 6)", "pixels", "all",
       "2D boxes of the full (amodal) 3D box extent, same format", "jaxfish"),
    _e("boxes_3d", "box_3d_annotations/{sample}.pkl", "pickle", "dict[int, float64 (8, 3)]", "{actor_id: (8, 3)}",
       "metres", "sample", "3D box corners of every actor at t in CARLA world coordinates (no class)"),
    _e("boxes_3d_ext", "box_3d_annotations_ext/{sample}.json", "json", "-", "{'boxes': [...]}", "metres", "sample",
       "3D boxes with class id / name and corners in CARLA world and ISO 8855 vehicle frames", "jaxfish"),
    _e("distances", "distances_traveled/{sample}.txt", "text", "text", "(A, 4)", "metres", "sample",
       "'# header' then 'actor_id class_id displacement_m moving' per actor (displacement t-1 -> t)"),
    _e("vehicle", "vehicle_data/rgb_images/{sample}.txt", "text", "text", "key values", "see lines", "sample",
       "ego vehicle at t: 'name v1 v2 ...' lines (timestamp_s, location_m, rotation_deg, velocity_mps, ...)"),
    _e("vehicle_prev", "vehicle_data/previous_images/{sample}.txt", "text", "text", "key values", "see lines",
       "sample", "ego vehicle at t-1, same format"),
    _e("lidar", "lidar_data/{sample}.pkl", "pickle", "dict of arrays", "{'points': (N, 4) float32, ...}",
       "metres", "sample", "lidar sweep at t: 'points' x, y, z, intensity in the sensor frame (Unreal axes), "
       "'semantic_lidar' and 'radar' CARLA records, 'frame' (words)"),
    _e("sensor_data", "sensor_data/{sample}.json", "json", "-", "{'sample', 'frame', 'timestamp_s', ...}",
       "s, m, m/s, m/s^2, rad/s, rad, deg", "sample",
       "timestamps of t and t-1; ego 'vehicle_to_world' (4 x 4: ISO 8855 vehicle at t -> CARLA world), "
       "'velocity_mps', 'acceleration_mps2', 'angular_velocity_radps' (ISO vehicle frame at t); 'imu' "
       "('accelerometer_mps2', 'gyroscope_radps' in the ISO vehicle frame, 'compass_rad') and 'gnss' "
       "('latitude_deg', 'longitude_deg', 'altitude_m'), null when the capture has none", "jaxfish"),
    _e("lidar_vehicle", "lidar_vehicle/{sample}.npy", "npy", "float32", "(N, 4)", "metres", "sample",
       "lidar sweep at t: x, y, z in the ISO 8855 vehicle frame at t, intensity", "jaxfish"),
    _e("semantic_lidar_vehicle", "semantic_lidar_vehicle/{sample}.npy", "npy",
       "[x <f4, y <f4, z <f4, cos_inc_angle <f4, object_idx <u4, object_tag <u4]", "(N,)", "metres", "sample",
       "semantic lidar at t: x, y, z in the ISO 8855 vehicle frame at t; CARLA's cosine of the incidence "
       "angle, actor id (0 = static) and semantic tag (the capture's table)", "jaxfish"),
    _e("radar", "radar_data/{sample}.npy", "npy",
       "[velocity <f4, azimuth <f4, altitude <f4, depth <f4, x <f4, y <f4, z <f4]", "(N,)",
       "m/s, rad, rad, m, metres", "sample",
       "radar detections at t: CARLA's fields in the sensor frame (radial velocity, negative = approaching; "
       "azimuth positive to the right; altitude; depth) and x, y, z of each detection in the ISO 8855 "
       "vehicle frame at t", "jaxfish"),
    _e("bev_height", "bev_height/raw_data/{sample}_BEV.npy", "npy", "float32", "(H, W)", "metres", "BEV",
       "height above the ground of the surface each BEV pixel sees at t", "jaxfish"),
    _e("bev_height_color", "bev_height/colormap/{sample}_BEV.png", "png", "uint8", "(H, W, 3)", "-", "BEV",
       "height rendering (viridis); the PNG attribute 'jaxfish:bev' holds the BEV scale", "jaxfish"),
    _e("bev_occupancy", "bev_occupancy/{sample}_BEV.png", "png", "uint8", "(H, W)", "0 / 255", "BEV",
       "255 where the top surface is higher than the occupancy threshold", "jaxfish"),
)
"""Every per-sample file of a dataset. ``pattern`` uses ``{sample}`` (5-digit id) and ``{camera}``;
``cameras`` is ``"fisheye"`` (FV, RV, MVL, MVR), ``"all"`` (the fisheyes and BEV), ``"BEV"`` or
``"sample"`` (one file per sample); ``origin`` is ``"synwoodscape"`` for the released layout
and ``"jaxfish"`` for the extras. Shapes: ``H, W`` of the camera's image, ``N`` events/points,
``B`` boxes, ``A`` actors."""

DATASET_FILES: tuple[dict[str, Any], ...] = (
    {"key": "manifest", "pattern": "dataset.json", "format": "json",
     "description": "conventions, class table, BEV scale, frames, corrected extrinsics, layout, samples"},
    {"key": "calibration", "pattern": "calibration_data/{camera}.json", "format": "json",
     "description": "WoodScape calibration JSON per fisheye camera (quaternion x, y, z, w; camera -> vehicle)"},
    {"key": "bev_calibration", "pattern": "calibration_data/BEV.json", "format": "json",
     "description": "BEV scale and axes (metres per pixel, pixel -> vehicle affine, camera -> vehicle pose)"},
    {"key": "classes", "pattern": "semantic_annotations/seg_annotation_info.json", "format": "json",
     "description": "class names and palette ({'classes': [...], 'colors': [[r, g, b], ...]})"},
    {"key": "sequences", "pattern": "sequence.json", "format": "json",
     "description": "sequences of consecutive samples and each sample's neighbours ({'sequences': [{'name', "
                    "'samples', 'dt_s'}], 'neighbours': {sample: {'previous', 'next'}}})"},
    {"key": "done", "pattern": ".done/{sample}.json", "format": "json",
     "description": "completion marker of a sample (written last): its files and their digests (BLAKE3)"},
)
"""Files written once per dataset (not per sample)."""


def layout_entries(cameras: str | None = None) -> list[dict[str, Any]]:
    """The `LAYOUT` entries, optionally only those whose ``cameras`` field equals ``cameras``."""
    return [dict(e) for e in LAYOUT if cameras is None or e["cameras"] == cameras]


def sample_files(sample: str, fisheye: tuple[str, ...] = FISHEYE_CAMERAS, *, bev: bool = True) -> list[str]:
    """Relative paths of every file `LAYOUT` promises for ``sample`` (sorted)."""
    out = []
    for e in LAYOUT:
        cams = {"fisheye": list(fisheye), "all": list(fisheye) + ([BEV_CAMERA] if bev else []),
                "BEV": [BEV_CAMERA] if bev else [], "sample": [None]}[e["cameras"]]
        for cam in cams:
            out.append(e["pattern"].format(sample=sample, camera=cam))
    return sorted(out)
