"""Calibration files of other tools (`jaxfish.io._formats`, ``jaxfish export``): every format
round-trips exactly where it holds the model, is read by the tool's own library where one installs
(cv2.FileStorage, pycolmap), and reads hand-written files in the layouts the tools document."""

from __future__ import annotations

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish as jf
from jaxfish.calibration import Calibration
from jaxfish.io import load_camera_calibration
from jaxfish.io._formats import (
    detect_calibration_format,
    export_calibrations,
    format_models,
    holds_exactly,
    read_calibration_file,
)
from jaxfish.refit import MODEL_CLASSES, camera_from_intrinsics, intrinsics_vector, rotation_from_vector

jax.config.update("jax_enable_x64", True)

MOUNTS = [jf.Pose(rotation_from_vector(jnp.asarray(w)), jnp.asarray(t)) for w, t in (
    ([1.2, -1.1, 1.3], [3.7, 0.01, 0.62]), ([-0.4, 2.1, -1.9], [1.95, 1.02, 0.98]), ([0.3, 0.2, -2.8], [-1.05, 0.0, 0.92]))]
PARAMS = {
    "kannala_brandt": [331.5, 330.25, 641.3, 479.7, 0.0254, 0.0215, -0.0059, 0.00056],
    "double_sphere": [158.28, 158.27, 254.76, 256.68, -0.17, 0.59],
    "extended_unified": [250.0, 251.0, 640.5, 480.25, 0.62, 1.1],
    "unified": [300.0, 300.5, 640.0, 480.0, 0.55],
    "pinhole": [640.0, 640.0, 639.5, 482.5],
}


def calib(model: str, i: int = 0, name: str | None = None) -> Calibration:
    cam = camera_from_intrinsics(model, np.asarray(PARAMS[model]), width=1280, height=966, dtype=jnp.float64)
    return Calibration(name or f"cam_{model}_{i}", cam, MOUNTS[i % len(MOUNTS)])


def same(a: Calibration, b: Calibration, *, rtol: float = 0.0, pose_atol: float = 1e-12) -> None:
    assert type(a.camera) is type(b.camera)
    assert a.camera.image_size == b.camera.image_size
    np.testing.assert_allclose(np.asarray(intrinsics_vector(b.camera)), np.asarray(intrinsics_vector(a.camera)),
                               rtol=rtol, atol=0)
    np.testing.assert_allclose(np.asarray(b.camera_to_vehicle.as_matrix()), np.asarray(a.camera_to_vehicle.as_matrix()),
                               atol=pose_atol)


OUT = {"kalibr": "camchain.yaml", "colmap": "sparse", "opencv": "cams", "basalt": "calib.json", "carla": "sensors.json"}


@pytest.mark.parametrize("fmt", ["kalibr", "colmap", "opencv", "basalt"])
def test_every_model_a_format_holds_round_trips_exactly(fmt, tmp_path):
    calibs = [calib(m, i, name=f"C{i}") for i, m in enumerate(format_models(fmt)) if m in PARAMS]
    assert len(calibs) >= 2
    export_calibrations(calibs, fmt, tmp_path / OUT[fmt])
    back = read_calibration_file(tmp_path / OUT[fmt] if fmt != "opencv" or len(calibs) == 1 else tmp_path / "cams" / "C0.yaml")
    if fmt == "opencv":  # one file per camera
        back = [read_calibration_file(tmp_path / "cams" / f"{c.name}.yaml")[0] for c in calibs]
    assert len(back) == len(calibs)
    for a, b in zip(calibs, back, strict=True):
        if fmt == "kalibr" and isinstance(a.camera, jf.UnifiedCamera):
            # kalibr's omni is Mei's model: the unified camera is written as xi = alpha / (1 - alpha),
            # f / (1 - alpha) and read back as that (mei where jaxfish has it): the same projection.
            pts = jnp.asarray(np.random.default_rng(0).normal(size=(50, 3)) + np.array([0.0, 0.0, 1.5]))
            np.testing.assert_allclose(np.asarray(b.camera.project(pts)[0]), np.asarray(a.camera.project(pts)[0]),
                                       atol=1e-9)
            np.testing.assert_allclose(np.asarray(b.camera_to_vehicle.as_matrix()),
                                       np.asarray(a.camera_to_vehicle.as_matrix()), atol=1e-12)
        else:
            same(a, b)
        if fmt != "basalt":  # basalt files carry no camera names
            assert b.name == a.name


