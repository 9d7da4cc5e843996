"""Every sensor in the dataset, in the ISO 8855 vehicle frame: ``sensor_data``, ``lidar_vehicle``,
``semantic_lidar_vehicle``, ``radar_data``; flow masks on disk; ``sequence.json``."""

from __future__ import annotations

import json
import math
import pickle
import shutil

import cv2
import numpy as np
import pytest

import jaxfish as jf
from jaxfish.dataset import write_dataset_files
from jaxfish.dataset._manifest import sequences_doc
from jaxfish.pipeline import (
    RADAR_VEHICLE_DTYPE,
    SEMANTIC_LIDAR_VEHICLE_DTYPE,
    SensorRecords,
    sensor_to_vehicle_matrix,
    sensor_truth,
    vehicle_to_world_matrix,
)
from jaxfish.pipeline._sensors import unreal_angular_velocity_to_iso

from .. import tolerances as tol

S = np.diag([1.0, -1.0, 1.0])


def _carla_rotation(pitch, yaw, roll):
    """CARLA's rotation (Unreal, left-handed) written from its documented composition: roll about x,
    then pitch (nose up) about y, then yaw about z (x towards y)."""
    p, y, r = np.deg2rad([pitch, yaw, roll])
    rz = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
    ry = np.array([[np.cos(p), 0, -np.sin(p)], [0, 1, 0], [np.sin(p), 0, np.cos(p)]])
    rx = np.array([[1, 0, 0], [0, np.cos(r), np.sin(r)], [0, -np.sin(r), np.cos(r)]])
    return rz @ ry @ rx


def test_mount_and_ego_matrices_against_an_independent_composition():
    loc, rot = [1.5, -0.25, 2.0], [3.0, 40.0, -7.0]
    m = sensor_to_vehicle_matrix(loc, rot)
    ref = np.eye(4)
    ref[:3, :3], ref[:3, 3] = S @ _carla_rotation(*rot), S @ np.asarray(loc)
    np.testing.assert_allclose(m, ref, atol=tol.SENSOR_FRAME_F64)
    assert np.linalg.det(m[:3, :3]) == pytest.approx(-1.0)
    # A point 10 m straight ahead of a level sensor lies 10 m ahead of its ISO location.
    level = sensor_to_vehicle_matrix(loc, [0.0, 0.0, 0.0])
    np.testing.assert_allclose(level @ [10.0, 0.0, 0.0, 1.0], [11.5, 0.25, 2.0, 1.0], atol=tol.SENSOR_FRAME_F64)
    # A point to the sensor's right (Unreal +y) is at negative ISO y.
    assert (level @ [0.0, 3.0, 0.0, 1.0])[1] == pytest.approx(0.25 - 3.0)
    v2w = vehicle_to_world_matrix(loc, rot)
    back = np.linalg.inv(v2w) @ np.append(ref[:3, :3] @ [1.0, 2.0, 3.0] + ref[:3, 3], 1.0)
    assert np.all(np.isfinite(back))
    np.testing.assert_allclose(v2w[:3, :3] @ S, _carla_rotation(*rot), atol=tol.SENSOR_FRAME_F64)


def test_angular_velocity_follows_the_rotation_it_integrates():
    # A rotation rate w of the left-handed frame moves R(t) = expm([w]x t) R0 (formal in its coordinates);
    # the same motion in ISO coordinates is S R(t) S, whose rate must be the converted vector.
    w = np.array([0.3, -0.2, 0.5])
    r0 = _carla_rotation(5.0, 30.0, -4.0)
    h = 1e-6
    skew = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    r_h = (np.eye(3) + skew * h + skew @ skew * h * h / 2) @ r0
    d = (S @ r_h @ S - S @ r0 @ S) / h @ (S @ r0 @ S).T
    w_iso = np.array([d[2, 1], d[0, 2], d[1, 0]])
    np.testing.assert_allclose(unreal_angular_velocity_to_iso(w), w_iso, atol=1e-5)
    # Yaw increasing in CARLA (turning right) is a negative ISO yaw rate.
    assert unreal_angular_velocity_to_iso([0.0, 0.0, 1.0])[2] == -1.0


