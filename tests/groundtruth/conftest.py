"""Shared fixtures of the ground-truth tests: one small embedded-scene sample (cube faces at t-1
and t of one fisheye camera, the actors, the ego poses), its ground truth and its exact fisheye
oracle, computed once per session."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish as jf
from jaxfish import groundtruth as gt
from jaxfish.reprojection import CubeRig, build_lut, cube_face_size
from jaxfish.scene import generate_street, render_cube_faces, render_fisheye, render_pixels
from jaxfish.transforms import Pose

F32 = jnp.float32
#: Small fisheye of the scene tests (jaxfish's front camera resized).
WIDTH, HEIGHT = 128, 96
SEED, FRAME = 0, 3


@dataclasses.dataclass(frozen=True)
class Faces:
    """One camera's faces at one instant, stacked in the CubeRig order."""

    rgb: np.ndarray
    depth_m: np.ndarray
    semantic: np.ndarray
    actor_id: np.ndarray


@dataclasses.dataclass(frozen=True)
class Sample:
    """Everything the ground-truth tests share."""

    frame: object
    calib: object
    camera: object
    face_size: int
    lut: object
    faces_prev: Faces
    faces: Faces
    actors: list
    boxes_prev: gt.Boxes3D
    boxes: gt.Boxes3D
    vehicle_to_world_prev: Pose
    vehicle_to_world: Pose
    truth: gt.CameraGroundTruth
    oracle: object
    oracle_prev: object


def actor_dict(a) -> dict:
    """The capture's ``actors.json`` record of a scene actor (CARLA units)."""
    tr = lambda loc, rot: {"location": list(loc), "rotation": list(rot)}  # noqa: E731
    return {"id": a.id, "category": a.category, "bounding_box": {"location": list(a.bbox_location), "extent": list(a.bbox_extent)},
            "transform_prev": tr(a.location_prev, a.rotation_prev), "transform": tr(a.location, a.rotation)}


def _faces(frame, calib, size, time) -> Faces:
    bufs = render_cube_faces(frame, calib, size, time=time)
    names = list(bufs)
    get = lambda f: np.stack([f(bufs[n]) for n in names])  # noqa: E731
    return Faces(
        rgb=get(lambda b: np.clip(np.rint(np.asarray(b.rgb, np.float32) * 255), 0, 255).astype(np.uint8)),
        depth_m=get(lambda b: np.asarray(b.depth_m, np.float32)),
        semantic=get(lambda b: np.asarray(b.semantic).astype(np.uint8)),
        actor_id=get(lambda b: np.asarray(b.actor_id, np.int32)),
    )


@pytest.fixture(scope="session")
def sample() -> Sample:
    rig = jf.default_rig(width=WIDTH, height=HEIGHT, dtype=F32)
    calib = rig["FV"].astype(F32)
    cam = calib.camera.astype(F32)
    frame = generate_street(SEED, frame=FRAME, rig=rig)
    size = cube_face_size(cam)
    lut = jax.jit(build_lut)(CubeRig(size, dtype=F32), cam)
    fp, fc = _faces(frame, calib, size, 0.0), _faces(frame, calib, size, 1.0)
    actors = [actor_dict(a) for a in frame.actors]
    bp, bc = gt.boxes_from_actors(actors, "t-1"), gt.boxes_from_actors(actors, "t")
    e = frame.ego
    v2w_p = gt.vehicle_to_world_from_carla(np.asarray(e.location_prev, np.float32), np.asarray(e.rotation_prev, np.float32))
    v2w = gt.vehicle_to_world_from_carla(np.asarray(e.location, np.float32), np.asarray(e.rotation, np.float32))
    truth = gt.fisheye_ground_truth(lut, cam, calib.camera_to_vehicle, fp, fc, bp, bc, v2w_p, v2w, backward_flow=True)
    oracle = render_fisheye(frame, calib)
    pose_prev = frame.scene.camera_to_world(Pose(calib.camera_to_vehicle.rotation_matrix, calib.camera_to_vehicle.translation, dtype=F32), 0.0)
    oracle_prev = render_pixels(frame.scene, cam, pose_prev, cam.pixel_grid(F32), time=0.0)
    return Sample(frame, calib, cam, size, lut, fp, fc, actors, bp, bc, v2w_p, v2w, truth, oracle, oracle_prev)