def test_carla_pinhole_round_trips_and_mounts_as_the_capture_does(tmp_path):
    try:
        from jaxfish.carla import camera_mount  # the CARLA glue's own package
    except ImportError:
        from jaxfish.io import camera_mount

    c = Calibration("front", jf.Pinhole.from_fov(1280, 966, 100.0, dtype=jnp.float64), MOUNTS[0])
    assert holds_exactly("carla", c)
    export_calibrations([c], "carla", tmp_path / "s.json")
    data = json.loads((tmp_path / "s.json").read_text())
    s = data["sensors"][0]
    assert s["blueprint"] == "sensor.camera.rgb" and float(s["attributes"]["fov"]) == pytest.approx(100.0, abs=1e-12)
    mount = camera_mount(MOUNTS[0])
    np.testing.assert_allclose(s["transform"]["location"], mount.location, atol=1e-12)
    np.testing.assert_allclose(s["transform"]["rotation"], mount.rotation, atol=1e-9)
    back = read_calibration_file(tmp_path / "s.json")[0]
    same(c, back, rtol=1e-13, pose_atol=1e-12)
    off_centre = Calibration("x", jf.Pinhole(500.0, 500.0, 600.0, 480.0, width=1280, height=966), MOUNTS[0])
    assert not holds_exactly("carla", off_centre)


def test_the_first_camera_of_a_kalibr_chain_without_imu_is_the_vehicle_frame(tmp_path):
    """kalibr's cam-only camchain: T_cn_cnm1 chains the cameras; cam0 is the vehicle frame."""
    p = tmp_path / "camchain.yaml"
    p.write_text("""cam0:
  camera_model: ds
  intrinsics: [-0.17, 0.59, 158.28, 158.27, 254.76, 256.68]
  distortion_model: none
  distortion_coeffs: []
  resolution: [512, 512]
  rostopic: /cam0/image_raw
cam1:
  T_cn_cnm1:
  - [0.9999, -0.0100, 0.0100, -0.1010]
  - [0.0101, 0.9999, -0.0050, 0.0005]
  - [-0.0100, 0.0051, 0.9999, 0.0010]
  - [0.0, 0.0, 0.0, 1.0]
  camera_model: eucm
  intrinsics: [0.62, 1.1, 250.0, 251.0, 255.5, 256.0]
  distortion_model: none
  distortion_coeffs: []
  resolution: [512, 512]
  rostopic: /cam1/image_raw
""")
    assert detect_calibration_format(p) == "kalibr"
    c0, c1 = read_calibration_file(p, dtype=jnp.float64)
    assert isinstance(c0.camera, jf.DoubleSphere) and isinstance(c1.camera, jf.ExtendedUnifiedCamera)
    assert float(c0.camera.xi) == -0.17 and float(c1.camera.beta) == 1.1 and c1.name == "cam1"
    np.testing.assert_allclose(np.asarray(c0.camera_to_vehicle.as_matrix()), np.eye(4), atol=1e-15)
    # cam1 -> cam0 is the inverse of T_cn_cnm1 (cam0 -> cam1): its origin sits 0.101 m along cam0's x
    np.testing.assert_allclose(np.asarray(c1.camera_to_vehicle.translation), [0.101, 0.0, 0.0], atol=2e-3)
    with pytest.raises(jf.CalibrationError, match="holds 2 cameras"):
        load_camera_calibration(p)
    assert load_camera_calibration(p, camera="cam1").name == "cam1"
    assert load_camera_calibration(p, camera="0").name == "cam0"
    assert load_camera_calibration(f"{p}::cam1").name == jf.load_calibration(f"{p}::1").name == "cam1"
    with pytest.raises(jf.CalibrationError, match=r"no camera 'FV' \(cameras: cam0, cam1\)"):
        load_camera_calibration(f"{p}::FV")