def _records(**kw):
    ego = {"timestamp_s": 1.0, "timestamp_prev_s": 0.9,
           "transform": {"location": [10.0, 20.0, 0.0], "rotation": [0.0, 90.0, 0.0]},
           "velocity": [0.0, 5.0, 0.0], "acceleration": [1.0, 0.0, 0.0], "angular_velocity": [0.0, 0.0, 10.0]}
    base = dict(ego=ego, lidar=np.zeros((0, 4), np.float32), semantic_lidar=np.zeros(0), radar=np.zeros(0),
                imu={}, gnss={})
    return SensorRecords(**{**base, **kw})


def test_ego_state_in_the_vehicle_frame():
    s = sensor_truth(_records())
    # Heading along world +y (yaw 90) at 5 m/s: straight ahead in the vehicle frame.
    np.testing.assert_allclose(s.ego.velocity_mps, [5.0, 0.0, 0.0], atol=tol.SENSOR_FRAME_F64)
    # World +x is to the ego's left when it heads along +y in a left-handed world (+y right of +x).
    np.testing.assert_allclose(s.ego.acceleration_mps2, [0.0, 1.0, 0.0], atol=tol.SENSOR_FRAME_F64)
    np.testing.assert_allclose(s.ego.angular_velocity_radps, [0.0, 0.0, -math.radians(10.0)], atol=tol.SENSOR_FRAME_F64)
    assert s.imu is None and s.gnss is None  # a capture without IMU / GNSS records
    assert (s.ego.timestamp_s, s.ego.previous_timestamp_s) == (1.0, 0.9)


def test_points_without_their_mount_are_refused():
    with pytest.raises(ValueError, match="lidar mount"):
        sensor_truth(_records(lidar=np.ones((3, 4), np.float32)))


def test_sequences_split_at_gaps():
    doc = sequences_doc(["00004", "00000", "00001", "00002", "00007", "00005"], 0.1)
    assert [s["samples"] for s in doc["sequences"]] == [["00000", "00001", "00002"], ["00004", "00005"], ["00007"]]
    assert [s["name"] for s in doc["sequences"]] == ["seq_00000", "seq_00001", "seq_00002"]
    assert all(s["dt_s"] == 0.1 for s in doc["sequences"])
    assert doc["neighbours"]["00001"] == {"previous": "00000", "next": "00002"}
    assert doc["neighbours"]["00002"] == {"previous": "00001", "next": None}
    assert doc["neighbours"]["00007"] == {"previous": None, "next": None}
    assert sequences_doc([], 0.1) == {"sequences": [], "neighbours": {}}


# ------------------------------------------------------------------------------ the built dataset
def _read(path):
    a = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert a is not None, path
    return a


def test_sensor_files_have_their_dtypes_and_shapes(reference_build):
    out, _ = reference_build
    meta = json.loads((out / "dataset.json").read_text())
    keys = {e["key"] for e in meta["layout"]}
    assert {"sensor_data", "lidar_vehicle", "semantic_lidar_vehicle", "radar", "flow_valid", "flow_occlusion"} <= keys
    assert "sequence.json" in {e["pattern"] for e in meta["dataset_files"]}
    assert "sensors" in meta["conventions"] and "valid_mask" in meta["conventions"]["optical_flow"]
    for sid in meta["samples"]:
        doc = json.loads((out / "sensor_data" / f"{sid}.json").read_text())
        assert list(doc) == ["sample", "frame", "timestamp_s", "previous_timestamp_s", "ego", "imu", "gnss"]
        assert doc["sample"] == sid and doc["frame"] == int(sid)
        assert doc["timestamp_s"] - doc["previous_timestamp_s"] == pytest.approx(meta["time"]["dt_s"])
        assert np.asarray(doc["ego"]["vehicle_to_world"]).shape == (4, 4)
        assert set(doc["imu"]) == {"accelerometer_mps2", "gyroscope_radps", "compass_rad"}
        assert set(doc["gnss"]) == {"latitude_deg", "longitude_deg", "altitude_m"}
        assert doc["imu"]["accelerometer_mps2"][2] == pytest.approx(9.81, abs=0.5)  # gravity up in ISO too
        lidar = np.load(out / "lidar_vehicle" / f"{sid}.npy")
        assert lidar.dtype == np.float32 and lidar.ndim == 2 and lidar.shape[1] == 4 and len(lidar) > 100
        sem = np.load(out / "semantic_lidar_vehicle" / f"{sid}.npy")
        assert sem.dtype == SEMANTIC_LIDAR_VEHICLE_DTYPE and sem.shape == (len(lidar),)
        radar = np.load(out / "radar_data" / f"{sid}.npy")
        assert radar.dtype == RADAR_VEHICLE_DTYPE and radar.ndim == 1 and len(radar) > 0
        marker = json.loads((out / ".done" / f"{sid}.json").read_text())["files"]
        for cam in meta["cameras"]:
            w, h = meta["image_size_wh"][cam]
            valid = _read(out / "optical_flow" / "valid_mask" / f"{sid}_{cam}.png")
            occ = _read(out / "optical_flow" / "occlusion_mask" / f"{sid}_{cam}.png")
            for m in (valid, occ):
                assert m.dtype == np.uint8 and m.shape == (h, w) and set(np.unique(m)) <= {0, 255}
            assert not np.any((valid > 0) & (occ > 0))
            kitti = _read(out / "optical_flow" / "kitti" / f"{sid}_{cam}.png")  # BGR: valid is channel 0 here
            np.testing.assert_array_equal(valid > 0, kitti[..., 0] > 0)
            assert f"optical_flow/valid_mask/{sid}_{cam}.png" in marker
        for rel in (f"sensor_data/{sid}.json", f"lidar_vehicle/{sid}.npy", f"semantic_lidar_vehicle/{sid}.npy",
                    f"radar_data/{sid}.npy"):
            assert rel in marker
    seq = json.loads((out / "sequence.json").read_text())
    assert seq["sequences"] == [{"name": "seq_00000", "samples": meta["samples"], "dt_s": meta["time"]["dt_s"]}]


