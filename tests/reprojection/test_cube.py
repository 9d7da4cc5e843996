"""The cube rig's face geometry against CARLA's conventions, computed independently."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish as jf
from jaxfish.reprojection import CUBE_FACE_ROTATIONS, SIX_FACES, CubeRig, cube_face_size

from ..tolerances import POSE_F64


def carla_get_matrix(pitch: float, yaw: float, roll: float) -> np.ndarray:
    """CARLA ``Transform.get_matrix()`` rotation (CONVENTIONS §3), typed in from the docs."""
    p, y, r = (math.radians(a) for a in (pitch, yaw, roll))
    cp, sp, cy, sy, cr, sr = math.cos(p), math.sin(p), math.cos(y), math.sin(y), math.cos(r), math.sin(r)
    return np.array(
        [
            [cp * cy, cy * sp * sr - sy * cr, -cy * sp * cr - sy * sr],
            [cp * sy, sy * sp * sr + cy * cr, -sy * sp * cr + cy * sr],
            [sp, -cp * sr, cp * cr],
        ]
    )


#: Unreal camera-local (x fwd, y right, z up) -> OpenCV (x right, y down, z fwd): (y, -z, x).
UNREAL_TO_CV = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])


@pytest.mark.parametrize("face", SIX_FACES)
def test_face_pose_matches_carla_get_matrix(face):
    rig = CubeRig(32, faces=SIX_FACES, dtype=jnp.float64)
    expected = UNREAL_TO_CV @ carla_get_matrix(*CUBE_FACE_ROTATIONS[face]) @ UNREAL_TO_CV.T
    np.testing.assert_allclose(np.asarray(rig.face_pose(face).rotation_matrix), expected, atol=POSE_F64)


# face -> (optical axis, direction of the face image's top edge, of its right edge), fisheye OpenCV frame
FACE_DIRECTIONS = {
    "front": ((0, 0, 1), (0, -1, 0), (1, 0, 0)),
    "left": ((-1, 0, 0), (0, -1, 0), (0, 0, 1)),  # its right edge looks forward
    "right": ((1, 0, 0), (0, -1, 0), (0, 0, -1)),
    "top": ((0, -1, 0), (0, 0, -1), (1, 0, 0)),  # pitch +90: image top looks backward
    "bottom": ((0, 1, 0), (0, 0, 1), (1, 0, 0)),
    "back": ((0, 0, -1), (0, -1, 0), (-1, 0, 0)),
}


@pytest.mark.parametrize("face", SIX_FACES)
def test_face_orientation_semantics(face):
    s = 32
    rig = CubeRig(s, faces=SIX_FACES, dtype=jnp.float64)
    c = (s - 1) / 2
    uv = jnp.asarray([[c, c], [c, -0.5], [s - 0.5, c]])
    rays, valid = rig.unproject_faces(jnp.full((3,), rig.face_index(face)), uv)
    axis, top, right = (np.asarray(d, float) for d in FACE_DIRECTIONS[face])
    expected = np.stack([axis, (axis + top) / math.sqrt(2), (axis + right) / math.sqrt(2)])
    np.testing.assert_allclose(np.asarray(rays), expected, atol=1e-12)
    assert np.all(np.asarray(valid))


def test_carla_face_intrinsics():
    rig = CubeRig(64, dtype=jnp.float64)
    assert float(rig.face.fx) == pytest.approx(32.0)  # S / (2 tan 45 deg)
    assert float(rig.face.cx) == pytest.approx(31.5) and float(rig.face.cy) == pytest.approx(31.5)


def test_dominant_axis_round_trip():
    rig = CubeRig(48, faces=SIX_FACES, dtype=jnp.float64)
    rng = np.random.default_rng(0)
    d = rng.normal(size=(2000, 3))
    face, uv, valid = rig.project_faces(jnp.asarray(d))
    assert np.all(np.asarray(valid))
    axes = np.asarray(rig.face_to_camera.rotation_matrix)[:, :, 2]
    np.testing.assert_array_equal(np.asarray(face), np.argmax(d @ axes.T, axis=-1))
    rays, _ = rig.unproject_faces(face, uv)
    np.testing.assert_allclose(np.asarray(rays), d / np.linalg.norm(d, axis=-1, keepdims=True), atol=1e-12)


def test_five_face_rig_does_not_see_behind():
    rig = CubeRig(16, dtype=jnp.float64)
    _, _, valid = rig.project_faces(jnp.asarray([[0.0, 0.0, -1.0], [0.1, 0.05, -1.0]]))
    assert not np.any(np.asarray(valid))


def test_face_size_never_undersamples(jit_unproject):
    cam = jf.resize_fisheye(jf.default_rig()["MVL"].camera, 160, 120).astype(jnp.float64)  # shares a compile
    s = cube_face_size(cam, multiple=1)
    rays, valid = jit_unproject(cam, cam.pixel_grid(jnp.float64))
    rays, valid = np.asarray(rays), np.asarray(valid)
    # Angle between horizontally / vertically adjacent fisheye pixels >= one face pixel at its centre (2/S rad).
    for a, b, va, vb in (
        (rays[:, 1:], rays[:, :-1], valid[:, 1:], valid[:, :-1]),
        (rays[1:], rays[:-1], valid[1:], valid[:-1]),
    ):
        ang = np.arccos(np.clip(np.sum(a * b, axis=-1), -1, 1))[va & vb]
        assert ang.min() >= (2.0 / s) * (1 - 1e-3)
    assert cube_face_size(cam, multiple=1, oversample=2.0) >= 2 * s - 2
    assert cube_face_size(cam) % 32 == 0
