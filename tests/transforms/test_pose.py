"""Pose laws, quaternion order, CARLA get_matrix semantics and frame conversions."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import jaxfish as jf
from jaxfish.transforms import (
    carla_camera_pose_to_opencv,
    carla_pose_to_iso,
    carla_rotation_matrix,
    carla_to_iso,
    iso_pose_to_carla,
    matrix_to_quaternion_xyzw,
    opencv_camera_pose_to_carla,
    opencv_to_unreal_camera,
    quaternion_xyzw_to_matrix,
    unreal_camera_to_opencv,
)
from tests import tolerances as tol
from tests.helpers import three_ways


def _random_pose(seed: int, batch=()) -> jf.Pose:
    rng = np.random.default_rng(seed)
    r = Rotation.random(int(np.prod(batch)) or 1, random_state=seed).as_matrix().reshape(batch + (3, 3))
    return jf.Pose(r, rng.normal(size=batch + (3,)))


def test_quaternion_is_scalar_last_like_scipy():
    q = Rotation.random(50, random_state=0).as_quat()  # scipy: (x, y, z, w)
    np.testing.assert_allclose(np.asarray(quaternion_xyzw_to_matrix(q)), Rotation.from_quat(q).as_matrix(), atol=tol.POSE_F64)


def test_matrix_to_quaternion_roundtrip_including_half_turns():
    mats = np.concatenate([
        Rotation.random(200, random_state=1).as_matrix(),
        np.stack([np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1]), np.eye(3)]),
    ])
    q = np.asarray(matrix_to_quaternion_xyzw(mats))
    assert np.all(q[:, 3] >= 0)
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-14)
    np.testing.assert_allclose(np.asarray(quaternion_xyzw_to_matrix(q)), mats, atol=tol.POSE_F64)


def test_pose_laws():
    a, b, c = _random_pose(1), _random_pose(2), _random_pose(3)
    p = np.random.default_rng(4).normal(size=(10, 3))
    np.testing.assert_allclose(np.asarray((a @ b).apply(p)), np.asarray(a.apply(b.apply(p))), atol=tol.POSE_F64)
    np.testing.assert_allclose(np.asarray(((a @ b) @ c).as_matrix()), np.asarray((a @ (b @ c)).as_matrix()), atol=tol.POSE_F64)
    np.testing.assert_allclose(np.asarray((a @ a.inverse()).as_matrix()), np.eye(4), atol=tol.POSE_F64)
    np.testing.assert_allclose(np.asarray(jf.Pose.identity().apply(p)), p, atol=0)
    np.testing.assert_allclose(np.asarray(jf.Pose.from_matrix(a.as_matrix()).apply(p)), np.asarray(a.apply(p)), atol=tol.POSE_F64)
    # Rotations preserve lengths; rotate ignores the translation.
    np.testing.assert_allclose(np.linalg.norm(np.asarray(a.rotate(p)), axis=-1), np.linalg.norm(p, axis=-1), atol=1e-12)


def test_batched_pose_broadcasts():
    poses = _random_pose(5, batch=(4,))
    p = np.random.default_rng(6).normal(size=(4, 3))
    out = np.asarray(poses.apply(p))
    for i in range(4):
        expected = np.asarray(poses.rotation_matrix[i]) @ p[i] + np.asarray(poses.translation[i])
        np.testing.assert_allclose(out[i], expected, atol=tol.POSE_F64)
    # One pose, many points.
    one = _random_pose(7)
    np.testing.assert_allclose(np.asarray(one.apply(np.zeros((2, 5, 3)))), np.broadcast_to(np.asarray(one.translation), (2, 5, 3)))


def test_apply_eager_jit_vmap_and_gradient():
    pose = _random_pose(8)
    p = jnp.asarray(np.random.default_rng(9).normal(size=(3,)))
    eager, jitted, batched = three_ways(lambda q: pose.apply(q), p)
    np.testing.assert_allclose(eager, jitted, atol=tol.POSE_F64)
    np.testing.assert_allclose(eager, batched, atol=tol.POSE_F64)
    jac = jax.jacrev(lambda q: pose.apply(q))(p)
    np.testing.assert_allclose(np.asarray(jac), np.asarray(pose.rotation_matrix), atol=tol.POSE_F64)


def _carla_get_matrix(x, y, z, pitch, yaw, roll):
    """CARLA's Transform.get_matrix(), transcribed from CONVENTIONS §3 (degrees)."""
    cp, sp = np.cos(np.radians(pitch)), np.sin(np.radians(pitch))
    cy, sy = np.cos(np.radians(yaw)), np.sin(np.radians(yaw))
    cr, sr = np.cos(np.radians(roll)), np.sin(np.radians(roll))
    return np.array([
        [cp * cy, cy * sp * sr - sy * cr, -cy * sp * cr - sy * sr, x],
        [cp * sy, sy * sp * sr + cy * cr, -sy * sp * cr + cy * sr, y],
        [sp, -cp * sr, cp * cr, z],
        [0, 0, 0, 1],
    ])


@pytest.mark.parametrize("rot", [(0, 0, 0), (10, 20, 30), (-35, 170, -80), (89, -45, 12), (0, -90, 0), (90, 0, 0)])
def test_from_carla_matches_get_matrix_and_roundtrips(rot):
    loc = (1.5, -2.0, 0.7)
    pose = jf.Pose.from_carla(loc, rot)
    np.testing.assert_allclose(np.asarray(pose.as_matrix()), _carla_get_matrix(*loc, *rot), atol=tol.POSE_F64)
    loc2, rot2 = pose.as_carla()
    again = jf.Pose.from_carla(loc2, rot2)
    np.testing.assert_allclose(np.asarray(again.as_matrix()), np.asarray(pose.as_matrix()), atol=1e-9)