def _mount(small_capture, name):
    doc = json.loads((small_capture / "sensors.json").read_text())[name]
    return doc, sensor_to_vehicle_matrix(doc["carla_transform"]["location"], doc["carla_transform"]["rotation"])


def test_raw_and_vehicle_frame_points_are_one_rigid_map_apart(reference_build, small_capture):
    out, _ = reference_build
    lidar_doc, m_lidar = _mount(small_capture, "lidar")
    radar_doc, m_radar = _mount(small_capture, "radar")
    # The mount's ISO position is the capture's own record of it.
    np.testing.assert_allclose(m_lidar[:3, 3], lidar_doc["location_vehicle"], atol=tol.SENSOR_FRAME_F64)
    np.testing.assert_allclose(m_radar[:3, 3], radar_doc["location_vehicle"], atol=tol.SENSOR_FRAME_F64)
    for sid in json.loads((out / "dataset.json").read_text())["samples"]:
        raw = pickle.loads((out / "lidar_data" / f"{sid}.pkl").read_bytes())
        lidar = np.load(out / "lidar_vehicle" / f"{sid}.npy")
        back = (np.linalg.inv(m_lidar) @ np.c_[lidar[:, :3], np.ones(len(lidar))].T).T[:, :3]
        np.testing.assert_allclose(back, raw["points"][:, :3], atol=tol.LIDAR_FLOAT32_M)
        np.testing.assert_array_equal(lidar[:, 3], raw["points"][:, 3])
        sem = np.load(out / "semantic_lidar_vehicle" / f"{sid}.npy")
        np.testing.assert_array_equal(sem["object_tag"], raw["semantic_lidar"]["ObjTag"])
        np.testing.assert_array_equal(sem["object_idx"], raw["semantic_lidar"]["ObjIdx"])
        np.testing.assert_array_equal(sem["cos_inc_angle"], raw["semantic_lidar"]["CosAngle"])
        radar = np.load(out / "radar_data" / f"{sid}.npy")
        for k in ("velocity", "azimuth", "altitude", "depth"):
            np.testing.assert_array_equal(radar[k], raw["radar"][k])
        # Each detection lies `depth` from the radar, in its azimuth (positive to the right = ISO -y).
        rel = np.stack([radar["x"], radar["y"], radar["z"]], -1).astype(np.float64) - m_radar[:3, 3]
        np.testing.assert_allclose(np.linalg.norm(rel, axis=-1), radar["depth"], rtol=1e-5, atol=1e-4)
        np.testing.assert_allclose(np.arctan2(-rel[:, 1], rel[:, 0]), radar["azimuth"], atol=1e-4)


