"""Analytic optical flow: the scene flow of every pixel's 3D point, projected with the camera model.

Convention (also in ``docs/groundtruth.md``): **forward flow** is defined on the grid of the
*source* instant (t-1) and points to where the surface point seen there is at the *target* instant
(t): ``flow(p) = uv_t(P) - p`` in pixels, ``u`` right and ``v`` down. Backward flow swaps the
roles (defined on the t grid, pointing to t-1). Every point moves with the rigid motion of the
actor it belongs to (static points do not move); the camera moves with the ego vehicle, so every
point also undergoes the inverse camera motion.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._constants import FAR_DEPTH_M
from .._numerics import materialize, stack_last
from ..cameras import AbstractCamera
from ..transforms import CARLA_TO_ISO, Pose

OCCLUSION_REL_TOL = 0.03
"""Default relative tolerance of the occlusion test (predicted range vs the target range map)."""
FAR_RANGE_M = FAR_DEPTH_M
"""Far / sky range (metres): `jaxfish.reprojection.FAR_DEPTH_M` (CARLA's depth saturation) under the
name of range maps; SynWoodScape's sky value."""


class FlowField(eqx.Module):
    """Optical flow on the source grid, ``(H, W)`` per field.

    - `flow` ``(H, W, 2)``: ``(du, dv)`` pixels from the source pixel to the target position
      (0 where not `in_image`);
    - `valid`: the point projects inside the target image *and* is visible there (not occluded;
      always True when no target range map was given);
    - `in_image`: the source pixel has a ray and the moved point projects inside the target image;
    - `occluded` (a property, computed from the fields): `in_image` but hidden at the target (a
      nearer surface covers it there): exactly ``in_image & ~valid`` (never True when no target
      range map was given);
    - `target_uv` ``(H, W, 2)``: the target pixel position, `target_range_m` its predicted range.
    """

    flow: Float[Array, "*batch H W 2"]
    valid: Bool[Array, "*batch H W"]
    in_image: Bool[Array, "*batch H W"]
    target_uv: Float[Array, "*batch H W 2"]
    target_range_m: Float[Array, "*batch H W"]

    @property
    def occluded(self) -> Bool[Array, "*batch H W"]:
        """The occlusion mask: the point projects inside the target image but is hidden there
        (``in_image & ~valid``). A property, not a field: the jitted flow programs are unchanged."""
        return self.in_image & ~self.valid


def vehicle_to_world_from_carla(location: Float[ArrayLike, "*batch 3"], rotation: Float[ArrayLike, "*batch 3"], *, dtype=None) -> Pose:
    """ISO 8855 ego vehicle frame -> CARLA world of an ego actor whose CARLA transform is
    ``(location, (pitch, yaw, roll))``: ``Pose.from_carla(...) @ diag(1, -1, 1)`` (determinant -1)."""
    ego = Pose.from_carla(location, rotation, dtype=dtype)
    s = jnp.asarray(CARLA_TO_ISO, ego.rotation_matrix.dtype)
    return Pose(ego.rotation_matrix @ s, ego.translation)


def apply_pose(pose: Pose, points: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3"]:
    """``R p + t`` for one (unbatched) pose and any number of points, written as multiply-adds on
    coordinate planes (on CPU XLA fuses these, unlike the einsum of `Pose.apply`, into vectorised
    loops over image-sized arrays). Batch poses with `jax.vmap`."""
    p = jnp.asarray(points)
    r = pose.rotation_matrix.astype(p.dtype)
    t = pose.translation.astype(p.dtype)
    if r.shape != (3, 3):
        raise ValueError(f"apply_pose: expects one pose (3 x 3 rotation), got {r.shape}; use jax.vmap for batches")
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    return jnp.stack([r[i, 0] * x + r[i, 1] * y + r[i, 2] * z + t[i] for i in range(3)], axis=-1)


def rigid_motion(pose_from: Pose, pose_to: Pose) -> Pose:
    """World -> world motion of a rigid body whose local -> world pose goes from ``pose_from`` to
    ``pose_to``: ``pose_to @ pose_from.inverse()`` (batched over actors)."""
    return pose_to @ pose_from.inverse()


def pixel_rays(camera: AbstractCamera, *, dtype=jnp.float32) -> tuple[Float[Array, "H W 3"], Bool[Array, "H W"]]:
    """Unit rays (camera frame) and validity of every pixel centre: a per-calibration constant that
    `pixel_points`, `analytic_flow` and `fisheye_ground_truth` accept precomputed (``rays=``), which
    saves one fisheye unprojection (a Newton solve per pixel) per call."""
    return camera.unproject(camera.pixel_grid(dtype))


def pixel_points(
    camera: AbstractCamera, range_m: Float[ArrayLike, "H W"], *, dtype=None,
    rays: tuple[Float[ArrayLike, "H W 3"], Bool[ArrayLike, "H W"]] | None = None,
) -> tuple[Float[Array, "H W 3"], Bool[Array, "H W"]]:
    """Camera-frame 3D point of every pixel centre: ``origin + range * ray`` (metres). ``range_m``
    is the Euclidean range along the ray (for `Orthographic`, the distance from the image plane);
    ``rays`` optionally gives `pixel_rays` precomputed."""
    r = jnp.asarray(range_m)
    dtype = dtype or (r.dtype if jnp.issubdtype(r.dtype, jnp.floating) else jnp.float32)
    grid = camera.pixel_grid(dtype)
    if tuple(r.shape[-2:]) != tuple(grid.shape[:2]):
        raise ValueError(f"pixel_points: range map {r.shape} does not match the camera's image {grid.shape[:2]}")
    rays, ok = camera.unproject(grid) if rays is None else (jnp.asarray(rays[0]), jnp.asarray(rays[1], bool))
    pts = camera.ray_origins(grid).astype(dtype) + r.astype(dtype)[..., None] * rays.astype(dtype)
    return jnp.where(ok[..., None], pts, 0.0), ok


def _sample_taps(img: Array, uv: Array) -> Array:
    """The 4 bilinear taps (nearest 2 x 2 pixels, clamped) of ``img (H, W)`` at ``uv (..., 2)``."""
    h, w = img.shape
    flat = img.reshape(-1)
    x0 = jnp.clip(jnp.floor(uv[..., 0]), 0, w - 1).astype(jnp.int32)
    y0 = jnp.clip(jnp.floor(uv[..., 1]), 0, h - 1).astype(jnp.int32)
    x1 = jnp.clip(x0 + 1, 0, w - 1)
    y1 = jnp.clip(y0 + 1, 0, h - 1)
    g = lambda yy, xx: jnp.take(flat, yy * w + xx)  # noqa: E731
    return jnp.stack([g(y0, x0), g(y0, x1), g(y1, x0), g(y1, x1)], axis=-1)


def analytic_flow(
    camera: AbstractCamera,
    range_m: Float[ArrayLike, "H W"],
    actor_index: Int[ArrayLike, "H W"],
    actor_motion: Pose,
    camera_to_world_source: Pose,
    camera_to_world_target: Pose,
    *,
    target_camera: AbstractCamera | None = None,
    target_range_m: Float[ArrayLike, "H W"] | None = None,
    occlusion_rel_tol: float = OCCLUSION_REL_TOL,
    valid: Bool[ArrayLike, "H W"] | None = None,
    rays: tuple[Float[ArrayLike, "H W 3"], Bool[ArrayLike, "H W"]] | None = None,
) -> FlowField:
    """Optical flow of every source pixel from its range, its actor and the poses.

    - ``range_m``: range along each source pixel's ray (metres; sky/far points at 1000 m are static
      points at that range);
    - ``actor_index``: per pixel, the index into ``actor_motion`` of the actor the point belongs to,
      or -1 for static points;
    - ``actor_motion``: batched `Pose` ``(A,)`` of world -> world rigid motions from the source to
      the target instant (`rigid_motion` of the actors' transforms); ``A`` may be 0;
    - ``camera_to_world_*``: camera (OpenCV) -> world at the source and target instants;
    - ``target_camera``: the model projecting at the target (default ``camera``: the same camera);
    - ``rays``: the source camera's `pixel_rays`, precomputed (optional);
    - ``target_range_m``: range map of the target image; when given, points hidden at the target
      (their predicted range exceeds every one of the 4 nearest target ranges by more than
      ``occlusion_rel_tol``) are not `valid`.

    Pure JAX: jit/vmap-safe (vmap over frames or cameras with batched poses).
    """
    tgt_cam = camera if target_camera is None else target_camera
    r = jnp.asarray(range_m)
    dtype = r.dtype if jnp.issubdtype(r.dtype, jnp.floating) else jnp.float32
    pts, ok = pixel_points(camera, r, dtype=dtype, rays=rays)
    if valid is not None:
        ok = ok & jnp.asarray(valid, bool)
    # Coordinate planes from here on: on CPU, XLA fuses the producers of every minor-axis stack into
    # a loop that does not vectorise.
    x, y, z = _pose_planes(camera_to_world_source, pts[..., 0], pts[..., 1], pts[..., 2])
    idx = jnp.asarray(actor_index).astype(jnp.int32)
    n_act = actor_motion.rotation_matrix.shape[0]
    if n_act > 0:
        # One scalar gather per matrix entry from a (A, 12) table, then multiply-adds on (H, W)
        # planes: on CPU these vectorise, a gather of (H, W, 3, 3) matrices does not.
        table = jnp.concatenate([actor_motion.rotation_matrix.reshape(n_act, 9), actor_motion.translation], axis=-1).astype(dtype)
        k = jnp.clip(idx, 0, n_act - 1)
        m = [jnp.take(table[:, j], k) for j in range(12)]
        moved = [m[3 * i] * x + m[3 * i + 1] * y + m[3 * i + 2] * z + m[9 + i] for i in range(3)]
        dyn = idx >= 0
        x, y, z = (jnp.where(dyn, a, b) for a, b in zip(moved, (x, y, z), strict=True))
        # Materialise the moved points: XLA on CPU would fuse the gathers into the projection below,
        # and a loop fusion holding a gather is not vectorised.
        x, y, z = materialize((x, y, z), r.reshape(-1)[0].astype(dtype))
    px, py, pz = _pose_planes(camera_to_world_target.inverse(), x, y, z)
    p_tgt = stack_last([px, py, pz])
    uv, ok_proj = tgt_cam.project(p_tgt)
    if tgt_cam.is_central:
        pred_range = jnp.sqrt(px * px + py * py + pz * pz)
    else:
        rays_t, ok_t = tgt_cam.unproject(uv)
        pred_range = jnp.sum((p_tgt - tgt_cam.ray_origins(uv).astype(dtype)) * rays_t.astype(dtype), axis=-1)
        ok_proj = ok_proj & ok_t
    u, v = uv[..., 0].astype(dtype), uv[..., 1].astype(dtype)
    # Materialise the projection once: otherwise XLA fuses (and recomputes) it into every consumer
    # below (the four occlusion taps, the flow, the range).
    u, v, ok_proj, pred_range = materialize((u, v, ok_proj, pred_range), r.reshape(-1)[0].astype(dtype))
    in_image = ok & ok_proj & (u >= -0.5) & (u <= tgt_cam.width - 0.5) & (v >= -0.5) & (v <= tgt_cam.height - 0.5)
    vis = in_image
    if target_range_m is not None:
        tr = jnp.asarray(target_range_m).astype(dtype)
        th, tw = tr.shape
        flat = tr.reshape(-1)
        x0 = jnp.clip(jnp.floor(u), 0, tw - 1).astype(jnp.int32)
        y0 = jnp.clip(jnp.floor(v), 0, th - 1).astype(jnp.int32)
        x1 = jnp.minimum(x0 + 1, tw - 1)
        y1 = jnp.minimum(y0 + 1, th - 1)
        tol = jnp.asarray(occlusion_rel_tol, dtype)
        far = jnp.asarray(FAR_DEPTH_M, dtype)
        near_limit = pred_range * (1 - tol)
        far_point = pred_range >= far * (1 - tol)
        # Seen (not occluded) when one of the 4 nearest target ranges reaches the predicted range.
        seen = jnp.zeros(u.shape, bool)
        for yy, xx in ((y0, x0), (y0, x1), (y1, x0), (y1, x1)):
            t = flat[yy * tw + xx]
            seen = seen | (t >= near_limit) | (far_point & (t >= far))
        vis = vis & seen
    h, w = r.shape[-2:]
    gu, gv = jnp.meshgrid(jnp.arange(w, dtype=dtype), jnp.arange(h, dtype=dtype), indexing="xy")
    zero = jnp.zeros((), dtype)
    return FlowField(flow=stack_last([jnp.where(in_image, u - gu, zero), jnp.where(in_image, v - gv, zero)]), valid=vis,
                     in_image=in_image, target_uv=stack_last([jnp.where(in_image, u, zero), jnp.where(in_image, v, zero)]),
                     target_range_m=jnp.where(in_image, pred_range, zero))


def _pose_planes(pose: Pose, x, y, z):
    """``R p + t`` of one (unbatched) pose on coordinate planes."""
    r = pose.rotation_matrix.astype(x.dtype)
    t = pose.translation.astype(x.dtype)
    return tuple(r[i, 0] * x + r[i, 1] * y + r[i, 2] * z + t[i] for i in range(3))


def warp_with_flow(image: Float[ArrayLike, "H W C"], flow: Float[ArrayLike, "H W 2"]) -> Float[Array, "H W C"]:
    """Sample ``image`` bilinearly at ``grid + flow`` (clamped at the border): with forward flow
    (t-1 grid) and the image at t, this reconstructs the image at t-1 on its valid pixels."""
    img = jnp.asarray(image)
    f = jnp.asarray(flow)
    h, w = img.shape[:2]
    dtype = f.dtype
    uu, vv = jnp.meshgrid(jnp.arange(w, dtype=dtype), jnp.arange(h, dtype=dtype), indexing="xy")
    u = jnp.clip(uu + f[..., 0], 0, w - 1)
    v = jnp.clip(vv + f[..., 1], 0, h - 1)
    x0 = jnp.clip(jnp.floor(u), 0, max(w - 2, 0)).astype(jnp.int32)
    y0 = jnp.clip(jnp.floor(v), 0, max(h - 2, 0)).astype(jnp.int32)
    fx = (u - x0.astype(dtype))[..., None]
    fy = (v - y0.astype(dtype))[..., None]
    im = img.astype(dtype)
    top = im[y0, x0] + (im[y0, x0 + 1] - im[y0, x0]) * fx
    bot = im[y0 + 1, x0] + (im[y0 + 1, x0 + 1] - im[y0 + 1, x0]) * fx
    return top + (bot - top) * fy