def test_kalibr_documented_camchain(tmp_path):
    """The layout of kalibr's wiki (a pinhole-radtan cam0 with T_cam_imu and timeshift, an
    omni-radtan cam1): read when jaxfish has the opencv and mei models, else refused naming the
    field and the missing model."""
    p = tmp_path / "camchain-imucam.yaml"
    p.write_text("""cam0:
  camera_model: pinhole
  intrinsics: [461.629, 460.152, 362.680, 246.049]
  distortion_model: radtan
  distortion_coeffs: [-0.27695497, 0.06712482, 0.00087538, 0.00011556]
  T_cam_imu:
  - [0.01779318, 0.99967549, -0.01822936, 0.07008565]
  - [-0.9998017, 0.01795239, 0.00860714, -0.01771023]
  - [0.00893160, 0.01807260, 0.99979678, 0.00399246]
  - [0.0, 0.0, 0.0, 1.0]
  timeshift_cam_imu: -8.121e-05
  rostopic: /cam0/image_raw
  resolution: [752, 480]
cam1:
  camera_model: omni
  intrinsics: [0.80065662, 833.006, 830.345, 373.850, 253.749]
  distortion_model: radtan
  distortion_coeffs: [-0.33518750, 0.13211436, 0.00055967, 0.00057686]
  T_cn_cnm1:
  - [0.99998854, 0.00216014, 0.00427195, -0.11003785]
  - [-0.00221074, 0.99992702, 0.01187697, 0.00045792]
  - [-0.00424598, -0.01188627, 0.99992034, -0.00064487]
  - [0.0, 0.0, 0.0, 1.0]
  rostopic: /cam1/image_raw
  resolution: [752, 480]
""")
    if "opencv" in MODEL_CLASSES and "mei" in MODEL_CLASSES:
        c0, c1 = read_calibration_file(p, dtype=jnp.float64)
        assert float(c0.camera.fx) == 461.629 and float(c1.camera.xi) == 0.80065662
    else:
        with pytest.raises(jf.CalibrationError, match=r"camchain-imucam\.yaml: field 'cam0\.camera_model'.*'opencv'"):
            read_calibration_file(p)


def test_colmap_documented_cameras_and_images(tmp_path):
    """COLMAP's text layout (comments, a camera line, an image line and its 2D points line):
    the principal point moves by 0.5 px and the image pose (world -> camera) is the mounting."""
    (tmp_path / "cameras.txt").write_text("""# Camera list with one line of data per camera:
#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]
# Number of cameras: 2
1 OPENCV_FISHEYE 1280 966 331.5 330.25 641.8 480.2 0.0254 0.0215 -0.0059 0.00056
2 SIMPLE_RADIAL_FISHEYE 640 480 200.0 320.0 240.0 0.01
""")
    (tmp_path / "images.txt").write_text("""# Image list with two lines of data per image:
#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME
#   POINTS2D[] as (X, Y, POINT3D_ID)
# Number of images: 1, mean observations per image: 2
1 0.7071067811865476 0.0 0.7071067811865476 0.0 1.0 2.0 3.0 1 front.jpg
2362.39 248.498 58396 1784.7 268.254 59027
""")
    a, b = read_calibration_file(tmp_path, dtype=jnp.float64)
    assert a.name == "front" and b.name == "camera2"
    assert float(a.camera.cx) == 641.3 and float(a.camera.cy) == 479.7
    assert float(b.camera.fx) == float(b.camera.fy) == 200.0 and float(b.camera.k[0]) == 0.01
    w2c = a.camera_to_vehicle.inverse()
    np.testing.assert_allclose(np.asarray(w2c.translation), [1.0, 2.0, 3.0], atol=1e-12)
    np.testing.assert_allclose(np.asarray(w2c.rotation_matrix), [[0, 0, 1], [0, 1, 0], [-1, 0, 0]], atol=1e-12)
    assert detect_calibration_format(tmp_path / "cameras.txt") == "colmap"