def test_ego_pose_maps_the_vehicle_frame_boxes_to_the_world_ones(reference_build, small_capture):
    out, _ = reference_build
    for sid in json.loads((out / "dataset.json").read_text())["samples"]:
        doc = json.loads((out / "sensor_data" / f"{sid}.json").read_text())
        v2w = np.asarray(doc["ego"]["vehicle_to_world"])
        boxes = json.loads((out / "box_3d_annotations_ext" / f"{sid}.json").read_text())["boxes"]
        assert boxes
        for b in boxes:
            veh, world = np.asarray(b["corners_vehicle"]), np.asarray(b["corners_world"])
            np.testing.assert_allclose(veh @ v2w[:3, :3].T + v2w[:3, 3], world, atol=2e-3)
        ego = json.loads((small_capture / "frames" / f"{int(sid):06d}" / "ego.json").read_text())
        r = v2w[:3, :3]
        np.testing.assert_allclose(r @ doc["ego"]["velocity_mps"], ego["velocity"], atol=tol.SENSOR_FRAME_F64)
        np.testing.assert_allclose(r @ doc["ego"]["acceleration_mps2"], ego["acceleration"], atol=tol.SENSOR_FRAME_F64)


def test_lidar_points_in_the_vehicle_frame_land_on_the_depth_maps(reference_build):
    out, _ = reference_build
    meta = json.loads((out / "dataset.json").read_text())
    sid = meta["samples"][-1]
    lidar = np.load(out / "lidar_vehicle" / f"{sid}.npy")[:, :3].astype(np.float64)
    used = 0
    for cam in meta["fisheye_cameras"]:
        calib = jf.load_calibration(out / "calibration_data" / f"{cam}.json", dtype=np.float64)
        c2v = calib.camera_to_vehicle
        r, t = np.asarray(c2v.rotation_matrix, np.float64), np.asarray(c2v.translation, np.float64)
        p_cam = (lidar - t) @ r  # R^T (p - t)
        uv, ok = calib.camera.project(p_cam)
        uv, ok = np.asarray(uv), np.asarray(ok)
        depth = np.load(out / "depth_maps" / "raw_data" / f"{sid}_{cam}.npy")
        h, w = depth.shape
        x0, y0 = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
        inside = ok & (x0 >= 0) & (y0 >= 0) & (x0 + 1 < w) & (y0 + 1 < h)
        x0, y0 = x0[inside], y0[inside]
        taps = np.stack([depth[y0, x0], depth[y0, x0 + 1], depth[y0 + 1, x0], depth[y0 + 1, x0 + 1]], -1).astype(np.float64)
        rng = np.linalg.norm(p_cam[inside], axis=-1)
        keep = np.all(taps > 0, axis=-1)
        rng, lo, hi = rng[keep], taps[keep].min(-1), taps[keep].max(-1)
        on = (rng >= lo * (1 - tol.LIDAR_ON_DEPTH_REL)) & (rng <= hi * (1 + tol.LIDAR_ON_DEPTH_REL))
        in_front = rng < lo * (1 - tol.LIDAR_ON_DEPTH_REL)
        used += rng.size
        assert on.mean() >= tol.LIDAR_ON_DEPTH_BRACKETED, (cam, on.mean())
        assert in_front.mean() <= tol.LIDAR_IN_FRONT_OF_DEPTH, (cam, in_front.mean())
    assert used > 200


def test_sequence_json_is_rewritten_from_the_complete_samples_and_splits_at_gaps(reference_build, small_capture, tmp_path):
    out, _ = reference_build
    copy = tmp_path / "dataset"
    shutil.copytree(out, copy)
    before = (copy / "sequence.json").read_bytes()
    write_dataset_files(small_capture, copy)
    assert (copy / "sequence.json").read_bytes() == before  # deterministic bytes
    marker = json.loads((copy / ".done" / "00001.json").read_text())
    (copy / ".done" / "00003.json").write_text(json.dumps({**marker, "sample": "00003", "frame": 3}))
    write_dataset_files(small_capture, copy)
    seq = json.loads((copy / "sequence.json").read_text())
    assert [s["samples"] for s in seq["sequences"]] == [["00000", "00001"], ["00003"]]
    assert seq["neighbours"]["00001"]["next"] is None and seq["neighbours"]["00003"]["previous"] is None
