"""The CARLA capture program's pure parts, driven by fake carla objects (no server, no ``carla``)."""

from __future__ import annotations

import dataclasses
import json
from types import SimpleNamespace

import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish as jf
from jaxfish.cameras import Orthographic
from jaxfish.carla import (
    CarlaCaptureError,
    CarlaImages,
    bev_pinhole,
    camera_attributes,
    camera_mount,
    capture_sensor_specs,
    carla_actor_records,
    carla_angles_from_matrix,
    carla_ego_motion,
    carla_frame_records,
    carla_frame_sensors,
    carla_semantic_tags,
    carla_street_frame,
    cube_face_mounts,
    dvs_to_events,
    finish_carla_header,
    gnss_to_dict,
    height_from_depth,
    image_to_bgra,
    imu_to_dict,
    lidar_attributes,
    lidar_to_points,
    parse_carla_version,
    radar_to_records,
    rear_axle_origin,
    rig_on_actor,
    semantic_lidar_to_records,
    sensor_carla_mounts,
    set_blueprint_attributes,
    validate_weather,
    with_bev_altitude,
    write_carla_frame,
)
from jaxfish.dataset import synthesize_capture
from jaxfish.io import (
    DVS_EVENT_DTYPE,
    CaptureReader,
    decode_depth,
    decode_instance,
    decode_semantic,
    encode_depth,
    encode_instance,
    encode_semantic,
    read_image,
    write_capture_header,
)
from jaxfish.reprojection import CUBE_FACE_ROTATIONS, FIVE_FACES, CubeRig
from jaxfish.scene import (
    RADAR_DTYPE,
    SEMANTIC_LIDAR_DTYPE,
    CaptureConfig,
    bev_camera,
    front_camera,
    sensor_mounts,
)
from jaxfish.transforms import Pose, carla_camera_pose_to_opencv, carla_rotation_matrix
from tests.helpers import describe_differences, tree_bytes
from tests.tolerances import CARLA_HEIGHT_FROM_DEPTH_M, POSE_F64

# The sizes of tests/io/test_capture.py's capture: the embedded scene's compiled renderers are shared.
SMALL = CaptureConfig(face_size=32, bev_size=32, front_width=32, front_height=24, lidar_channels=4,
                      lidar_points_per_channel=64, radar_points=32, dvs_substeps=2)


def _image(bgra: np.ndarray) -> SimpleNamespace:
    """A fake ``carla.Image``."""
    return SimpleNamespace(raw_data=memoryview(np.ascontiguousarray(bgra).tobytes()), width=bgra.shape[1],
                           height=bgra.shape[0], frame=1)