@pytest.mark.parametrize("rot", [(-90, 30, 0), (90, -45, 20), (-90, 170, -60)])
def test_as_carla_at_gimbal_lock_keeps_the_rotation_and_finite_gradients(rot):
    """Pitch +-90 with the matrix rounded exactly (a straight-down camera mount): yaw and roll are
    no longer separable, the rotation must survive (roll 0, yaw carries it) and so must gradients."""
    r = np.round(np.asarray(jf.Pose.from_carla(jnp.zeros(3), jnp.asarray(rot, jnp.float64)).rotation_matrix), 12)
    pose = jf.Pose(jnp.asarray(r), jnp.zeros(3))
    for _, angles in three_ways(lambda p: p.as_carla(), pose):
        assert angles[2] == 0.0 and abs(abs(angles[0]) - 90.0) < 1e-9
        again = jf.Pose.from_carla(jnp.zeros(3), jnp.asarray(angles))
        np.testing.assert_allclose(np.asarray(again.rotation_matrix), r, atol=1e-9)
    grad = jax.grad(lambda m: jnp.sum(jf.Pose(m, jnp.zeros(3)).as_carla()[1]))(jnp.asarray(r))
    assert bool(jnp.all(jnp.isfinite(grad)))


def test_carla_yaw_turns_towards_unreal_plus_y():
    # Unreal is left-handed: yaw +90 turns x (forward) to +y (right).
    np.testing.assert_allclose(np.asarray(carla_rotation_matrix(0.0, 90.0, 0.0)) @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    # Pitch +90 looks up.
    np.testing.assert_allclose(np.asarray(carla_rotation_matrix(90.0, 0.0, 0.0)) @ [1, 0, 0], [0, 0, 1], atol=1e-15)


def test_frame_conversions():
    p = np.array([[1.0, 2.0, 3.0]])
    np.testing.assert_allclose(np.asarray(carla_to_iso(p)), [[1.0, -2.0, 3.0]])
    np.testing.assert_allclose(np.asarray(unreal_camera_to_opencv(p)), [[2.0, -3.0, 1.0]])
    np.testing.assert_allclose(np.asarray(opencv_to_unreal_camera(unreal_camera_to_opencv(p))), p)
    pose = jf.Pose.from_carla((1.0, 2.0, 3.0), (10.0, 20.0, 30.0))
    iso = carla_pose_to_iso(pose)
    assert float(jnp.linalg.det(iso.rotation_matrix)) == pytest.approx(1.0)
    # Converting the points then applying = applying then converting.
    np.testing.assert_allclose(np.asarray(iso.apply(carla_to_iso(p))), np.asarray(carla_to_iso(pose.apply(p))), atol=tol.POSE_F64)
    np.testing.assert_allclose(np.asarray(iso_pose_to_carla(iso).as_matrix()), np.asarray(pose.as_matrix()), atol=tol.POSE_F64)


def test_carla_camera_mounting_roundtrip():
    # A CARLA camera on the ego vehicle, yawed right (+90 in Unreal) and pitched down 30 degrees.
    mount = jf.Pose.from_carla((0.8, 0.9, 1.0), (-30.0, 90.0, 0.0))
    cv = carla_camera_pose_to_opencv(mount)  # OpenCV camera -> ISO vehicle
    assert float(jnp.linalg.det(cv.rotation_matrix)) == pytest.approx(1.0)
    axis = np.asarray(cv.rotate(jnp.asarray([0.0, 0.0, 1.0])))
    # Looks to the vehicle's right (ISO -y) and down.
    np.testing.assert_allclose(axis, [0.0, -np.cos(np.radians(30)), -np.sin(np.radians(30))], atol=1e-12)
    down = np.asarray(cv.rotate(jnp.asarray([0.0, 1.0, 0.0])))
    assert down[2] < 0, "image 'down' points towards the ground"
    np.testing.assert_allclose(np.asarray(cv.translation), [0.8, -0.9, 1.0], atol=1e-15)
    back = opencv_camera_pose_to_carla(cv)
    np.testing.assert_allclose(np.asarray(back.as_matrix()), np.asarray(mount.as_matrix()), atol=1e-12)
    loc, rot = back.as_carla()
    np.testing.assert_allclose(np.asarray(rot), [-30.0, 90.0, 0.0], atol=1e-9)


def test_shape_errors():
    with pytest.raises(ValueError, match="rotation_matrix"):
        jf.Pose(np.eye(2), np.zeros(3))
    with pytest.raises(ValueError, match="translation"):
        jf.Pose(np.eye(3), np.zeros(2))
    with pytest.raises(ValueError, match="quaternion"):
        quaternion_xyzw_to_matrix(np.zeros(3))


def test_a_zero_quaternion_is_refused_never_a_silent_nan():
    from jaxfish.transforms import quaternion_xyzw_to_matrix

    for q in ([0.0, 0.0, 0.0, 0.0], [[0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0, 0.0]], [np.nan, 0.0, 0.0, 1.0],
              [np.inf, 0.0, 0.0, 1.0]):
        with pytest.raises(ValueError, match=r"quaternion \(x, y, z, w\) of norm 0 or with a non-finite component"):
            jf.Pose.from_quaternion_xyzw(q, np.zeros(np.shape(q)[:-1] + (3,)))
    with pytest.raises(Exception, match="of norm 0 or with a non-finite component"):  # inside jit: at run time
        jax.block_until_ready(jax.jit(quaternion_xyzw_to_matrix)(jnp.zeros(4)))
    r = jax.jit(quaternion_xyzw_to_matrix)(jnp.array([0.0, 0.0, 0.0, 2.0]))  # any non-zero norm is normalised
    np.testing.assert_allclose(r, np.eye(3), atol=1e-7)
