"""Consistency of the capture with the scene: road on z = 0, actors in their boxes, events where
the log intensity changed, determinism, plausible motion, lidar / radar / IMU / GNSS."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
import pytest

from jaxfish.io import decode_depth, encode_depth
from jaxfish.reprojection import CubeRig
from jaxfish.scene import (
    CARLA_SEMANTIC_TAGS,
    bev_camera,
    dvs_events,
    frame_times_ns,
    generate_street,
    location_to_geo,
    log_intensity,
    sensor_mounts,
    simulate_camera,
    simulate_gnss,
    simulate_imu,
    simulate_lidar,
    simulate_radar,
    simulate_view,
)
from tests.tolerances import SCENE_BOX_PAD_M, SCENE_ROAD_Z_M

from .conftest import FACE

ROAD = (CARLA_SEMANTIC_TAGS["road"], CARLA_SEMANTIC_TAGS["roadline"])


def _world_points(street, calib, face_name, depth_m):
    """Face pixels + CARLA-decoded planar depth + calibration -> world points (independent path:
    numpy float64, K^-1 [u, v, 1] d, face pose, mount, ego transform)."""
    rig = CubeRig(FACE, dtype=jnp.float64)
    k = np.asarray(rig.face.intrinsic_matrix)
    v, u = np.mgrid[0:FACE, 0:FACE].astype(np.float64)
    pix = np.stack([u, v, np.ones_like(u)], axis=-1)
    p_face = (pix @ np.linalg.inv(k).T) * depth_m[..., None]
    face_pose = rig.face_pose(face_name)
    p_cam = p_face @ np.asarray(face_pose.rotation_matrix).T
    p_iso = p_cam @ np.asarray(calib.camera_to_vehicle.rotation_matrix, np.float64).T + np.asarray(calib.camera_to_vehicle.translation, np.float64)
    p_actor = p_iso * np.array([1.0, -1.0, 1.0])  # ISO -> CARLA actor frame
    ego = street.ego
    yaw = math.radians(ego.rotation[1])
    r = np.array([[math.cos(yaw), -math.sin(yaw), 0.0], [math.sin(yaw), math.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
    return p_actor @ r.T + np.asarray(ego.location)


def test_road_pixels_unproject_to_the_ground(street, small_rig, faces_t):
    n = 0
    for name, faces in faces_t.items():
        for face_name, b in faces.items():
            depth = decode_depth(encode_depth(np.asarray(b.depth_m))).astype(np.float64)
            road = np.isin(np.asarray(b.semantic), ROAD)
            if not road.any():
                continue
            p = _world_points(street, small_rig[name], face_name, depth)
            np.testing.assert_allclose(p[road][:, 2], 0.0, atol=SCENE_ROAD_Z_M)
            n += int(road.sum())
    assert n > 1000


def test_actor_pixels_fall_inside_their_boxes(street, small_rig, faces_t):
    seen = set()
    for name, faces in faces_t.items():
        for face_name, b in faces.items():
            ids = np.asarray(b.actor_id)
            depth = decode_depth(encode_depth(np.asarray(b.depth_m))).astype(np.float64)
            p = _world_points(street, small_rig[name], face_name, depth)
            for actor_id in np.unique(ids[ids > 0]):
                a = street.actor_by_id(int(actor_id))
                yaw = math.radians(a.rotation[1])
                rel = p[ids == actor_id] - np.asarray(a.location)
                local = np.stack([math.cos(yaw) * rel[:, 0] + math.sin(yaw) * rel[:, 1],
                                  -math.sin(yaw) * rel[:, 0] + math.cos(yaw) * rel[:, 1], rel[:, 2]], axis=-1)
                off = np.abs(local - np.asarray(a.bbox_location)) - np.asarray(a.bbox_extent)
                assert np.all(off <= SCENE_BOX_PAD_M), (a.id, a.category, off.max())
                seen.add(a.category)
    assert {"ego", "four_wheeler"} <= seen


def test_events_only_where_log_intensity_crossed_the_threshold(street, small_rig, small_config):
    cap = simulate_camera(street, small_rig["MVR"], small_config)
    c = small_config.dvs_threshold
    total = 0
    times = frame_times_ns(street, small_config.dvs_substeps)
    for face, ev in cap.dvs.items():
        assert ev.dtype.names == ("x", "y", "t", "pol")
        l0 = log_intensity(cap.prev[face].rgb)
        l1 = log_intensity(cap.curr[face].rgb)
        has = np.zeros(l0.shape, bool)
        has[ev["y"], ev["x"]] = True
        # a pixel whose end-to-end change exceeds C must fire; the net polarity tracks the change
        assert np.all(has[np.abs(l1 - l0) >= c + 1e-9])
        net = np.zeros(l0.shape)
        np.add.at(net, (ev["y"], ev["x"]), np.where(ev["pol"], c, -c))
        assert np.all(np.abs((l1 - l0) - net) < c + 1e-9)
        if ev.size:
            assert times[0] <= ev["t"].min() and ev["t"].max() <= times[-1]
            assert np.all(np.diff(ev["t"]) >= 0)
        total += ev.size
    assert total > 0


def test_dvs_events_synthetic():
    # one pixel rising by 0.7 linearly, one falling by 0.35, one still; threshold 0.3
    logs = np.zeros((3, 1, 3))
    logs[1, 0, 0], logs[2, 0, 0] = 0.35, 0.7
    logs[2, 0, 1] = -0.35
    ev = dvs_events(logs, np.array([0, 50, 100]), 0.3)
    assert list(zip(ev["x"].tolist(), ev["pol"].tolist(), strict=True)) == [(0, True), (0, True), (1, False)]
    np.testing.assert_array_equal(ev["t"], [43, 86, 93])  # 0.3/0.35 of 50 ns, then 50 + 0.25/0.35, 50 + 0.3/0.35
    assert dvs_events(np.zeros((3, 2, 2)), np.array([0, 1, 2])).size == 0


def _assert_same_images(a, b, what: str) -> None:
    for key in ("rgb", "depth_m", "semantic", "actor_id"):
        x, y = np.asarray(getattr(a, key)), np.asarray(getattr(b, key))
        assert x.dtype == y.dtype and np.array_equal(x, y), f"{what}: {key} differs in {int((x != y).sum())} pixels"


def test_a_frames_t_minus_1_is_the_previous_frames_t_bit_for_bit(small_rig, small_config):
    """Frame k+1's poses at t-1 are frame k's at t (the same floats), so that its renders at t-1
    are the previous frame's at t, bit for bit, and ``prev=`` (the kept renders) changes nothing."""
    k0, k1 = (generate_street(0, frame=k, rig=small_rig) for k in (2, 3))
    for field in ("object_location", "object_yaw_deg"):
        assert np.array_equal(np.asarray(getattr(k0.scene, field)[1]), np.asarray(getattr(k1.scene, field)[0])), field
    for a0, a1 in zip(k0.actors, k1.actors, strict=True):
        assert (a1.location_prev, a1.rotation_prev) == (a0.location, a0.rotation)
    calib = small_rig["MVL"]
    c0, c1 = simulate_camera(k0, calib, small_config), simulate_camera(k1, calib, small_config)
    kept = simulate_camera(k1, calib, small_config, prev=c0.curr)
    for face in small_config.faces:
        _assert_same_images(c0.curr[face], c1.prev[face], f"{face} at t of frame 2 and t-1 of frame 3")
        _assert_same_images(kept.prev[face], c1.prev[face], f"{face} at t-1, kept")
        _assert_same_images(kept.curr[face], c1.curr[face], f"{face} at t, with the kept t-1")
        assert np.array_equal(kept.dvs[face], c1.dvs[face])
    bev, mount = bev_camera(small_config), sensor_mounts(small_rig, small_config).bev_camera_to_vehicle
    v0, v1 = simulate_view(k0, bev, mount, small_config), simulate_view(k1, bev, mount, small_config)
    _assert_same_images(v0[1], v1[0], "BEV at t of frame 2 and t-1 of frame 3")
    again = simulate_view(k1, bev, mount, small_config, prev=v0[1])
    _assert_same_images(again[1], v1[1], "BEV at t, with the kept t-1")
    assert again[0] is v0[1] and np.array_equal(again[2], v1[2])


