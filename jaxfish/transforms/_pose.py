"""Rigid transforms (rotation + translation) as an immutable pytree."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._numerics import eps_for, float_dtype, resolve_dtype, stack_last


def _check_trailing(x: Array, shape: tuple[int, ...], what: str) -> None:
    if x.shape[x.ndim - len(shape) :] != shape:
        raise ValueError(f"{what} must have shape (..., {', '.join(map(str, shape))}), got {x.shape}")


def _matvec(r: Float[Array, "*b 3 3"], v: Float[Array, "*b 3"]) -> Float[Array, "*b 3"]:
    """``r @ v`` over broadcast batch axes as explicit multiply-adds.

    Written out because XLA:CPU lowers an einsum / dot_general with a tiny contraction over
    image-sized batches far slower than these fused elementwise products.
    """
    rows = [r[..., i, 0] * v[..., 0] + r[..., i, 1] * v[..., 1] + r[..., i, 2] * v[..., 2] for i in range(3)]
    return stack_last(rows)


def quaternion_xyzw_to_matrix(q: Float[ArrayLike, "*batch 4"]) -> Float[Array, "*batch 3 3"]:
    """Rotation matrix of a **scalar-last** quaternion ``(x, y, z, w)`` (normalised first).

    A quaternion of norm 0 (or with a non-finite component) has no rotation: concrete inputs raise
    ``ValueError``; traced ones (inside ``jit``) raise at run time through `equinox.error_if`
    (a ``JaxRuntimeError`` carrying the same message). Never a silent NaN matrix."""
    q = jnp.asarray(q)
    _check_trailing(q, (4,), "quaternion")
    norm = jnp.linalg.norm(q, axis=-1, keepdims=True)
    bad = ~(jnp.isfinite(norm) & (norm > 0))
    message = "quaternion (x, y, z, w) of norm 0 or with a non-finite component: it has no rotation"
    if isinstance(q, jax.core.Tracer) or isinstance(bad, jax.core.Tracer):
        q = eqx.error_if(q, bad, message)
    elif bool(np.any(np.asarray(bad))):
        first = np.asarray(q).reshape(-1, 4)[int(np.argmax(np.asarray(bad).reshape(-1)))]
        raise ValueError(f"{message}, got {first.tolist()}")
    q = q / norm
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def matrix_to_quaternion_xyzw(r: Float[ArrayLike, "*batch 3 3"]) -> Float[Array, "*batch 4"]:
    """Scalar-last unit quaternion ``(x, y, z, w)`` with ``w >= 0`` of a rotation matrix.

    Shepperd's method: the largest of the four candidate denominators is used, so it is exact and
    finite for every rotation (including 180-degree ones).
    """
    r = jnp.asarray(r)
    _check_trailing(r, (3, 3), "rotation matrix")
    m00, m11, m22 = r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]
    trace = m00 + m11 + m22
    cands = jnp.stack([trace, m00, m11, m22], axis=-1)
    which = jnp.argmax(cands, axis=-1)
    one = jnp.ones_like(trace)

    def branch(s_sq, fn):
        s = jnp.sqrt(jnp.maximum(s_sq, 1e-30 * one)) * 2  # s = 4 * |component|
        return fn(s)

    q_w = branch(1 + trace, lambda s: jnp.stack(
        [(r[..., 2, 1] - r[..., 1, 2]) / s, (r[..., 0, 2] - r[..., 2, 0]) / s, (r[..., 1, 0] - r[..., 0, 1]) / s, s / 4], -1))
    q_x = branch(1 + m00 - m11 - m22, lambda s: jnp.stack(
        [s / 4, (r[..., 0, 1] + r[..., 1, 0]) / s, (r[..., 0, 2] + r[..., 2, 0]) / s, (r[..., 2, 1] - r[..., 1, 2]) / s], -1))
    q_y = branch(1 - m00 + m11 - m22, lambda s: jnp.stack(
        [(r[..., 0, 1] + r[..., 1, 0]) / s, s / 4, (r[..., 1, 2] + r[..., 2, 1]) / s, (r[..., 0, 2] - r[..., 2, 0]) / s], -1))
    q_z = branch(1 - m00 - m11 + m22, lambda s: jnp.stack(
        [(r[..., 0, 2] + r[..., 2, 0]) / s, (r[..., 1, 2] + r[..., 2, 1]) / s, s / 4, (r[..., 1, 0] - r[..., 0, 1]) / s], -1))
    w = which[..., None]
    q = jnp.where(w == 0, q_w, jnp.where(w == 1, q_x, jnp.where(w == 2, q_y, q_z)))
    q = jnp.where(q[..., 3:4] < 0, -q, q)
    return q / jnp.linalg.norm(q, axis=-1, keepdims=True)


def carla_rotation_matrix(
    pitch_deg: ArrayLike, yaw_deg: ArrayLike, roll_deg: ArrayLike, *, dtype=None
) -> Float[Array, "*batch 3 3"]:
    """The rotation block of CARLA's ``Transform.get_matrix()`` (Unreal, left-handed, degrees)."""
    dtype = resolve_dtype(dtype, pitch_deg, yaw_deg, roll_deg)
    p = jnp.deg2rad(jnp.asarray(pitch_deg, dtype))
    y = jnp.deg2rad(jnp.asarray(yaw_deg, dtype))
    r = jnp.deg2rad(jnp.asarray(roll_deg, dtype))
    cp, sp, cy, sy, cr, sr = jnp.cos(p), jnp.sin(p), jnp.cos(y), jnp.sin(y), jnp.cos(r), jnp.sin(r)
    rows = [
        [cp * cy, cy * sp * sr - sy * cr, -cy * sp * cr - sy * sr],
        [cp * sy, sy * sp * sr + cy * cr, -sy * sp * cr + cy * sr],
        [sp, -cp * sr, cp * cr],
    ]
    return jnp.stack([jnp.stack(row, axis=-1) for row in rows], axis=-2)