def _vec(v) -> SimpleNamespace:
    return SimpleNamespace(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _transform(d) -> SimpleNamespace:
    p, y, r = d["rotation"]
    return SimpleNamespace(location=_vec(d["location"]), rotation=SimpleNamespace(pitch=p, yaw=y, roll=r))


def _matrix(rotation) -> np.ndarray:
    return np.asarray(carla_rotation_matrix(*rotation, dtype=jnp.float64))


# ---------------------------------------------------------------------------- mounts
def test_cube_face_mounts_are_the_embedded_scene_faces():
    rig = jf.default_rig()
    mounts = cube_face_mounts(rig)
    cube = CubeRig(8, dtype=jnp.float64)
    for name, calib in rig.items():
        # The embedded scene renders face `f` of a camera with `camera_to_vehicle @ CubeRig.face_pose(f)`.
        mount = Pose(calib.camera_to_vehicle.rotation_matrix, calib.camera_to_vehicle.translation, dtype=jnp.float64)
        fisheye = camera_mount(mount)
        for face in FIVE_FACES:
            ref = mount @ cube.face_pose(face)
            got = carla_camera_pose_to_opencv(mounts[name][face].pose())
            np.testing.assert_allclose(got.rotation_matrix, ref.rotation_matrix, atol=POSE_F64)
            np.testing.assert_allclose(got.translation, ref.translation, atol=POSE_F64)
            # And it is the fisheye's own CARLA transform rotated by the face's relative CARLA rotation.
            np.testing.assert_allclose(_matrix(mounts[name][face].rotation),
                                       _matrix(fisheye.rotation) @ _matrix(CUBE_FACE_ROTATIONS[face]), atol=POSE_F64)
            np.testing.assert_allclose(mounts[name][face].location, np.asarray(calib.camera_to_vehicle.translation)
                                       * [1.0, -1.0, 1.0], atol=POSE_F64)
    # FV (22 degrees down, looking forward): its front face is pitched -22, level, at y = 0.
    np.testing.assert_allclose(mounts["FV"]["front"].rotation, (-22.0, 0.0, 0.0), atol=1e-9)


def test_angles_at_gimbal_lock_and_other_sensor_mounts():
    for rot in [(90.0, 30.0, 0.0), (-90.0, -120.0, 0.0), (89.999, 10.0, 5.0), (12.0, 170.0, -179.0)]:
        back = carla_angles_from_matrix(_matrix(rot))
        np.testing.assert_allclose(_matrix(back), _matrix(rot), atol=1e-9)
    rig = jf.default_rig()
    mounts = sensor_mounts(rig, SMALL)
    ours = sensor_carla_mounts(mounts)
    theirs = mounts.carla_transforms()  # what the embedded capture writes to sensors.json
    for name in ("bev", "front", "lidar", "radar", "imu", "gnss"):
        np.testing.assert_allclose(ours[name].location, theirs[name]["location"], atol=POSE_F64)
        np.testing.assert_allclose(_matrix(ours[name].rotation), _matrix(theirs[name]["rotation"]), atol=1e-9)
    for name in ("bev", "front"):  # the camera poses are the embedded scene's
        pose = getattr(mounts, f"{name}_camera_to_vehicle")
        np.testing.assert_allclose(carla_camera_pose_to_opencv(ours[name].pose()).rotation_matrix,
                                   pose.rotation_matrix, atol=POSE_F64)
    raised = sensor_carla_mounts(with_bev_altitude(mounts, bev_altitude_m=400.0))
    assert raised["bev"].location[2] == 400.0 and raised["bev"].rotation == ours["bev"].rotation


def test_bev_pinhole_puts_ground_points_where_the_orthographic_bev_does():
    config = CaptureConfig(bev_size=64, bev_metres_per_pixel=0.1)
    ref = bev_camera(config)  # the embedded BEV camera, rebuilt in float64
    ortho = Orthographic(config.bev_metres_per_pixel, width=ref.width, height=ref.height, dtype=jnp.float64)
    pin = bev_pinhole(config, 300.0)
    pose = with_bev_altitude(sensor_mounts(None, config), bev_altitude_m=300.0).bev_camera_to_vehicle
    rng = np.random.default_rng(0)
    ground = np.concatenate([rng.uniform(-3.0, 3.0, (50, 2)), np.zeros((50, 1))], axis=-1)  # ISO, z = 0
    p_cam = pose.inverse().apply(jnp.asarray(ground))
    uv_pin, ok = pin.project(p_cam)
    uv_ortho, _ = ortho.project(p_cam)
    assert bool(np.all(ok))
    np.testing.assert_allclose(uv_pin, uv_ortho, atol=1e-9)


def test_rear_axle_origin_and_rig_on_actor():
    # Ego at (10, 20, 0.5) yawed 30 degrees; wheels at actor x = +1.4 (front) and -1.3 (rear), y = +-0.8.
    loc, rot = (10.0, 20.0, 0.5), (0.0, 30.0, 0.0)
    r = _matrix(rot)
    local = np.array([[1.4, -0.8, 0.3], [1.4, 0.8, 0.3], [-1.3, -0.8, 0.3], [-1.3, 0.8, 0.3]])
    world_cm = (local @ r.T + loc) * 100.0
    origin = rear_axle_origin([_vec(w) for w in world_cm], (loc, rot))
    np.testing.assert_allclose(origin, (-1.3, 0.0, 0.0), atol=1e-9)
    rig = jf.default_rig()
    moved = rig_on_actor(rig, origin)
    for name in rig:
        np.testing.assert_allclose(np.asarray(moved[name].camera_to_vehicle.translation)
                                   - np.asarray(rig[name].camera_to_vehicle.translation), [-1.3, 0.0, 0.0], atol=1e-6)
        np.testing.assert_array_equal(moved[name].camera_to_vehicle.rotation_matrix,
                                      rig[name].camera_to_vehicle.rotation_matrix)


# ---------------------------------------------------------------------------- attributes and specs
def test_blueprint_attributes_fix_exposure_and_skip_missing_ones():
    rgb = camera_attributes("rgb", 32, 32)
    assert rgb["exposure_mode"] == "manual" and rgb["fov"] == "90.0" and rgb["motion_blur_intensity"] == "0.0"
    assert rgb["image_size_x"] == "32" and rgb["sensor_tick"] == "0.0"
    assert "exposure_mode" not in camera_attributes("depth", 32, 32)
    dvs = camera_attributes("dvs", 32, 32, config=SMALL)
    assert dvs["positive_threshold"] == dvs["negative_threshold"] == "0.3" and dvs["exposure_mode"] == "manual"
    lidar = lidar_attributes(SMALL, dt_s=0.1)
    assert lidar["points_per_second"] == str(4 * 64 * 10) and lidar["rotation_frequency"] == "10.0"
    with pytest.raises(CarlaCaptureError, match="kind"):
        camera_attributes("thermal", 32, 32)

    class Blueprint:
        def __init__(self, names):
            self.values = dict.fromkeys(names)

        def has_attribute(self, key):
            return key in self.values

        def set_attribute(self, key, value):
            assert isinstance(value, str)
            self.values[key] = value

    bp = Blueprint([k for k in rgb if k not in ("lens_flare_intensity", "exposure_compensation")])
    assert set_blueprint_attributes(bp, rgb) == ("exposure_compensation", "lens_flare_intensity")
    assert bp.values["exposure_mode"] == "manual"
    rig = {k: v for k, v in jf.default_rig().items() if k in ("FV", "RV")}
    mounts = sensor_mounts(rig, SMALL)
    old = capture_sensor_specs(rig, SMALL, mounts, carla_version="0.9.13")
    new = capture_sensor_specs(rig, SMALL, mounts, carla_version="0.9.15")
    assert len(old) == 2 * 5 * 4 + 2 * 3 + 5 and len(new) == 2 * 5 * 5 + 2 * 4 + 5
    keys = {s.key for s in new}
    assert ("camera", "RV", "top", "instance") in keys and ("view", "bev", "depth") in keys and ("gnss",) in keys
    assert len(keys) == len(new)


def test_versions_and_weather_presets():
    assert carla_semantic_tags("0.9.10") == carla_semantic_tags("0.9.13") == "0.9.10"
    assert carla_semantic_tags("0.9.14") == carla_semantic_tags("0.9.16-12-gabc") == "0.9.14"
    assert parse_carla_version("0.9.15.2") == (0, 9, 15)
    for bad in ("0.9.9", "0.10.0", "latest"):
        with pytest.raises(CarlaCaptureError, match="version"):
            parse_carla_version(bad)
    assert validate_weather(["ClearNoon", "WetSunset", "ClearNoon"]) == ("ClearNoon", "WetSunset")
    with pytest.raises(CarlaCaptureError, match="did you mean 'ClearNoon'"):
        validate_weather(["ClearNon"])
    with pytest.raises(CarlaCaptureError, match="no weather"):
        validate_weather([])
    old_carla = SimpleNamespace(WeatherParameters=SimpleNamespace(ClearNoon=object()))
    assert validate_weather(["ClearNoon"], carla=old_carla) == ("ClearNoon",)
    with pytest.raises(CarlaCaptureError, match="ClearNight"):
        validate_weather(["ClearNight"], carla=old_carla)


# ---------------------------------------------------------------------------- sensor data
def test_image_buffers_round_trip_with_the_carla_codecs():
    rng = np.random.default_rng(1)
    depth = rng.uniform(0.5, 999.0, (6, 5))
    tags = rng.integers(0, 23, (6, 5))
    ids = rng.integers(0, 65536, (6, 5))
    enc = encode_depth(depth)
    np.testing.assert_array_equal(image_to_bgra(_image(enc)), enc)
    np.testing.assert_array_equal(decode_depth(image_to_bgra(_image(enc))), decode_depth(enc))
    np.testing.assert_array_equal(decode_semantic(image_to_bgra(_image(encode_semantic(tags)))), tags)
    t, i = decode_instance(image_to_bgra(_image(encode_instance(tags, ids))))
    np.testing.assert_array_equal(t, tags)
    np.testing.assert_array_equal(i, ids)
    bad = SimpleNamespace(raw_data=bytes(6 * 5 * 4 - 1), width=5, height=6)
    with pytest.raises(CarlaCaptureError, match="FV/front/rgb.*5x6"):
        image_to_bgra(bad, "FV/front/rgb")


def test_dvs_and_point_buffers():
    ev = np.zeros(6, DVS_EVENT_DTYPE)
    ev["x"], ev["y"] = [1, 2, 3, 4, 0, 1], [0, 1, 2, 3, 4, 0]
    ev["t"] = [100, 100, 150, 150, 150, 200]
    ev["pol"] = [True, False, True, True, False, False]
    out = dvs_to_events(SimpleNamespace(raw_data=ev.tobytes(), width=5, height=5))
    assert out.dtype == DVS_EVENT_DTYPE and out.dtype.itemsize == 13
    np.testing.assert_array_equal(out, ev)  # sorted input: order kept, ties included
    shuffled = ev[[5, 2, 0, 3, 1, 4]]
    np.testing.assert_array_equal(dvs_to_events(shuffled.tobytes())["t"], np.sort(ev["t"]))
    np.testing.assert_array_equal(dvs_to_events(shuffled.tobytes())[2:5], shuffled[[1, 3, 5]])  # stable
    assert dvs_to_events(b"").shape == (0,)
    with pytest.raises(CarlaCaptureError, match="13-byte"):
        dvs_to_events(b"\0" * 14)
    with pytest.raises(CarlaCaptureError, match="outside"):
        dvs_to_events(SimpleNamespace(raw_data=ev.tobytes(), width=4, height=5))
    pts = np.arange(12, dtype=np.float32).reshape(3, 4)
    np.testing.assert_array_equal(lidar_to_points(SimpleNamespace(raw_data=pts.tobytes())), pts)
    sem = np.zeros(3, SEMANTIC_LIDAR_DTYPE)
    sem["x"], sem["ObjIdx"], sem["ObjTag"] = [1.0, 2.0, 3.0], [0, 7, 9], [7, 10, 4]
    np.testing.assert_array_equal(semantic_lidar_to_records(SimpleNamespace(raw_data=sem.tobytes())), sem)
    radar = np.zeros(2, RADAR_DTYPE)
    radar["velocity"], radar["depth"] = [-3.0, 1.5], [10.0, 20.0]
    np.testing.assert_array_equal(radar_to_records(radar.tobytes()), radar)
    for fn, n in ((lidar_to_points, 17), (semantic_lidar_to_records, 25), (radar_to_records, 15)):
        with pytest.raises(CarlaCaptureError, match="whole number"):
            fn(b"\0" * n)


# ---------------------------------------------------------------------------- a whole frame
@pytest.fixture(scope="module")
def embedded(tmp_path_factory):
    rig = {"FV": jf.default_rig()["FV"].resize(96, 72).astype(jnp.float32)}
    root = tmp_path_factory.mktemp("embedded")
    synthesize_capture(root, rig, frames=1, seed=3, config=SMALL)
    return root, rig


def _fake_world(root, frame):
    """Fake CARLA actors and world snapshots at t-1 and t rebuilt from an embedded capture's JSON."""
    reader = CaptureReader(root)
    actors, ego = reader.actors(frame), reader.ego(frame)
    fake_actors, snaps = [], ({}, {})
    for a in actors:
        wheels = "2" if a["category"] == "two_wheeler" else "4"
        fake_actors.append(SimpleNamespace(
            id=a["id"], type_id=a["type_id"], attributes={"number_of_wheels": wheels}, semantic_tags=[a["semantic_tag"]],
            bounding_box=SimpleNamespace(location=_vec(a["bounding_box"]["location"]),
                                         extent=_vec(a["bounding_box"]["extent"]))))
        accel = ego["acceleration"] if a["is_ego"] else (0.0, 0.0, 0.0)
        for snap, key in zip(snaps, ("transform_prev", "transform"), strict=True):
            snap[a["id"]] = SimpleNamespace(get_transform=lambda t=_transform(a[key]): t,
                                            get_velocity=lambda v=_vec(a["velocity"]): v,
                                            get_angular_velocity=lambda v=_vec(a["angular_velocity"]): v,
                                            get_acceleration=lambda v=_vec(accel): v)
    world = [SimpleNamespace(find=s.get) for s in snaps]
    return reader, fake_actors[::-1], world, ego  # reversed: the records put the ego first themselves


def _carla_inputs(root):
    """The CARLA path's inputs for frame 0 of an embedded capture: fake actors and snapshots through
    `carla_actor_records`, the raw BGRA images, DVS events, height maps and readings of its files."""
    reader, fake_actors, (snap_prev, snap), ego = _fake_world(root, 0)
    records = carla_actor_records(fake_actors, snap_prev, snap, ego_id=ego["id"], tag_table="0.9.10")
    frame = carla_street_frame(0, ego["timestamp_s"], records, carla_ego_motion(snap.find(ego["id"])),
                               dt_s=reader.meta["dt_s"], seed=3)
    d = root / "frames" / "000000"

    def raw(directory, instant):
        return CarlaImages(*(image_to_bgra(_image(read_image(directory / f"{k}_{instant}.png")))
                             for k in ("rgb", "depth", "semantic", "instance")))

    faces = {"FV": {f: (raw(d / "cameras" / "FV" / f, "prev"), raw(d / "cameras" / "FV" / f, "curr"),
                        dvs_to_events(reader.dvs(0, "FV", f).tobytes()))
                    for f in SMALL.faces}}
    views = {v: (raw(d / v, "prev"), raw(d / v, "curr"), read_image(d / v / "height_curr.exr")[..., 0])
             for v in ("bev", "front")}
    imu, gnss = reader.imu(0), reader.gnss(0)
    fake_imu = SimpleNamespace(accelerometer=_vec(imu["accelerometer"]), gyroscope=_vec(imu["gyroscope"]),
                               compass=imu["compass"], timestamp=imu["timestamp_s"])
    fake_gnss = SimpleNamespace(timestamp=gnss["timestamp_s"], **{k: gnss[k] for k in ("latitude", "longitude", "altitude")})
    sensors = {"lidar": lidar_to_points(reader.lidar(0).tobytes()),
               "semantic_lidar": semantic_lidar_to_records(reader.semantic_lidar(0).tobytes()),
               "radar": radar_to_records(reader.radar(0).tobytes()), "imu": imu_to_dict(fake_imu),
               "gnss": gnss_to_dict(fake_gnss)}
    return reader, frame, faces, views, sensors, (fake_imu, fake_gnss)


def test_embedded_frame_through_the_carla_path_is_byte_identical(embedded, tmp_path):
    root, rig = embedded
    reader, frame, faces, views, sensors, (fake_imu, fake_gnss) = _carla_inputs(root)
    out = tmp_path / "carla"
    mounts = sensor_mounts(rig, SMALL)
    write_capture_header(out, rig, SMALL, mounts, seed=3)
    write_carla_frame(out, frame, faces=faces, views=views, **sensors)
    files = sorted(p.relative_to(root) for p in root.rglob("*") if p.is_file())
    extra = out / "frames" / "000000" / "carla_frame.json"  # the CARLA path's one extra file
    assert json.loads(extra.read_text()) == {"dvs_missing": []}
    assert files == sorted(p.relative_to(out) for p in out.rglob("*") if p.is_file() and p != extra)
    # EXR headers may carry the write time: the height maps are compared by value.
    different = [str(f) for f in files if f.suffix != ".exr" and (root / f).read_bytes() != (out / f).read_bytes()]
    assert not different, different
    for f in (f for f in files if f.suffix == ".exr"):
        np.testing.assert_array_equal(read_image(out / f), read_image(root / f))
    # CARLA 0.9.10-0.9.13 have no instance camera: the tag and actor id 0 are written instead.
    finish_carla_header(out, carla_version="0.9.12", mounts=sensor_carla_mounts(mounts), bev_altitude_m=500.0,
                        config=SMALL, geo={"latitude": 1.0, "longitude": 2.0, "altitude": 3.0}, extra={"town": "T"})
    old = faces["FV"]["top"][1]
    write_carla_frame(out, dataclasses.replace(frame, frame=1),
                      faces={"FV": {f: (faces["FV"][f][0], CarlaImages(old.rgb, old.depth, old.semantic),
                                        faces["FV"][f][2]) for f in SMALL.faces}},
                      views=views, lidar=np.zeros((0, 4), np.float32), semantic_lidar=np.zeros(0, SEMANTIC_LIDAR_DTYPE),
                      radar=np.zeros(0, RADAR_DTYPE), imu=imu_to_dict(fake_imu), gnss=gnss_to_dict(fake_gnss))
    back = CaptureReader(out)
    assert back.frames == [0, 1] and back.meta["carla_semantic_tags"] == "0.9.10" and back.meta["instance_ids"] is False
    assert back.meta["town"] == "T" and back.sensors()["gnss"]["geo_reference"]["longitude"] == 2.0
    img = back.face(1, "FV", "left")
    np.testing.assert_array_equal(img.semantic, decode_semantic(old.semantic))
    assert not img.actor_id.any()
    assert back.sensors()["bev"]["carla_camera"]["altitude_m"] == 500.0


def test_a_frame_assembled_in_memory_is_what_the_reader_decodes_from_the_written_frame(embedded, tmp_path):
    root, rig = embedded
    _, frame, faces, views, sensors, _ = _carla_inputs(root)
    out = tmp_path / "carla"
    write_capture_header(out, rig, SMALL, sensor_mounts(rig, SMALL), seed=3, source="carla")
    write_carla_frame(out, frame, faces=faces, views=views, **sensors)
    back = CaptureReader(out)
    actors, ego = carla_frame_records(frame)
    assert actors == back.actors(0) and ego == back.ego(0)
    assert all(type(v) is list for v in (ego["velocity"], actors[1]["transform"]["location"]))  # JSON types
    got = carla_frame_sensors(frame, **sensors)
    for name in ("lidar", "semantic_lidar", "radar"):
        want = getattr(back, name)(0)
        assert got[name].dtype == want.dtype
        np.testing.assert_array_equal(got[name], want)
    assert got["imu"] == back.imu(0) and got["gnss"] == back.gnss(0)
    for face, (prev, curr, _) in faces["FV"].items():
        for instant, images in (("prev", prev), ("curr", curr)):
            mine, theirs = images.decoded(f"FV/{face}", instant, actor_ids=True), back.face(0, "FV", face, instant)
            for k in ("rgb", "depth_m", "semantic", "actor_id"):
                assert getattr(mine, k).dtype == getattr(theirs, k).dtype, k
                np.testing.assert_array_equal(getattr(mine, k), getattr(theirs, k))
    mine = views["bev"][1].decoded("bev", "curr")
    assert mine.actor_id is None
    np.testing.assert_array_equal(mine.depth_m, back.view(0, "bev").depth_m)
    # Without an instance camera (CARLA < 0.9.14) the ids read back are 0, as the writer fills them in.
    old = CarlaImages(curr.rgb, curr.depth, curr.semantic).decoded("FV/top", "curr", actor_ids=True)
    assert old.actor_id.dtype == np.int32 and not old.actor_id.any()
    with pytest.raises(CarlaCaptureError, match=r"FV/top: depth_prev is \(3, 32, 4\)"):
        CarlaImages(curr.rgb, curr.depth[:3], curr.semantic).decoded("FV/top", "prev")
    bad = dict(sensors, lidar=np.full((2, 4), np.nan, np.float32))
    with pytest.raises(CarlaCaptureError, match="frame 0: lidar: 8 value"):
        carla_frame_sensors(frame, **bad)
    with pytest.raises(CarlaCaptureError, match="frame 0 imu.json"):
        carla_frame_sensors(frame, **dict(sensors, imu={"compass": float("nan")}))


def test_front_height_map_from_depth_matches_the_scene(embedded):
    root, rig = embedded
    reader = CaptureReader(root)
    ego = reader.ego(0)["transform"]
    depth = reader.view(0, "front").depth_m
    mounts = sensor_mounts(reader.rig(), SMALL)
    # The embedded scene's ego is level on flat ground: vehicle z and world z (its height writer) agree.
    assert abs(ego["rotation"][0]) < 1e-6 and abs(ego["rotation"][2]) < 1e-6
    got = height_from_depth(depth, front_camera(SMALL), mounts.front_camera_to_vehicle)
    np.testing.assert_allclose(got, reader.height(0, "front"), atol=CARLA_HEIGHT_FROM_DEPTH_M)
    with pytest.raises(CarlaCaptureError, match="does not match"):
        height_from_depth(depth[:-1], front_camera(SMALL), mounts.front_camera_to_vehicle)


def test_height_is_vehicle_frame_z_when_the_ego_pitches():
    # The ego pitched 6 degrees nose-up on flat ground (its origin on the ground): the world ground
    # plane is n . p = 0 in the vehicle frame. Height = vehicle-frame z (as jaxfish.bev.height_map),
    # not world z minus the ego's z (which is 0 on all of that ground).
    cam = front_camera(SMALL)
    pose = sensor_mounts(jf.default_rig(), SMALL).front_camera_to_vehicle
    th = np.deg2rad(6.0)
    n = np.array([np.sin(th), 0.0, np.cos(th)])  # world up in the pitched vehicle frame
    fx, fy, cx, cy = (float(getattr(cam, k)) for k in ("fx", "fy", "cx", "cy"))
    v, u = np.mgrid[0:cam.height, 0:cam.width].astype(np.float64)
    ray = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], -1) @ np.asarray(pose.rotation_matrix, np.float64).T
    t = np.asarray(pose.translation, np.float64)
    s = -(n @ t) / (ray @ n)  # planar depth where each pixel's ray meets the ground
    hits = (s > 0) & (s < 500.0)
    depth = np.where(hits, s, 1000.0)
    want = np.where(hits, (t + s[..., None] * ray)[..., 2], 0.0)
    got = height_from_depth(depth.astype(np.float32), cam, pose)
    assert hits.sum() > 0.3 * hits.size and np.abs(want[hits]).max() > 0.2  # the pitch shows
    np.testing.assert_allclose(got, want, atol=CARLA_HEIGHT_FROM_DEPTH_M)