def test_generator_is_deterministic_and_seeded():
    a, b, c = generate_street(3), generate_street(3), generate_street(4)
    for field in ("box_center", "capsule_center", "object_location"):
        np.testing.assert_array_equal(np.asarray(getattr(a.scene, field)), np.asarray(getattr(b.scene, field)))
    assert not np.array_equal(np.asarray(a.scene.box_center), np.asarray(c.scene.box_center))
    assert a.actors == b.actors


def test_actors_and_motion_are_plausible(street):
    ids = [a.id for a in street.actors]
    assert len(set(ids)) == len(ids) and street.actors[0].category == "ego"
    cats = {a.category for a in street.actors}
    assert cats == {"ego", "four_wheeler", "two_wheeler", "pedestrian"}
    speeds = np.array([a.displacement_m / street.dt_s for a in street.actors])
    assert np.any(speeds == 0.0) and np.all(speeds < 20.0)
    for a in street.actors:
        v = np.linalg.norm(a.velocity)
        assert abs(v - a.displacement_m / street.dt_s) < 0.05 * max(v, 1.0)
        assert all(e > 0 for e in a.bbox_extent)
    # consecutive frames chain: frame k's t is frame k + 1's t-1
    nxt = generate_street(0, frame=1, rig=None)
    first = generate_street(0, frame=0, rig=None)
    for a0, a1 in zip(first.actors, nxt.actors, strict=True):
        np.testing.assert_allclose(a0.location, a1.location_prev)