class Pose(eqx.Module):
    """A rigid transform ``p -> R p + t`` from a *source* frame to a *target* frame.

    Named by what it maps, e.g. ``camera_to_vehicle``. Fields may carry leading batch axes
    (``rotation_matrix (..., 3, 3)``, ``translation (..., 3)``, metres); every method broadcasts.
    Compose with ``a @ b`` (apply ``b`` first, then ``a``).
    """

    rotation_matrix: Float[Array, "*batch 3 3"]
    translation: Float[Array, "*batch 3"]

    def __init__(self, rotation_matrix: Float[ArrayLike, "*batch 3 3"], translation: Float[ArrayLike, "*batch 3"], *, dtype=None):
        dtype = resolve_dtype(dtype, rotation_matrix, translation)
        rot = jnp.asarray(rotation_matrix, dtype=dtype)
        t = jnp.asarray(translation, dtype=dtype)
        _check_trailing(rot, (3, 3), "Pose.rotation_matrix")
        _check_trailing(t, (3,), "Pose.translation")
        self.rotation_matrix = rot
        self.translation = t

    # ------------------------------------------------------------------ constructors
    @classmethod
    def identity(cls, *, dtype=None) -> Pose:
        """The identity transform."""
        dtype = resolve_dtype(dtype, )
        return cls(jnp.eye(3, dtype=dtype), jnp.zeros(3, dtype=dtype))

    @classmethod
    def from_quaternion_xyzw(cls, quaternion: Float[ArrayLike, "*batch 4"], translation: Float[ArrayLike, "*batch 3"], *, dtype=None) -> Pose:
        """From a **scalar-last** quaternion ``(x, y, z, w)`` (WoodScape / scipy order, normalised
        first) and a translation; a quaternion of norm 0 raises (see `quaternion_xyzw_to_matrix`)."""
        dtype = resolve_dtype(dtype, quaternion, translation)
        return cls(quaternion_xyzw_to_matrix(jnp.asarray(quaternion, dtype)), translation, dtype=dtype)

    @classmethod
    def from_matrix(cls, matrix: Float[ArrayLike, "*batch 4 4"], *, dtype=None) -> Pose:
        """From a homogeneous ``(..., 4, 4)`` or ``(..., 3, 4)`` matrix."""
        m = jnp.asarray(matrix)
        if m.shape[-1] != 4 or m.shape[-2] not in (3, 4):
            raise ValueError(f"Pose.from_matrix: expected (..., 4, 4) or (..., 3, 4), got {m.shape}")
        return cls(m[..., :3, :3], m[..., :3, 3], dtype=dtype)

    @classmethod
    def from_carla(cls, location: Float[ArrayLike, "*batch 3"], rotation: Float[ArrayLike, "*batch 3"], *, dtype=None) -> Pose:
        """CARLA ``Transform(Location(x, y, z), Rotation(pitch, yaw, roll))`` with
        ``get_matrix()`` semantics: actor-local -> parent (world), both in Unreal's left-handed
        frame (x forward, y right, z up), angles in degrees as ``(pitch, yaw, roll)``."""
        rot = jnp.asarray(rotation)
        dtype = resolve_dtype(dtype, location, rotation)
        _check_trailing(rot, (3,), "Pose.from_carla rotation (pitch, yaw, roll)")
        r = carla_rotation_matrix(rot[..., 0], rot[..., 1], rot[..., 2], dtype=dtype)
        return cls(r, location, dtype=dtype)

    # ------------------------------------------------------------------ operations
    def apply(self, points: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 3"]:
        """Transform points: ``R p + t`` (in the points' floating dtype)."""
        p = jnp.asarray(points)
        dtype = float_dtype(p, self.translation)
        return self.rotate(p.astype(dtype)) + self.translation.astype(dtype)

    def rotate(self, vectors: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 3"]:
        """Rotate direction vectors: ``R v`` (no translation)."""
        v = jnp.asarray(vectors)
        _check_trailing(v, (3,), "vectors")
        dtype = float_dtype(v, self.rotation_matrix)
        return _matvec(self.rotation_matrix.astype(dtype), v.astype(dtype))

    def inverse(self) -> Pose:
        """The inverse transform ``p -> R^T (p - t)``."""
        rt = jnp.swapaxes(self.rotation_matrix, -1, -2)
        return Pose(rt, -_matvec(rt, self.translation))

    def compose(self, other: Pose) -> Pose:
        """``self ∘ other``: first `other`, then `self`."""
        r = jnp.einsum("...ij,...jk->...ik", self.rotation_matrix, other.rotation_matrix)
        t = _matvec(self.rotation_matrix, other.translation) + self.translation
        return Pose(r, t)

    def __matmul__(self, other: Pose) -> Pose:
        return self.compose(other)

    def as_matrix(self) -> Float[Array, "*batch 4 4"]:
        """Homogeneous ``(..., 4, 4)`` matrix."""
        top = jnp.concatenate([self.rotation_matrix, self.translation[..., None]], axis=-1)
        bottom = jnp.broadcast_to(
            jnp.asarray([0.0, 0.0, 0.0, 1.0], self.translation.dtype), top.shape[:-2] + (1, 4)
        )
        return jnp.concatenate([top, bottom], axis=-2)

    def as_quaternion_xyzw(self) -> Float[Array, "*batch 4"]:
        """Scalar-last unit quaternion ``(x, y, z, w)``, ``w >= 0``."""
        return matrix_to_quaternion_xyzw(self.rotation_matrix)

    def as_carla(self) -> tuple[Float[Array, "*batch 3"], Float[Array, "*batch 3"]]:
        """``(location, (pitch, yaw, roll) in degrees)`` such that `from_carla` gives this pose back
        (the pose must be expressed in Unreal's frame). Pitch is in [-90, 90]. At pitch +-90 (gimbal
        lock: only yaw - roll or yaw + roll is defined) roll is 0 and yaw carries the rotation;
        values and gradients stay finite."""
        r = self.rotation_matrix
        one, zero = jnp.ones_like(r[..., 0, 0]), jnp.zeros_like(r[..., 0, 0])
        cp2 = r[..., 0, 0] ** 2 + r[..., 1, 0] ** 2
        lock = cp2 <= eps_for(r.dtype)  # cos(pitch) below ~sqrt(eps)
        cp = jnp.sqrt(jnp.where(lock, one, cp2))
        pitch = jnp.where(lock, jnp.sign(r[..., 2, 0]) * (jnp.pi / 2), jnp.arctan2(r[..., 2, 0], cp))
        free_yaw = jnp.arctan2(jnp.where(lock, zero, r[..., 1, 0]), jnp.where(lock, one, r[..., 0, 0]))
        # roll = 0 in carla_rotation_matrix leaves column 1 = (-sin yaw, cos yaw, 0)
        safe01 = jnp.where(lock, -r[..., 0, 1], zero)
        safe11 = jnp.where(lock, r[..., 1, 1], one)
        yaw = jnp.where(lock, jnp.arctan2(safe01, safe11), free_yaw)
        roll = jnp.where(lock, zero, jnp.arctan2(jnp.where(lock, zero, -r[..., 2, 1]), jnp.where(lock, one, r[..., 2, 2])))
        return self.translation, jnp.rad2deg(jnp.stack([pitch, yaw, roll], axis=-1))