def test_frame_assembly_rejects_bad_inputs(embedded, tmp_path):
    root, rig = embedded
    reader, fake_actors, (snap_prev, snap), ego = _fake_world(root, 0)
    with pytest.raises(CarlaCaptureError, match="actor 999"):
        carla_actor_records(fake_actors, snap_prev, snap, ego_id=999, tag_table="0.9.10")
    records = carla_actor_records(fake_actors, snap_prev, snap, ego_id=ego["id"], tag_table="0.9.14")
    assert records[0].category == "ego" and [r.id for r in records[1:]] == sorted(r.id for r in records[1:])
    with pytest.raises(CarlaCaptureError, match="first actor"):
        carla_street_frame(0, 1.0, records[1:], carla_ego_motion(snap.find(ego["id"])))
    frame = carla_street_frame(0, 1.0, records, carla_ego_motion(snap.find(ego["id"])))
    img = np.zeros((4, 4, 4), np.uint8)
    ok = CarlaImages(img, img, img)
    write_capture_header(tmp_path, rig, SMALL, sensor_mounts(rig, SMALL), seed=0, source="carla")
    with pytest.raises(CarlaCaptureError, match="FV/front: depth_curr"):
        write_carla_frame(tmp_path, frame, faces={"FV": {"front": (ok, CarlaImages(img, img[:3], img),
                                                                   np.zeros(0, DVS_EVENT_DTYPE))}},
                          views={}, lidar=np.zeros((0, 4)), semantic_lidar=np.zeros(0, SEMANTIC_LIDAR_DTYPE),
                          radar=np.zeros(0, RADAR_DTYPE), imu={}, gnss={})
    with pytest.raises(CarlaCaptureError, match="DVS_EVENT_DTYPE"):
        write_carla_frame(tmp_path, frame, faces={"FV": {"front": (ok, ok, np.zeros(3))}}, views={},
                          lidar=np.zeros((0, 4)), semantic_lidar=np.zeros(0, SEMANTIC_LIDAR_DTYPE),
                          radar=np.zeros(0, RADAR_DTYPE), imu={}, gnss={})
    with pytest.raises(CarlaCaptureError, match=r"dvs_missing names faces \['FV/nope'\]"):
        write_carla_frame(tmp_path, frame, faces={"FV": {"front": (ok, ok, np.zeros(0, DVS_EVENT_DTYPE))}}, views={},
                          lidar=np.zeros((0, 4)), semantic_lidar=np.zeros(0, SEMANTIC_LIDAR_DTYPE),
                          radar=np.zeros(0, RADAR_DTYPE), imu={}, gnss={}, dvs_missing=["FV/nope"])
    with pytest.raises(CarlaCaptureError, match=r"bev: height map \(3, 4\)"):  # a view after a good face
        write_carla_frame(tmp_path, frame, faces={"FV": {"front": (ok, ok, np.zeros(0, DVS_EVENT_DTYPE))}},
                          views={"bev": (ok, ok, np.zeros((3, 4)))}, lidar=np.zeros((0, 4)),
                          semantic_lidar=np.zeros(0, SEMANTIC_LIDAR_DTYPE), radar=np.zeros(0, RADAR_DTYPE), imu={},
                          gnss={})
    assert json.loads((tmp_path / "capture.json").read_text())["frames"] == []  # nothing listed
    assert not (tmp_path / "frames" / "000000").exists()  # and nothing written: inputs are checked first