def test_lidar_ground_points_lie_on_the_ground(street, small_rig, small_config):
    mounts = sensor_mounts(small_rig, small_config)
    lidar, sem = simulate_lidar(street, mounts.lidar_location, small_config)
    assert lidar.dtype == np.float32 and lidar.shape[1] == 4 and lidar.shape[0] == sem.shape[0] > 100
    ground = np.isin(sem["ObjTag"], ROAD + (CARLA_SEMANTIC_TAGS["sidewalk"], CARLA_SEMANTIC_TAGS["terrain"]))
    assert ground.any()
    # the sensor is level (yaw only), so its local z + its height is the world z
    np.testing.assert_allclose(sem["z"][ground] + mounts.lidar_location[2], 0.0, atol=SCENE_ROAD_Z_M)
    dist = np.linalg.norm(lidar[:, :3], axis=-1)
    np.testing.assert_allclose(lidar[:, 3], np.exp(-0.004 * dist), rtol=1e-5)


def test_radar_static_points_close_at_the_ego_speed(street, small_rig, small_config):
    mounts = sensor_mounts(small_rig, small_config)
    det = simulate_radar(street, mounts.radar_location, small_config)
    assert det.size > 10
    # every detection: |radial velocity| <= relative speed; static ones (most) approach the ego
    speed = np.linalg.norm(street.ego_motion.velocity)
    assert np.all(np.abs(det["velocity"]) <= speed + 25.0)
    expected = -speed * np.cos(det["azimuth"]) * np.cos(det["altitude"])
    assert np.mean(np.abs(det["velocity"] - expected) < 0.3) > 0.5


def test_imu_and_gnss():
    f = generate_street(0)
    imu = simulate_imu(f)
    assert abs(imu["accelerometer"][2] - 9.81) < 1e-9 and abs(imu["accelerometer"][0]) < 1.0
    np.testing.assert_allclose(imu["compass"], (math.radians(f.ego.rotation[1]) + math.pi / 2) % (2 * math.pi), atol=1e-9)
    lat, lon, alt = location_to_geo((0.0, 0.0, 0.0))
    assert abs(lat) < 1e-12 and abs(lon) < 1e-12 and alt == 0.0
    lat, lon, _ = location_to_geo((2 * math.pi * 6378137.0 / 360.0, 0.0, 0.0))
    assert lon == pytest.approx(1.0) and abs(lat) < 1e-9
    lat, _, _ = location_to_geo((0.0, -1000.0, 5.0))  # -y is north
    assert lat > 0
    assert simulate_gnss(f)["altitude"] == f.ego.location[2]


def test_invalid_inputs_are_rejected(street):
    import equinox as eqx

    from jaxfish.scene import CaptureConfig, Scene

    with pytest.raises(ValueError, match="frame"):
        generate_street(0, frame=-1)
    with pytest.raises(ValueError, match="dt_s"):
        generate_street(0, dt_s=0.0)
    with pytest.raises(ValueError, match="face_size"):
        CaptureConfig(face_size=0)
    with pytest.raises(ValueError, match="dvs_threshold"):
        CaptureConfig(dvs_threshold=0.0)
    fields = {f: getattr(street.scene, f) for f in street.scene.__dataclass_fields__}
    fields["box_tag"] = fields["box_tag"][:-1]
    with pytest.raises(ValueError, match="box fields disagree"):
        Scene(**fields)
    # a scene passes through jit and pytree surgery untouched
    moved = eqx.tree_at(lambda s: s.object_location, street.scene, street.scene.object_location + 1.0)
    assert moved.num_objects == street.scene.num_objects


def test_ego_body_keeps_every_camera_outside():
    import jaxfish as jf
    from jaxfish.scene import ego_body_boxes
    from jaxfish.transforms import Pose

    rig = dict(jf.default_rig())
    roof = rig["FV"].camera_to_vehicle
    rig["ROOF"] = jf.Calibration("ROOF", rig["FV"].camera, Pose(roof.rotation_matrix, np.array([1.2, 0.0, 1.3])))
    for r in (jf.default_rig(), rig):
        boxes = ego_body_boxes(r)
        assert boxes
        t = np.stack([np.asarray(c.camera_to_vehicle.translation) * np.array([1.0, -1.0, 1.0]) for c in r.values()])
        for c, h in boxes:
            assert not np.any(np.all(np.abs(t - np.asarray(c)) < np.asarray(h), axis=-1))