def test_pycolmap_reads_the_export_and_projects_as_jaxfish(tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    calibs = [calib("kannala_brandt", 0, "FV"), calib("pinhole", 1, "side"), calib("extended_unified", 2, "rear")]
    export_calibrations(calibs, "colmap", tmp_path / "sparse")
    rec = pycolmap.Reconstruction()
    rec.read_text(str(tmp_path / "sparse"))
    assert rec.num_cameras() == 3 and rec.num_images() == 3
    rng = np.random.default_rng(0)
    world = rng.uniform(-3, 3, size=(40, 3))
    for c in calibs:
        image = rec.find_image_with_name(f"{c.name}.png")
        cam_from_world = image.cam_from_world()
        pts_cam = np.asarray(c.camera_to_vehicle.inverse().apply(jnp.asarray(world)))
        np.testing.assert_allclose(np.asarray([cam_from_world * p for p in world]), pts_cam, atol=1e-9)
        front = pts_cam[:, 2] > 0.5
        uv_colmap = np.asarray(image.camera.img_from_cam(pts_cam[front]))
        uv, valid = c.camera.project(jnp.asarray(pts_cam[front]))
        assert bool(jnp.all(valid))
        np.testing.assert_allclose(uv_colmap - 0.5, np.asarray(uv), atol=1e-6)  # COLMAP's pixel origin: the corner


def test_opencv_filestorage_is_read_by_cv2_and_cv2_files_by_jaxfish(tmp_path):
    cv2 = pytest.importorskip("cv2")
    c = calib("kannala_brandt", 1, "FV")
    export_calibrations([c], "opencv", tmp_path / "fv.yaml")
    fs = cv2.FileStorage(str(tmp_path / "fv.yaml"), cv2.FILE_STORAGE_READ)
    k, d = fs.getNode("K").mat(), fs.getNode("D").mat()
    r, t = fs.getNode("R").mat(), fs.getNode("T").mat()
    assert fs.getNode("distortion_model").string() == "fisheye" and int(fs.getNode("image_width").real()) == 1280
    fs.release()
    pts = np.random.default_rng(1).uniform(-2, 2, size=(30, 3)) + np.array([0, 0, 0.0])
    pts_cam = np.asarray(c.camera_to_vehicle.inverse().apply(jnp.asarray(pts)))
    np.testing.assert_allclose(pts @ r.T + t.ravel(), pts_cam, atol=1e-12)
    front = pts_cam[:, 2] > 0.3
    uv_cv, _ = cv2.fisheye.projectPoints(pts_cam[front][:, None, :], np.zeros(3), np.zeros(3), k, d)
    uv, _ = c.camera.project(jnp.asarray(pts_cam[front]))
    np.testing.assert_allclose(uv_cv[:, 0], np.asarray(uv), atol=1e-6)
    # A file cv2 writes (the calibration sample's keys), read by jaxfish.
    fs = cv2.FileStorage(str(tmp_path / "cv.yml"), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 1280)
    fs.write("image_height", 966)
    fs.write("camera_matrix", k)
    fs.write("distortion_coefficients", d)
    fs.write("distortion_model", "equidistant")
    fs.release()
    back = jf.load_calibration(tmp_path / "cv.yml")
    np.testing.assert_array_equal(np.asarray(intrinsics_vector(back.camera)), np.asarray(intrinsics_vector(c.camera)))
    np.testing.assert_allclose(np.asarray(back.camera_to_vehicle.as_matrix()), np.eye(4))


def test_opencv_ambiguous_and_plain_pinhole_files(tmp_path):
    p = tmp_path / "k.yaml"
    p.write_text("%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\ncamera_matrix: !!opencv-matrix\n   rows: 3\n"
                 "   cols: 3\n   dt: d\n   data: [ 500., 0., 319.5, 0., 500., 239.5, 0., 0., 1. ]\n"
                 "distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 4\n   dt: d\n   data: [ 0.1, 0.01, 0., 0. ]\n")
    with pytest.raises(jf.CalibrationError, match=r"k\.yaml: field 'distortion_model': missing"):
        load_camera_calibration(p)
    p.write_text(p.read_text().replace("[ 0.1, 0.01, 0., 0. ]", "[ 0., 0., 0., 0., 0. ]").replace("cols: 4", "cols: 5"))
    c = load_camera_calibration(p)  # cv2's model with zero coefficients
    assert type(c.camera).__name__ == ("OpenCVPinhole" if "opencv" in MODEL_CLASSES else "Pinhole")
    assert float(c.camera.cx) == 319.5
    p.write_text(p.read_text() + "distortion_model: pinhole\n")
    assert isinstance(load_camera_calibration(p).camera, jf.Pinhole)


def test_basalt_documented_calibration(tmp_path):
    """basalt's calibration JSON (as basalt_calibrate writes it, two ds cameras of TUM-VI)."""
    p = tmp_path / "calibration.json"
    cam = {"camera_type": "ds", "intrinsics": {"fx": 158.28, "fy": 158.27, "cx": 254.76, "cy": 256.68,
                                                "xi": -0.17, "alpha": 0.59}}
    p.write_text(json.dumps({"value0": {
        "T_imu_cam": [{"px": 0.04, "py": -0.06, "pz": -0.02, "qx": -0.0, "qy": 0.0, "qz": 0.7071067811865476,
                       "qw": 0.7071067811865476},
                      {"px": -0.06, "py": -0.06, "pz": -0.02, "qx": 0.0, "qy": 0.0, "qz": 0.7071067811865476,
                       "qw": 0.7071067811865476}],
        "intrinsics": [cam, {"camera_type": "kb4", "intrinsics": {"fx": 190.9, "fy": 190.9, "cx": 254.9, "cy": 256.8,
                                                                  "k1": 0.0034, "k2": 0.0007, "k3": 0.0, "k4": 0.0}}],
        "resolution": [[512, 512], [512, 512]], "vignette": [], "calib_accel_bias": [0.0] * 9,
        "calib_gyro_bias": [0.0] * 12, "imu_update_rate": 200.0, "accel_noise_std": [0.016, 0.016, 0.016],
        "gyro_noise_std": [0.000282, 0.000282, 0.000282], "accel_bias_std": [0.001] * 3, "gyro_bias_std": [1e-4] * 3,
        "cam_time_offset_ns": 0}}))
    assert detect_calibration_format(p) == "basalt"
    a, b = read_calibration_file(p, dtype=jnp.float64)
    assert isinstance(a.camera, jf.DoubleSphere) and isinstance(b.camera, jf.KannalaBrandt)
    assert (a.name, b.name) == ("cam0", "cam1")
    np.testing.assert_allclose(np.asarray(a.camera_to_vehicle.translation), [0.04, -0.06, -0.02])
    np.testing.assert_allclose(np.asarray(a.camera_to_vehicle.rotation_matrix), [[0, -1, 0], [1, 0, 0], [0, 0, 1]],
                               atol=1e-12)


def test_carla_blueprint_attributes(tmp_path):
    """A plain ``sensor.camera.rgb`` is CARLA's pinhole; WideAngle lens attributes need the
    carla_wide_angle model."""
    p = tmp_path / "front.json"
    p.write_text(json.dumps({"name": "front", "blueprint": "sensor.camera.rgb",
                             "attributes": {"image_size_x": "800", "image_size_y": "600", "fov": "90"},
                             "transform": {"location": {"x": 1.5, "y": 0.0, "z": 2.4},
                                           "rotation": {"pitch": -15.0, "yaw": 0.0, "roll": 0.0}}}))
    c = load_camera_calibration(p, dtype=jnp.float64)
    ref = jf.Pinhole.from_fov(800, 600, 90.0, dtype=jnp.float64)
    np.testing.assert_allclose(np.asarray(intrinsics_vector(c.camera)), np.asarray(intrinsics_vector(ref)), rtol=1e-15)
    np.testing.assert_allclose(np.asarray(c.camera_to_vehicle.translation), [1.5, 0.0, 2.4])
    axis = np.asarray(c.camera_to_vehicle.rotation_matrix)[:, 2]  # the optical axis: forward, 15 degrees down
    np.testing.assert_allclose(axis, [math.cos(math.radians(15)), 0.0, -math.sin(math.radians(15))], atol=1e-12)
    lens = tmp_path / "wide.json"
    lens.write_text(json.dumps({"sensors": [{"name": "fish", "attributes": {
        "image_size_x": "1280", "image_size_y": "966", "fov": "200", "camera_model": "equidistant", "k0": "0"}}]}))
    if "carla_wide_angle" not in MODEL_CLASSES:
        with pytest.raises(jf.CalibrationError, match=r"wide\.json: field 'sensors\[0\]\.attributes\.camera_model'"
                                                      r".*carla_wide_angle"):
            load_camera_calibration(lens)
        return
    fish = load_camera_calibration(lens, dtype=jnp.float64)
    assert type(fish.camera).__name__ == "CarlaWideAngle" and fish.name == "fish"
    vec = np.asarray(intrinsics_vector(fish.camera))
    assert vec[0] == 200.0 and vec[1] == 0.0  # fov, k0 as given; k1..k3 CARLA's defaults
    assert holds_exactly("carla", fish)
    export_calibrations([fish], "carla", tmp_path / "back.json")
    data = json.loads((tmp_path / "back.json").read_text())["sensors"][0]
    assert data["blueprint"] == "sensor.camera.rgb_wide_angle_lens"
    assert data["attributes"]["camera_model"] == "equidistant"
    back = load_camera_calibration(tmp_path / "back.json", dtype=jnp.float64)
    np.testing.assert_array_equal(np.asarray(intrinsics_vector(back.camera)), vec)
    assert back.camera.image_size == (1280, 966)


def test_export_cli_writes_exactly_or_converts_within_max_error(tmp_path):
    from typer.testing import CliRunner

    from jaxfish.cli import app
    from jaxfish.io import save_camera_calibration

    save_camera_calibration(calib("kannala_brandt", 0, "FV"), tmp_path / "fv.json")
    save_camera_calibration(calib("double_sphere", 1, "MVL"), tmp_path / "mvl.json")
    run = CliRunner().invoke
    r = run(app, ["export", str(tmp_path / "fv.json"), str(tmp_path / "mvl.json"), "--format", "basalt",
                  "--out", str(tmp_path / "b.json"), "--report", str(tmp_path / "r.json")])
    assert r.exit_code == 0, r.output
    assert "written exactly" in r.output
    back = read_calibration_file(tmp_path / "b.json", dtype=jnp.float64)
    same(calib("kannala_brandt", 0), back[0])
    same(calib("double_sphere", 1), back[1])
    report = json.loads((tmp_path / "r.json").read_text())
    assert [c["converted"] for c in report["cameras"]] == [False, False]
    # COLMAP lacks the double sphere: converted to Kannala-Brandt over the image, error reported.
    r = run(app, ["export", str(tmp_path / "mvl.json"), "--format", "colmap", "--out", str(tmp_path / "sparse"),
                  "--report", str(tmp_path / "r2.json")])
    assert r.exit_code == 0, r.output
    row = json.loads((tmp_path / "r2.json").read_text())["cameras"][0]
    assert row["converted"] and row["model"] == "kannala_brandt" and 0 < row["max_px"] < 2.0
    assert "double_sphere -> kannala_brandt over the 1280x966 image's valid pixels" in r.output
    # Above --max-error: nothing written, exit 2 (as jaxfish convert); --force writes.
    r = run(app, ["export", str(tmp_path / "mvl.json"), "--format", "colmap", "--out", str(tmp_path / "s2"),
                  "--max-error", "1e-6"])
    assert r.exit_code == 2 and not (tmp_path / "s2").exists()
    r = run(app, ["export", str(tmp_path / "mvl.json"), "--format", "colmap", "--out", str(tmp_path / "s2"),
                  "--max-error", "1e-6", "--force"])
    assert r.exit_code == 0 and (tmp_path / "s2" / "cameras.txt").exists()


def test_calibration_paths_of_folders_files_and_single_cameras(tmp_path):
    from jaxfish.io import read_calibration_paths, save_camera_calibration

    (tmp_path / "rig").mkdir()
    save_camera_calibration(calib("kannala_brandt", 0, "MVL"), tmp_path / "rig" / "MVL.json")
    save_camera_calibration(calib("double_sphere", 1, "FV"), tmp_path / "rig" / "FV.json")
    export_calibrations([calib("pinhole", 2, "A"), calib("unified", 1, "B")], "basalt", tmp_path / "b.json")
    got = read_calibration_paths([tmp_path / "rig", f"{tmp_path / 'b.json'}::cam1"])
    assert [c.name for c in got] == ["FV", "MVL", "cam1"]
    with pytest.raises(jf.CalibrationError, match="two cameras are named 'FV'"):
        read_calibration_paths([tmp_path / "rig", tmp_path / "rig" / "FV.json"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(jf.CalibrationError, match="neither calibration JSON files nor cameras.txt"):
        read_calibration_paths([tmp_path / "empty"])


def test_load_calibration_dispatches_and_woodscape_files_are_unchanged(tmp_path):
    fv = jf.load_calibration("../shared/calibration/synwoodscape/FV.json")
    assert fv.flavor == "synwoodscape"
    export_calibrations([calib("extended_unified", 0, "FV")], "kalibr", tmp_path / "one.yaml")
    c = jf.load_calibration(tmp_path / "one.yaml")
    assert isinstance(c.camera, jf.ExtendedUnifiedCamera) and c.name == "FV"


MORE_PARAMS = {
    "opencv": [500.0, 501.0, 640.2, 480.7, -0.12, 0.03, 0.001, -0.0008, -0.004, 0.01, 0.002, 0.001,
               0.0005, -0.0004, 0.0003, 0.0002],
    "mei": [700.0, 701.0, 640.5, 480.5, 1.2, -0.1, 0.02, 0.001, -0.001],
    "fov": [300.0, 301.0, 640.0, 481.0, 0.9],
    "fisheye624": [330.0, 331.0, 641.0, 479.5, 0.02, -0.01, 0.003, -0.0005, 0.0001, -0.00002,
                   0.0004, -0.0003, 0.0002, -0.0001, 0.0003, 0.0001],
}
"""Parameters of the models other lens modules add (tests below run where jaxfish has them)."""


def more_calib(model: str, i: int, name: str, **zero) -> Calibration:
    if model not in MODEL_CLASSES:
        pytest.skip(f"jaxfish has no {model} model")
    names = jf.refit.parameter_names(model)
    vec = [0.0 if n in zero.get("zero", ()) else v for n, v in zip(names, MORE_PARAMS[model], strict=True)]
    cam = camera_from_intrinsics(model, np.asarray(vec), width=1280, height=966, dtype=jnp.float64)
    return Calibration(name, cam, MOUNTS[i % len(MOUNTS)])


@pytest.mark.parametrize(("fmt", "model", "zero", "tool"), [
    ("kalibr", "opencv", ("k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4"), "radtan"),
    ("kalibr", "mei", (), "omni"),
    ("kalibr", "fov", (), "fov"),
    ("colmap", "opencv", ("s1", "s2", "s3", "s4"), "FULL_OPENCV"),
    ("colmap", "opencv", ("k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4"), "OPENCV "),
    ("colmap", "fov", (), "FOV"),
    ("colmap", "fisheye624", (), "RAD_TAN_THIN_PRISM_FISHEYE"),
    ("basalt", "opencv", ("s1", "s2", "s3", "s4"), "pinhole-radtan8"),
    ("basalt", "fov", (), '"fov"'),
    ("opencv", "opencv", (), "thin_prism"),
    ("opencv", "mei", (), "omnidir"),
])
def test_models_of_other_lens_modules_round_trip(fmt, model, zero, tool, tmp_path):
    c = more_calib(model, 1, "FV", zero=zero)
    assert holds_exactly(fmt, c)
    out = tmp_path / ("sparse" if fmt == "colmap" else "f.yaml" if fmt in ("kalibr", "opencv") else "f.json")
    export_calibrations([c], fmt, out)
    text = (out / "cameras.txt" if fmt == "colmap" else out).read_text()
    assert tool in text
    same(c, read_calibration_file(out)[0])


@pytest.mark.parametrize("model", ["opencv", "fov", "fisheye624"])
def test_pycolmap_projects_the_other_models_as_jaxfish(model, tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    c = more_calib(model, 0, "FV", zero=("s1", "s2", "s3", "s4") if model == "opencv" else ())  # FULL_OPENCV
    export_calibrations([c], "colmap", tmp_path / "sparse")
    rec = pycolmap.Reconstruction()
    rec.read_text(str(tmp_path / "sparse"))
    cam = rec.cameras[1]
    rng = np.random.default_rng(2)
    pts = rng.uniform(-0.6, 0.6, size=(60, 3)) * np.array([1, 1, 0]) + np.array([0, 0, 1.0])
    uv, valid = c.camera.project(jnp.asarray(pts))
    assert bool(jnp.all(valid))
    np.testing.assert_allclose(np.asarray(cam.img_from_cam(pts)) - 0.5, np.asarray(uv), atol=1e-6)


def test_cv2_omnidir_reads_and_projects_the_mei_export(tmp_path):
    cv2 = pytest.importorskip("cv2")
    if not hasattr(cv2, "omnidir"):
        pytest.skip("cv2.omnidir (opencv-contrib) is not installed")
    c = more_calib("mei", 0, "FV")
    export_calibrations([c], "opencv", tmp_path / "mei.yaml")
    fs = cv2.FileStorage(str(tmp_path / "mei.yaml"), cv2.FILE_STORAGE_READ)
    k, d, xi = fs.getNode("K").mat(), fs.getNode("D").mat(), fs.getNode("xi").real()
    fs.release()
    pts = np.random.default_rng(3).uniform(-1, 1, size=(40, 3)) + np.array([0, 0, 1.2])
    uv_cv, _ = cv2.omnidir.projectPoints(pts[:, None, :], np.zeros(3), np.zeros(3), k, xi, d)
    uv, _ = c.camera.project(jnp.asarray(pts))
    np.testing.assert_allclose(uv_cv[:, 0], np.asarray(uv), atol=1e-6)