# ---------------------------------------------------------------------------- the program, on a fake CARLA
class _FakeCarla:
    """Just enough of the ``carla`` module for `scripts/carla_capture.py`: a straight road where
    every vehicle drives along x at 5 m/s, sensors that return fixed images, points and readings."""

    def __init__(self, version: str = "0.9.13"):
        self.version = version
        self.WeatherParameters = SimpleNamespace(ClearNoon="clear-noon", WetSunset="wet-sunset")
        self.command = SimpleNamespace(
            SpawnActor=lambda bp, transform, parent=None: _Command("spawn", bp=bp, transform=transform, parent=parent),
            SetAutopilot=lambda actor, on, port: _Command("autopilot"), FutureActor=object(),
            DestroyActor=lambda actor_id: _Command("destroy", actor_id=actor_id))
        self.world = _World(self)

    @staticmethod
    def Location(x=0.0, y=0.0, z=0.0):  # noqa: N802 - carla's names
        return SimpleNamespace(x=x, y=y, z=z)

    @staticmethod
    def Rotation(pitch=0.0, yaw=0.0, roll=0.0):  # noqa: N802
        return SimpleNamespace(pitch=pitch, yaw=yaw, roll=roll)

    def Transform(self, location=None, rotation=None):  # noqa: N802
        return SimpleNamespace(location=location or self.Location(), rotation=rotation or self.Rotation())

    def Client(self, host, port):  # noqa: N802
        carla = self

        class Client:
            def set_timeout(self, s):
                pass

            def get_server_version(self):
                return carla.version

            def get_client_version(self):
                return carla.version

            def get_world(self):
                return carla.world

            def load_world(self, town):
                carla.world.town = town

            def get_trafficmanager(self, port):
                return SimpleNamespace(set_synchronous_mode=lambda on: setattr(carla.world, "tm_sync", on))

            def apply_batch_sync(self, commands, do_tick=False):
                out = [carla.world.run(c) for c in commands]
                if do_tick:
                    carla.world.tick()
                return out

        return Client()


