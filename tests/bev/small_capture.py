"""A small capture of the analytic BEV scene (`tests.bev.conftest`: a patterned ground plane and
boxes), written in the capture layout with CARLA encodings: the fisheye rig's cube faces and the
BEV view are ray-cast in float64 NumPy (no scene compile), the ego stands still at the world origin
and the vehicle box is an actor. Shared by the io and CLI BEV tests."""

from __future__ import annotations

import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np

import jaxfish as jf
from jaxfish.io import DVS_EVENT_DTYPE, write_capture_header
from jaxfish.io._capture import frame_dir, write_images
from jaxfish.reprojection import CubeRig
from jaxfish.scene import CameraImages, CaptureConfig, sensor_mounts
from tests.bev.conftest import BOXES, render

BEV_SIZE = 64
BEV_MPP = 0.5
CAM_W, CAM_H, FACE = 48, 36, 16
#: Analytic classes -> CARLA 0.9.10 tags: ground pattern 1..4 -> road, sidewalk, roadline,
#: vegetation; boxes keep their class (22 static -> tag 19).
TAG = {1: 7, 2: 8, 3: 6, 4: 9, 10: 10, 22: 19, 5: 5, 8: 8, 11: 11, 13: 13, 0: 0}
ACTOR_ID = 100  # the vehicle box (class 10) is an actor; the other boxes are static world


def _tags(cls):
    out = np.zeros(cls.shape, np.uint8)
    for c, t in TAG.items():
        out[cls == c] = t
    return out


def _images(rays_vehicle, origins, planar):
    rng, cls = render(rays_vehicle, origins)
    tags = _tags(cls)
    actor = np.where(cls == 10, ACTOR_ID, 0).astype(np.int32)
    depth = np.where(rng >= 1000.0, 1000.0, rng * planar).astype(np.float32)
    return CameraImages(rgb=np.zeros(rng.shape + (3,), np.uint8), depth_m=depth, semantic=tags, actor_id=actor), rng


def write_bev_capture(root: Path) -> Path:
    """Write one frame (0) of the analytic scene under ``root``."""
    rig = {k: v.astype(jnp.float32) for k, v in jf.default_rig(width=CAM_W, height=CAM_H, dtype=jnp.float32).items()}
    config = CaptureConfig(face_size=FACE, bev_size=BEV_SIZE, bev_metres_per_pixel=BEV_MPP)
    mounts = sensor_mounts(rig, config)
    write_capture_header(root, rig, config, mounts, seed=0, source="analytic")
    d = frame_dir(root, 0)
    cube = CubeRig(FACE, faces=config.faces, dtype=jnp.float32)
    rays_face, _ = cube.face.unproject(cube.face.pixel_grid(jnp.float32))
    rays_face = np.asarray(rays_face, np.float64)
    for name, calib in rig.items():
        r = np.asarray(calib.camera_to_vehicle.rotation_matrix, np.float64)
        t = np.asarray(calib.camera_to_vehicle.translation, np.float64)
        for face in config.faces:
            rf = np.asarray(cube.face_pose(face).rotation_matrix, np.float64)
            img, _ = _images(rays_face @ (r @ rf).T, t, rays_face[..., 2])
            fd = d / "cameras" / name / face
            write_images(fd, img, "prev")
            write_images(fd, img, "curr")
            np.save(fd / "dvs.npy", np.zeros(0, DVS_EVENT_DTYPE))
    bev = jf.scene.bev_camera(config)
    pose = mounts.bev_camera_to_vehicle
    origins = np.asarray(pose.apply(bev.ray_origins(bev.pixel_grid(jnp.float32))), np.float64)
    down = np.broadcast_to(np.asarray(pose.rotation_matrix, np.float64)[:, 2], origins.shape)
    img, rng = _images(down, origins, np.ones(origins.shape[:-1]))
    write_images(d / "bev", img, "prev")
    write_images(d / "bev", img, "curr")
    jf.io.write_image(d / "bev" / "height_curr.exr", (origins[..., 2] - rng).astype(np.float32)[..., None])
    still = {"location": [0.0, 0.0, 0.0], "rotation": [0.0, 0.0, 0.0]}
    ego_box = {"location": [1.3, 0.0, 0.75], "extent": [2.3, 0.9, 0.75]}
    x0, x1, y0, y1, h, _ = BOXES[0]  # CARLA y is -ISO y
    car = {"id": ACTOR_ID, "type_id": "vehicle.analytic", "category": "four_wheeler", "semantic_tag": 10,
           "is_ego": False, "bounding_box": {"location": [0.0, 0.0, h / 2], "extent": [(x1 - x0) / 2, (y1 - y0) / 2, h / 2]},
           "transform_prev": {"location": [(x0 + x1) / 2, -(y0 + y1) / 2, 0.0], "rotation": [0.0, 0.0, 0.0]},
           "transform": {"location": [(x0 + x1) / 2, -(y0 + y1) / 2, 0.0], "rotation": [0.0, 0.0, 0.0]},
           "velocity": [0.0, 0.0, 0.0], "angular_velocity": [0.0, 0.0, 0.0], "displacement_m": 0.0}
    (d / "ego.json").write_text(json.dumps({"frame": 0, "timestamp_s": 0.1, "timestamp_prev_s": 0.0, "id": 1,
                                            "transform_prev": still, "transform": still, "velocity": [0, 0, 0],
                                            "acceleration": [0, 0, 0], "angular_velocity": [0, 0, 0],
                                            "bounding_box": ego_box}))
    ego = {"id": 1, "type_id": "vehicle.ego", "category": "ego", "semantic_tag": 10, "is_ego": True,
           "bounding_box": ego_box, "transform_prev": still, "transform": still, "velocity": [0.0, 0.0, 0.0],
           "angular_velocity": [0.0, 0.0, 0.0], "displacement_m": 0.0}
    (d / "actors.json").write_text(json.dumps({"frame": 0, "timestamp_s": 0.1, "actors": [ego, car]}))
    header = json.loads((root / "capture.json").read_text())
    header["frames"] = [0]
    (root / "capture.json").write_text(json.dumps(header))
    return root


_SHARED: dict[str, Path] = {}


def shared_bev_capture(tmp_path_factory) -> Path:
    """The capture written once per test session (read-only for its users: copy it to modify)."""
    if "root" not in _SHARED:
        _SHARED["root"] = write_bev_capture(tmp_path_factory.mktemp("bevcapture"))
    return _SHARED["root"]