class _Command:
    def __init__(self, kind, **kw):
        self.kind, self.kw, self.next = kind, kw, None

    def then(self, command):
        self.next = command
        return self


class _Blueprint:
    def __init__(self, bp_id, attributes=()):
        self.id, self.values = bp_id, dict.fromkeys(attributes, "")

    def has_attribute(self, key):
        return key in self.values

    def set_attribute(self, key, value):
        self.values[key] = value

    def get_attribute(self, key):
        return SimpleNamespace(recommended_values=["0.0", "1.4", "3.0"])


class _Actor:
    def __init__(self, world, actor_id, bp, transform, parent=None):
        self.world, self.id, self.type_id, self.parent = world, actor_id, bp.id, parent
        self.attributes = {k: v for k, v in bp.values.items() if k == "number_of_wheels"}
        self.blueprint = bp
        self.location = [transform.location.x, transform.location.y, transform.location.z]
        self.yaw = transform.rotation.yaw
        self.speed = 5.0 if bp.id.startswith("vehicle.") else (1.0 if bp.id.startswith("walker.") else 0.0)
        self.semantic_tags = [10] if bp.id.startswith("vehicle.") else [4]
        self.bounding_box = SimpleNamespace(location=_vec((0.0, 0.0, 0.8)), extent=_vec((2.0, 0.9, 0.8)))
        self.callback = None

    # vehicles, walkers, controllers
    def set_autopilot(self, on, port):
        pass

    def get_transform(self):
        return _transform({"location": self.location, "rotation": (0.0, self.yaw, 0.0)})

    def get_physics_control(self):
        pts = [(1.4, -0.8), (1.4, 0.8), (-1.3, -0.8), (-1.3, 0.8)]
        return SimpleNamespace(wheels=[SimpleNamespace(position=_vec(((self.location[0] + x) * 100, (self.location[1] + y) * 100, 30.0)))
                                       for x, y in pts])

    def start(self):
        pass

    def go_to_location(self, loc):
        pass

    def set_max_speed(self, s):
        pass

    # sensors
    def listen(self, callback):
        self.callback = callback

    def stop(self):
        self.callback = None


class _World:
    def __init__(self, carla):
        self.carla, self.actors, self.next_id, self.frame, self.time = carla, {}, 100, 0, 0.0
        self.settings = SimpleNamespace(synchronous_mode=False, fixed_delta_seconds=None)
        self.weather, self.town, self.tm_sync = None, None, False
        names = ["image_size_x", "image_size_y", "fov", "sensor_tick", "exposure_mode", "shutter_speed", "iso",
                 "fstop", "motion_blur_intensity", "positive_threshold", "negative_threshold", "channels", "range",
                 "points_per_second", "rotation_frequency", "upper_fov", "lower_fov", "horizontal_fov", "vertical_fov",
                 "role_name", "speed", "is_invincible", "color"]  # no lens_flare_intensity etc.: an older release
        self.library = {b: _Blueprint(b, names) for b in
                        ["sensor.camera.rgb", "sensor.camera.depth", "sensor.camera.semantic_segmentation",
                         "sensor.camera.instance_segmentation", "sensor.camera.dvs", "sensor.lidar.ray_cast",
                         "sensor.lidar.ray_cast_semantic", "sensor.other.radar", "sensor.other.imu", "sensor.other.gnss",
                         "vehicle.lincoln.mkz_2017", "vehicle.audi.tt", "walker.pedestrian.0001", "controller.ai.walker"]}
        self.library["vehicle.bh.crossbike"] = _Blueprint("vehicle.bh.crossbike", names + ["number_of_wheels"])
        self.library["vehicle.bh.crossbike"].values["number_of_wheels"] = "2"

    # settings, map, blueprints
    def get_settings(self):
        return SimpleNamespace(**vars(self.settings))

    def apply_settings(self, s):
        self.settings = SimpleNamespace(**vars(s))

    def set_weather(self, w):
        self.weather = w

    def get_blueprint_library(self):
        lib = self.library

        def blueprints(pattern):
            import fnmatch

            return [_Blueprint(b.id, b.values) for k, b in sorted(lib.items()) if fnmatch.fnmatch(k, pattern)]

        return SimpleNamespace(filter=blueprints, find=lambda b: blueprints(b)[0])

    def get_map(self):
        carla = self.carla
        points = [carla.Transform(carla.Location(x=20.0 * i, y=3.5 * (i % 2), z=0.3)) for i in range(6)]
        return SimpleNamespace(name="Town10HD_Opt", get_spawn_points=lambda: list(points),
                               transform_to_geolocation=lambda loc: SimpleNamespace(latitude=0.5, longitude=1.5, altitude=2.0))

    def get_random_location_from_navigation(self):
        return self.carla.Location(x=5.0 + len(self.actors), y=8.0, z=1.0)

    # actors
    def _spawn(self, bp, transform, parent=None):
        self.next_id += 1
        actor = _Actor(self, self.next_id, bp, transform, parent)
        self.actors[actor.id] = actor
        return actor

    def try_spawn_actor(self, bp, transform):
        return self._spawn(bp, transform)

    def spawn_actor(self, bp, transform, attach_to=None):
        return self._spawn(bp, transform, attach_to)

    def run(self, command):
        if command.kind == "destroy":
            self.actors.pop(command.kw["actor_id"])
            return SimpleNamespace(actor_id=command.kw["actor_id"], error="")
        actor = self._spawn(command.kw["bp"], command.kw["transform"], command.kw["parent"])
        return SimpleNamespace(actor_id=actor.id, error="")

    def get_actor(self, actor_id):
        return self.actors[actor_id]

    def get_actors(self):
        import fnmatch

        actors = list(self.actors.values())
        return SimpleNamespace(filter=lambda pattern: [a for a in actors if fnmatch.fnmatch(a.type_id, pattern)])

    def get_snapshot(self):
        snaps = {}
        for a in self.actors.values():
            t = a.get_transform()
            v = _vec((a.speed, 0.0, 0.0))
            snaps[a.id] = SimpleNamespace(get_transform=lambda t=t: t, get_velocity=lambda v=v: v,
                                          get_angular_velocity=lambda: _vec((0.0, 0.0, 0.0)),
                                          get_acceleration=lambda: _vec((0.0, 0.0, 0.0)))
        return SimpleNamespace(find=snaps.get, timestamp=SimpleNamespace(elapsed_seconds=self.time))

    def tick(self):
        assert self.settings.synchronous_mode and self.settings.fixed_delta_seconds == 0.1
        self.frame += 1
        self.time = round(self.time + 0.1, 9)
        for a in self.actors.values():
            if a.parent is None:
                a.location[0] += a.speed * 0.1
        for a in list(self.actors.values()):
            if a.callback is not None:
                data = self.reading(a)
                if data is not None:
                    a.callback(data)
        return self.frame

    def reading(self, sensor):
        bp, frame = sensor.blueprint, self.frame
        base = {"frame": frame, "timestamp": self.time}
        if bp.id.startswith("sensor.camera."):
            w, h = int(bp.values["image_size_x"]), int(bp.values["image_size_y"])
            kind = bp.id.rsplit(".", 1)[1]
            if kind == "dvs":
                if frame % 2:
                    return None  # CARLA's DVS sends nothing when no pixel changed
                ev = np.zeros(3, DVS_EVENT_DTYPE)
                ev["x"], ev["y"], ev["t"], ev["pol"] = [0, 1, 2], [1, 1, 0], int(self.time * 1e9) - np.arange(3)[::-1], True
                return SimpleNamespace(raw_data=ev.tobytes(), width=w, height=h, **base)
            img = {"rgb": np.full((h, w, 4), [frame % 256, 20, 30, 255], np.uint8), "depth": encode_depth(np.full((h, w), 12.5)),
                   "semantic_segmentation": encode_semantic(np.full((h, w), 7)),
                   "instance_segmentation": encode_instance(np.full((h, w), 7), np.full((h, w), 5))}[kind]
            return SimpleNamespace(raw_data=img.tobytes(), width=w, height=h, **base)
        if bp.id == "sensor.lidar.ray_cast":
            return SimpleNamespace(raw_data=np.ones((5, 4), np.float32).tobytes(), **base)
        if bp.id == "sensor.lidar.ray_cast_semantic":
            return SimpleNamespace(raw_data=np.zeros(4, SEMANTIC_LIDAR_DTYPE).tobytes(), **base)
        if bp.id == "sensor.other.radar":
            return SimpleNamespace(raw_data=np.zeros(2, RADAR_DTYPE).tobytes(), **base)
        if bp.id == "sensor.other.imu":
            return SimpleNamespace(accelerometer=_vec((0.0, 0.0, 9.81)), gyroscope=_vec((0.0, 0.0, 0.0)), compass=0.5, **base)
        return SimpleNamespace(latitude=0.1, longitude=0.2, altitude=3.0, **base)


@pytest.fixture(scope="module")
def script():
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "scripts" / "carla_capture.py"
    spec = importlib.util.spec_from_file_location("carla_capture_script", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_program_on_a_fake_carla(script, tmp_path, monkeypatch, capsys):
    fake = _FakeCarla("0.9.13")
    monkeypatch.setattr(script, "import_carla", lambda: fake)
    calib = tmp_path / "calib"
    jf.save_rig({"FV": jf.default_rig()["FV"].resize(32, 24)}, calib)
    out = tmp_path / "out"
    argv = ["--out", str(out), "--frames", "2", "--warmup", "2", "--weather", "WetSunset", "--calibration", str(calib),
            "--face-size", "8", "--bev-size", "8", "--front-size", "8", "6", "--vehicles", "2", "--walkers", "1",
            "--town", "Town10HD"]
    assert script.main(argv) == 0
    reader = CaptureReader(out / "WetSunset")
    assert reader.frames == [0, 1] and reader.cameras == ["FV"] and reader.meta["source"] == "carla"
    assert reader.meta["carla_semantic_tags"] == "0.9.10" and reader.meta["instance_ids"] is False
    assert reader.meta["weather"] == "WetSunset" and fake.world.weather == "wet-sunset" and fake.world.town == "Town10HD"
    face = reader.face(1, "FV", "top", "prev")
    assert face.rgb.shape == (8, 8, 3) and (face.semantic == 7).all() and not face.actor_id.any()
    np.testing.assert_allclose(face.depth_m, 12.5, atol=1e-4)
    assert reader.face(1, "FV", "top", "curr").rgb[0, 0, 2] == reader.face(1, "FV", "top", "prev").rgb[0, 0, 2] + 1
    for sub in ("cameras/FV/right", "bev", "front"):  # frame 1's t-1 is frame 0's t: copied, not re-encoded
        for kind in ("rgb", "depth", "semantic", "instance"):
            a, b = (out / "WetSunset" / "frames" / f"{k:06d}" / sub / f"{kind}_{i}.png" for k, i in ((0, "curr"), (1, "prev")))
            assert a.read_bytes() == b.read_bytes()
    dvs = [reader.dvs(k, "FV", "left") for k in (0, 1)]
    assert sorted(d.size for d in dvs) == [0, 3] and all(d.dtype == DVS_EVENT_DTYPE for d in dvs)
    # The faces without a DVS reading (the fake's DVS sends nothing on odd ticks) are recorded per frame.
    missing = [json.loads((out / "WetSunset" / "frames" / f"{k:06d}" / "carla_frame.json").read_text())["dvs_missing"]
               for k in (0, 1)]
    for d, m in zip(dvs, missing, strict=True):
        assert m == ([] if d.size else sorted(f"FV/{f}" for f in FIVE_FACES))
    actors = reader.actors(1)
    assert actors[0]["is_ego"] and {a["category"] for a in actors[1:]} <= {"four_wheeler", "two_wheeler", "pedestrian"}
    assert len(actors) == 1 + 2 + 1  # ego, two vehicles, one walker: no sensors or controllers
    ego = reader.ego(1)
    assert ego["transform"]["location"][0] == pytest.approx(ego["transform_prev"]["location"][0] + 0.5)
    assert ego["timestamp_s"] == pytest.approx(ego["timestamp_prev_s"] + 0.1)
    # The WoodScape-flavour rig was moved to the actor origin: its vehicle origin is at the rear axle (x = -1.3).
    moved = reader.rig()["FV"].camera_to_vehicle.translation
    np.testing.assert_allclose(moved, np.asarray(jf.default_rig()["FV"].camera_to_vehicle.translation) + [-1.3, 0, 0],
                               atol=1e-5)
    assert reader.height(1, "bev").shape == (8, 8) and reader.lidar(1).shape == (5, 4) and reader.imu(1)["compass"] == 0.5
    assert reader.sensors()["gnss"]["geo_reference"]["longitude"] == 1.5
    # Everything spawned is gone and the world is asynchronous again.
    assert fake.world.actors == {} and not fake.world.settings.synchronous_mode and fake.world.tm_sync is False
    printed = capsys.readouterr().out
    assert "frame 2/2 written" in printed and "lens_flare_intensity" in printed
    assert script.main(argv[:4] + ["--weather", "Sunny"]) == 2
    assert "weather preset 'Sunny' is unknown" in capsys.readouterr().err


def test_a_second_writer_of_a_capture_folder_is_refused(script, tmp_path, monkeypatch, capsys):
    from jaxfish.io import CaptureError
    from jaxfish.io._folder import folder_lock

    fake = _FakeCarla("0.9.13")
    monkeypatch.setattr(script, "import_carla", lambda: fake)
    folder = tmp_path / "out" / "ClearNoon"
    folder.mkdir(parents=True)
    argv = ["--out", str(tmp_path / "out"), "--frames", "1", "--warmup", "2", "--face-size", "8", "--bev-size", "8",
            "--front-size", "8", "6", "--vehicles", "0", "--walkers", "0", "--vehicle-origin", "actor"]
    with folder_lock(folder, CaptureError, "capture writer"):  # another writer holds the folder
        assert script.main(argv) == 2
    err = capsys.readouterr().err
    assert f"error: {folder}: another jaxfish capture writer is writing into this folder" in err
    assert "Traceback" not in err and list(folder.iterdir()) == []  # nothing written
    assert fake.world.actors == {} and fake.world.next_id == 100  # nothing spawned before the lock failed
    (folder / "notes.txt").write_text("mine")  # a folder that is not a capture: refused, its file kept
    assert script.main(argv) == 2
    assert "not empty and not a jaxfish capture" in capsys.readouterr().err
    assert [p.name for p in folder.iterdir()] == ["notes.txt"] and fake.world.actors == {}


def _session(script, fake, argv):
    return script.Session(fake, fake.Client("h", 1), script.parse_args(["--out", "x", *argv]))


def test_ego_blueprint_fallback_spawn_points_and_failed_spawns(script, capsys):
    import random

    fake = _FakeCarla("0.9.11")
    lib = fake.world.library
    lib["vehicle.lincoln.mkz2017"] = _Blueprint("vehicle.lincoln.mkz2017", lib.pop("vehicle.lincoln.mkz_2017").values)
    session = _session(script, fake, ["--vehicles", "6", "--walkers", "0"])
    session.synchronous()
    tried = []
    spawn = fake.world.try_spawn_actor
    fake.world.try_spawn_actor = lambda bp, t: (tried.append(t), spawn(bp, t) if len(tried) > 1 else None)[1]
    points = session.spawn_ego(random.Random(0))  # 0.9.10 / 0.9.11 spelling; the first point is taken
    assert session.ego_blueprint == "vehicle.lincoln.mkz2017" and len(tried) == 2
    assert len(points) == 5 and tried[1] not in points and tried[0] in points  # the ego's point is removed
    run = fake.world.run
    used = []

    def run_failing_one(command):
        if command.kind == "spawn":
            used.append(command.kw["transform"])
            if len(used) == 2:
                return SimpleNamespace(actor_id=0, error="collision at spawn position")
        return run(command)

    fake.world.run = run_failing_one
    session.spawn_traffic(random.Random(0), points)
    assert used == points and tried[1] not in used and len(session.actor_ids) == 1 + 4
    out = capsys.readouterr().out
    assert "only 5 free spawn points for --vehicles 6" in out
    assert "1 of 5 traffic vehicles failed to spawn (collision at spawn position)" in out
    del lib["vehicle.lincoln.mkz2017"]
    with pytest.raises(CarlaCaptureError, match="mkz_2017 / vehicle.lincoln.mkz2017: no such blueprint"):
        _session(script, fake, []).spawn_ego(random.Random(0))


def test_a_late_dvs_reading_is_reported(script, capsys):
    import queue

    session = _session(script, _FakeCarla(), [])
    key = ("camera", "FV", "left", "dvs")
    session.queues[key] = q = queue.Queue()
    session.dvs_missed[key] = {7}
    q.put(SimpleNamespace(frame=6))  # stale, never recorded missing: dropped quietly
    q.put(SimpleNamespace(frame=7))  # came after --dvs-wait for frame 7: dropped with a warning
    assert session._get(key, 8, 0.0) is None and session.dvs_missed[key] == set()
    err = capsys.readouterr().err
    assert "camera/FV/left/dvs: its reading of frame 7 came after --dvs-wait" in err and "frame 6" not in err


def test_vehicle_origin_option(script):
    rig = jf.default_rig()
    ego = SimpleNamespace(get_physics_control=lambda: SimpleNamespace(wheels=[]),
                          get_transform=lambda: _transform({"location": (0, 0, 0), "rotation": (0, 0, 0)}))
    assert script.vehicle_origin(SimpleNamespace(vehicle_origin="actor"), rig, ego) == (0.0, 0.0, 0.0)
    assert script.vehicle_origin(SimpleNamespace(vehicle_origin="-1.4,0,0.1"), rig, ego) == (-1.4, 0.0, 0.1)
    syn = {k: type(v)(v.name, v.camera, v.camera_to_vehicle, "synwoodscape") for k, v in rig.items()}
    assert script.vehicle_origin(SimpleNamespace(vehicle_origin="auto"), syn, ego) == (0.0, 0.0, 0.0)
    with pytest.raises(CarlaCaptureError, match="X,Y,Z"):
        script.vehicle_origin(SimpleNamespace(vehicle_origin="1,2"), rig, ego)
    with pytest.raises(CarlaCaptureError, match="at least 2 wheels"):
        script.vehicle_origin(SimpleNamespace(vehicle_origin="auto"), rig, ego)
    no_wheels = SimpleNamespace(get_physics_control=lambda: SimpleNamespace(wheels=[SimpleNamespace(location=1)]))
    with pytest.raises(CarlaCaptureError, match="wheel positions"):
        script.vehicle_origin(SimpleNamespace(vehicle_origin="auto"), rig, no_wheels)


def test_dry_run_lists_the_sensors_without_a_server(script, capsys, monkeypatch):
    monkeypatch.setattr(script, "import_carla", lambda: pytest.fail("a dry run must not import carla"))
    assert script.main(["--dry-run", "--carla-version", "0.9.14", "--face-size", "16"]) == 0
    printed = capsys.readouterr()
    lines = printed.out.splitlines()
    assert lines[0] == "113 sensors for CARLA 0.9.14 (tags 0.9.14):" and len(lines) == 114  # 4 x 5 x 5 + 2 x 4 + 5
    assert any(line.startswith("camera/MVL/top/instance") and "image_size_x=16" in line for line in lines)
    # 16-px faces undersample the default rig's fisheyes: warned about as `jaxfish synth` does.
    assert printed.err.startswith("warning: cube faces of 16 px undersample") and "at least" in printed.err
    # The default face size suffices for the default rig: no warning.
    assert script.main(["--dry-run"]) == 0
    printed = capsys.readouterr()
    assert printed.err == "" and "camera/FV/front/rgb" in printed.out and "image_size_x=1152" in printed.out
    assert script.main(["--dry-run", "--carla-version", "0.9.9"]) == 2
    with pytest.raises(SystemExit):
        script.parse_args(["--frames", "3"])  # --out is required for a capture


def test_the_package_imports_without_the_carla_client(monkeypatch):
    import ast
    import subprocess
    import sys
    from pathlib import Path

    import jaxfish.carla as package

    for path in sorted(Path(package.__file__).parent.glob("*.py")):  # no module imports carla at its top
        tree = ast.parse(path.read_text())
        top = [n for n in tree.body if isinstance(n, ast.Import | ast.ImportFrom)]
        names = [a.name for n in top if isinstance(n, ast.Import) for a in n.names] + [n.module or "" for n in top if isinstance(n, ast.ImportFrom)]
        assert not [n for n in names if n.split(".")[0] == "carla"], path
    # A fresh interpreter where `import carla` fails still imports the package (the client is an optional extra).
    code = "import sys; sys.modules['carla'] = None; import jaxfish.carla; assert sys.modules['carla'] is None"
    subprocess.run([sys.executable, "-c", code], check=True)
    monkeypatch.setitem(sys.modules, "carla", None)
    with pytest.raises(CarlaCaptureError, match=r"pip install 'jaxfish\[carla\]'"):
        package.import_carla()


# ---------------------------------------------------------------------------- the online mode
def _leaves_equal(a, b) -> None:
    """Two pytrees (e.g. `jaxfish.pipeline.Frame`s): the same structure and static fields, and the
    same arrays (dtype, shape, values)."""
    import jax

    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    assert ta == tb
    for x, y in zip(la, lb, strict=True):
        x, y = np.asarray(x), np.asarray(y)
        assert x.dtype == y.dtype and x.shape == y.shape
        np.testing.assert_array_equal(x, y)


def _online_argv(tmp_path, mode: str) -> list[str]:
    calib = tmp_path / "calib"
    if not calib.is_dir():  # header order MVL, RV; dataset order RV, MVL
        rig = jf.default_rig()
        jf.save_rig({n: rig[n].resize(32, 24) for n in ("MVL", "RV")}, calib)
    return [mode, str(tmp_path / mode.strip("-")), "--frames", "2", "--warmup", "2", "--weather", "WetSunset",
            "--calibration", str(calib), "--face-size", "8", "--bev-size", "8", "--front-size", "8", "6",
            "--vehicles", "2", "--walkers", "1"]


def test_the_online_mode_builds_from_the_frames_the_offline_capture_reads_back(script, tmp_path, monkeypatch, capsys):
    """For the same (fake) ticks, the builder of the online mode reads, frame for frame and array for
    array, what `CaptureSource` reads from the offline mode's capture, and writes the same sample files."""
    import jaxfish.dataset
    from jaxfish.dataset import CaptureSource, build_dataset

    monkeypatch.setattr(script, "import_carla", lambda: _FakeCarla("0.9.13"))
    assert script.main(_online_argv(tmp_path, "--out")) == 0
    capture = tmp_path / "out" / "WetSunset"
    seen: dict = {}

    def spy(source, out_dir, **kwargs):  # the real builder, recording what it reads of the source
        read = source.read
        source.read = lambda index, **kw: seen.setdefault(index, read(index, **kw))
        seen["source"] = source
        return build_dataset(source, out_dir, **kwargs)

    monkeypatch.setattr(jaxfish.dataset, "build_dataset", spy)
    fake = _FakeCarla("0.9.13")
    monkeypatch.setattr(script, "import_carla", lambda: fake)
    assert script.main(_online_argv(tmp_path, "--build")) == 0
    printed = capsys.readouterr().out
    assert "sample 00001 built (2/2" in printed and "[WetSunset] dataset built in" in printed
    assert not (tmp_path / "build" / "WetSunset" / "frames").exists()  # no capture written
    # Everything spawned is gone; the online mode spawns no front view and no instance camera.
    assert fake.world.actors == {} and not fake.world.settings.synchronous_mode
    captured, online = CaptureSource(capture), seen["source"]
    assert online.cameras == captured.cameras == ["RV", "MVL"] and online.faces == captured.faces
    assert online.face_size == captured.face_size == 8 and online.carla_tags == captured.carla_tags == "0.9.10"
    assert online.describe() == captured.describe()
    for cam in captured.cameras:
        assert online.calibration_bytes(cam) == captured.calibration_bytes(cam)
    _leaves_equal(online.rig(), captured.rig())
    _leaves_equal(online.bev_sensor(), captured.bev_sensor())
    assert sorted(k for k in seen if k != "source") == captured.frames == [0, 1]
    for k in captured.frames:
        _leaves_equal(seen[k], captured.read(k))
    # The builds: every sample file byte for byte (dataset.json and the markers name their source).
    build_dataset(capture, tmp_path / "offline")
    online_files, offline_files = (tree_bytes(d) for d in (tmp_path / "build" / "WetSunset", tmp_path / "offline"))
    for files in (online_files, offline_files):
        for name in [n for n in files if n == "dataset.json" or n.startswith(".done/")]:
            del files[name]
    assert sorted(online_files) == sorted(offline_files) and len(online_files) > 20
    differ = [n for n in online_files if online_files[n] != offline_files[n]]
    assert differ == [], describe_differences(tmp_path / "build" / "WetSunset", tmp_path / "offline", differ)


def test_the_online_mode_refuses_a_folder_it_cannot_build_into(script, tmp_path, monkeypatch, capsys):
    from jaxfish.dataset import DatasetError
    from jaxfish.io._folder import folder_lock

    fake = _FakeCarla("0.9.13")
    monkeypatch.setattr(script, "import_carla", lambda: fake)
    argv = _online_argv(tmp_path, "--build")
    folder = tmp_path / "build" / "WetSunset"
    folder.mkdir(parents=True)
    with folder_lock(folder, DatasetError, "build"):  # another build holds it
        assert script.main(argv) == 2
    assert f"error: {folder}: another jaxfish build is writing into this folder" in capsys.readouterr().err
    (folder / ".done").mkdir()
    (folder / ".done" / "00000.json").write_text("{}")  # samples of an earlier build: no resume
    assert script.main(argv) == 2
    assert "holds samples of an earlier build" in capsys.readouterr().err
    (folder / ".done" / "00000.json").unlink()
    (folder / ".done").rmdir()
    (folder / "notes.txt").write_text("mine")
    assert script.main(argv) == 2
    assert "not empty and not a jaxfish dataset" in capsys.readouterr().err
    assert fake.world.next_id == 100 and fake.world.actors == {}  # nothing spawned for any of them
    with pytest.raises(SystemExit):
        script.parse_args(argv + ["--out", str(tmp_path / "x")])  # --out and --build exclude each other


def test_carla_source_reads_a_live_session_in_order(tmp_path):
    from jaxfish.carla import CarlaSource
    from jaxfish.dataset import EmbeddedSource

    rig = {"FV": jf.default_rig()["FV"].resize(32, 24)}
    embedded = EmbeddedSource(rig, frames=3, seed=1, config=SMALL)
    calls = []

    def next_frame(k):
        calls.append(k)
        if k == 2:
            raise RuntimeError("time-out while waiting for the simulator")
        return embedded.read(k)

    source = CarlaSource(rig, config=SMALL, bev_camera_to_vehicle=sensor_mounts(rig, SMALL).bev_camera_to_vehicle,
                         carla_version="0.9.12", frames=3, next_frame=next_frame, settings={"weather": "WetNoon"})
    assert source.read(1).index == 1 and calls == [0, 1]  # frame 0 ticked on the way (and kept)
    assert source.read(0, bev=False).bev is None and source.read(0).bev is not None and calls == [0, 1]
    with pytest.raises(RuntimeError, match="time-out"):
        source.read(2)
    with pytest.raises(CarlaCaptureError, match="the session stopped at frame 2: RuntimeError: time-out"):
        source.read(2)  # at once, without asking the simulator again
    assert calls == [0, 1, 2]
    with pytest.raises(CarlaCaptureError, match="frame 5 is not one of its 3 frames"):
        source.read(5)
    other = CarlaSource(rig, config=SMALL, bev_camera_to_vehicle=sensor_mounts(rig, SMALL).bev_camera_to_vehicle,
                        carla_version="0.9.12", frames=4, next_frame=embedded.read, keep=1)
    other.read(1)
    with pytest.raises(CarlaCaptureError, match="frame 0 was read before and is gone"):
        other.read(0)
    assert source.fingerprint() != other.fingerprint() and source.carla_tags == "0.9.10"
    assert source.constants_key() == other.constants_key()  # the same rig constants
