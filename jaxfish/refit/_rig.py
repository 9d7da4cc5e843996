"""Joint refit of a camera rig: every camera's intrinsics and mounting, and one pose per target
view shared by the cameras that see it (as kalibr's multi-camera calibration), with the
Gauss-Newton covariance of every free parameter.

Residual of correspondence ``i`` of camera ``c`` in target view ``v``::

    project_c( R_cvᵀ (R_v p_i + t_v - t_cv) ) - pixel_i

with ``(R_cv, t_cv)`` camera ``c`` -> vehicle (the calibration's ``camera_to_vehicle``) and
``(R_v, t_v)`` target view ``v`` -> vehicle. The gauge (a rigid motion of everything) is fixed by
holding one reference camera's mounting, or by target poses known in the vehicle frame.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from ..calibration import Calibration
from ..transforms import Pose
from ._fit import (
    LOSSES,
    Correspondences,
    default_tolerances,
    free_parameter_mask,
    jit_unproject,
    pose_from_rays,
    robust_factor,
    rotation_from_vector,
)
from ._parameters import intrinsics_vector, parameter_names, with_intrinsics

POSE_COMPONENTS = ("rx", "ry", "rz", "tx", "ty", "tz")
"""Names of a pose's 6 free parameters: a rotation vector ``ω`` (radians) perturbing the rotation as
``R <- exp([ω]x) R`` and a translation increment (metres), both in the vehicle frame."""


class RigRefitResult(eqx.Module):
    """The outcome of `refit_rig`.

    - `calibrations`: the fitted calibrations, in the input order (same names, models and flavors);
    - `target_poses` ``(n_targets,)``: target -> vehicle poses;
    - `residuals` / `valid`: per camera, ``(N_c, 2)`` pixels (``project - pixel``) and ``(N_c,)``;
    - `rms_px`: ``sqrt(mean |r|²)`` over the valid points of every camera; `per_camera_rms_px`
      ``(n_cameras,)``;
    - `parameter_names` / `parameters`: the free parameters: ``CAM.PARAM`` intrinsics (values),
      ``CAM.rx`` ... ``CAM.tz`` mounting perturbations and ``TARGET.rx`` ... ``TARGET.tz`` target
      pose perturbations (0 at the solution; see `POSE_COMPONENTS`);
    - `covariance` ``(P, P)``: ``σ² (JᵀJ)⁻¹`` at the solution with ``σ² = sum |r'|² / (2N - P)``
      (NaN throughout when the data do not determine the free parameters: `determined`);
      `standard_deviations` its root diagonal;
    - `num_steps`, `converged`: of the Levenberg-Marquardt solve.
    """

    calibrations: tuple[Calibration, ...]
    target_poses: Pose
    residuals: tuple[Float[Array, "N 2"], ...]
    valid: tuple[Bool[Array, " N"], ...]
    rms_px: Float[Array, ""]
    per_camera_rms_px: Float[Array, " C"]
    parameters: Float[Array, " P"]
    covariance: Float[Array, "P P"]
    standard_deviations: Float[Array, " P"]
    num_steps: Int[Array, ""]
    converged: Bool[Array, ""]
    parameter_names: tuple[str, ...] = eqx.field(static=True)
    target_names: tuple[str, ...] = eqx.field(static=True)

    @property
    def determined(self) -> bool:
        """Whether the data determine every free parameter (the covariance is finite)."""
        return bool(np.all(np.isfinite(np.asarray(self.covariance))))

    def standard_deviation(self, name: str) -> float:
        """The standard deviation of one free parameter, by name (``"FV.fx"``, ``"MVL.tx"``)."""
        if name not in self.parameter_names:
            raise KeyError(f"{name!r} is not a free parameter (free: {', '.join(self.parameter_names)})")
        return float(self.standard_deviations[self.parameter_names.index(name)])

    def calibration(self, name: str) -> Calibration:
        """The fitted calibration of one camera, by name."""
        for c in self.calibrations:
            if c.name == name:
                return c
        raise KeyError(f"no camera {name!r} (cameras: {', '.join(c.name for c in self.calibrations)})")


def _unpack(z, p0s, scales, ext_r0, ext_t0, tgt_r0, tgt_t0):
    off = 0
    ps = []
    for p0 in p0s:
        n = p0.shape[0]
        ps.append(p0 + scales[off:off + n] * z[off:off + n])
        off += n
    c, v = ext_r0.shape[0], tgt_r0.shape[0]
    de = (scales[off:off + 6 * c] * z[off:off + 6 * c]).reshape(c, 6)
    off += 6 * c
    dt = (scales[off:off + 6 * v] * z[off:off + 6 * v]).reshape(v, 6)
    ext_r = rotation_from_vector(de[:, :3]) @ ext_r0
    tgt_r = rotation_from_vector(dt[:, :3]) @ tgt_r0
    return ps, ext_r, ext_t0 + de[:, 3:], tgt_r, tgt_t0 + dt[:, 3:]


def _camera_residuals(cam, ext_r, ext_t, tgt_r, tgt_t, corr, loss_code, loss_scale):
    pv = jnp.einsum("nij,nj->ni", tgt_r[corr.view], corr.points) + tgt_t[corr.view]
    pc = (pv - ext_t) @ ext_r  # R_cvᵀ (p - t_cv), row vectors
    uv, valid = cam.project(pc)
    res = uv - corr.pixels
    w = corr.weight
    root_w = jnp.where(w > 0, jnp.sqrt(jnp.where(w > 0, w, 1.0)), 0.0)
    factor = robust_factor(jnp.sum(res * res, axis=-1), loss_code, loss_scale) * root_w
    return res * factor[:, None], res, valid & (w > 0)


def _residual_fn(z, args):
    cameras, p0s, scales, ext_r0, ext_t0, tgt_r0, tgt_t0, corrs, loss_code, loss_scale = args
    ps, er, et, tr, tt = _unpack(z, p0s, scales, ext_r0, ext_t0, tgt_r0, tgt_t0)
    out = [_camera_residuals(with_intrinsics(cam, p), er[i], et[i], tr, tt, corr, loss_code, loss_scale)[0].ravel()
           for i, (cam, p, corr) in enumerate(zip(cameras, ps, corrs, strict=True))]
    return jnp.concatenate(out)


@eqx.filter_jit
def _solve_rig(cameras, p0s, free, ext_r0, ext_t0, tgt_r0, tgt_t0, corrs, loss_code, loss_scale, max_steps, rtol, atol):
    dtype = p0s[0].dtype
    z0 = jnp.zeros(free.shape[0], dtype)

    def fn(z, scales):
        return _residual_fn(z, (cameras, p0s, scales, ext_r0, ext_t0, tgt_r0, tgt_t0, corrs, loss_code, loss_scale))

    jac0 = jax.jacfwd(fn)(z0, free)
    col = jnp.sqrt(jnp.sum(jac0 * jac0, axis=0))
    scales = free * jnp.where(col > 0, 1.0 / jnp.where(col > 0, col, 1.0), 1.0)
    args = (cameras, p0s, scales, ext_r0, ext_t0, tgt_r0, tgt_t0, corrs, loss_code, loss_scale)
    sol = optx.least_squares(_residual_fn, optx.LevenbergMarquardt(rtol=rtol, atol=atol), z0, args=args,
                             max_steps=max_steps, throw=False)
    ps, er, et, tr, tt = _unpack(sol.value, p0s, scales, ext_r0, ext_t0, tgt_r0, tgt_t0)
    # Covariance in natural units around the solution (pose perturbations re-based at 0).
    args_sol = (cameras, tuple(ps), free, er, et, tr, tt, corrs, loss_code, loss_scale)
    jac = jax.jacfwd(lambda zz: _residual_fn(zz, args_sol))(z0)
    r = _residual_fn(z0, args_sol)
    n_used = sum(jnp.sum(c.weight > 0) for c in corrs).astype(dtype)
    dof = jnp.maximum(2 * n_used - jnp.sum(free), 1.0)
    sigma2 = jnp.sum(r * r) / dof
    fixed_diag = jnp.diag(1.0 - free)
    cov = sigma2 * (jnp.linalg.inv(jac.T @ jac + fixed_diag) - fixed_diag)
    cov = 0.5 * (cov + cov.T)
    norms = jnp.sqrt(jnp.sum(jac * jac, axis=0))
    singular = jnp.linalg.svd(jac / jnp.where(norms > 0, norms, 1.0), compute_uv=False)
    tol = jnp.max(singular) * max(jac.shape) * jnp.finfo(dtype).eps
    determined = jnp.sum(singular > tol).astype(dtype) >= jnp.sum(free)
    cov = jnp.where(determined, cov, jnp.nan)
    summaries = []
    for i, (cam, p, corr) in enumerate(zip(cameras, ps, corrs, strict=True)):
        _, res, valid = _camera_residuals(with_intrinsics(cam, p), er[i], et[i], tr, tt, corr, jnp.asarray(0),
                                        jnp.asarray(1.0, dtype))
        summaries.append((res, valid))
    ok = sol.result == optx.RESULTS.successful
    return tuple(ps), er, et, tr, tt, cov, tuple(summaries), sol.stats["num_steps"], ok


def _initial_target_poses(cameras, mounts_r, mounts_t, corrs, n_targets, dtype):
    """Each target view's pose from the camera that sees most of it (`estimate_pose`'s linear
    solution from the unprojected rays), carried to the vehicle frame by that camera's mounting."""
    counts = np.zeros((len(cameras), n_targets))
    rays = []
    for c, (cam, corr) in enumerate(zip(cameras, corrs, strict=True)):
        used = np.asarray(corr.weight) > 0
        counts[c] = np.bincount(np.asarray(corr.view)[used], minlength=n_targets)[:n_targets]
        r, ok = jit_unproject(cam, corr.pixels)
        rays.append((np.asarray(r), np.asarray(ok) & used))
    rots, ts = [], []
    for v in range(n_targets):
        c = int(np.argmax(counts[:, v]))
        if counts[c, v] < 4:
            raise ValueError(f"refit_rig: target view {v} is seen by no camera with 4 points or more "
                             f"(best: {int(counts[c, v])})")
        corr = corrs[c]
        m = np.asarray(corr.view) == v
        pose = pose_from_rays(np.asarray(corr.points)[m], rays[c][0][m], rays[c][1][m], dtype)
        rc, tc = np.asarray(mounts_r[c], np.float64), np.asarray(mounts_t[c], np.float64)
        rots.append(rc @ np.asarray(pose.rotation_matrix, np.float64))
        ts.append(rc @ np.asarray(pose.translation, np.float64) + tc)
    return jnp.asarray(np.stack(rots), dtype), jnp.asarray(np.stack(ts), dtype)


def _view_poses(cam, corr, n_targets, dtype) -> dict[int, np.ndarray]:
    """``{view: 4x4 target -> camera}`` for the views a camera sees with 4+ valid rays (linear)."""
    used = np.asarray(corr.weight) > 0
    if not used.any():
        return {}
    rays, ok = jit_unproject(cam, corr.pixels)
    rays, ok = np.asarray(rays), np.asarray(ok) & used
    view, pts = np.asarray(corr.view), np.asarray(corr.points)
    out = {}
    for v in range(n_targets):
        m = (view == v) & ok
        if m.sum() < 4:
            continue
        try:
            pose = pose_from_rays(pts[m], rays[m], np.ones(int(m.sum()), bool), dtype)
        except ValueError:
            continue
        t = np.eye(4)
        t[:3, :3], t[:3, 3] = np.asarray(pose.rotation_matrix, np.float64), np.asarray(pose.translation, np.float64)
        out[v] = t
    return out


def _estimate_mountings(cams, mounts_r, mounts_t, corrs, n_targets, ref, dtype):
    """Mountings from shared target views, as kalibr initialises a rig: starting from the
    reference camera, a camera that shares views with an already placed one is placed at the
    average over those views of ``target -> vehicle`` (through the placed camera) composed with
    ``camera -> target`` (its own linear pose)."""
    poses = [_view_poses(c, o, n_targets, dtype) for c, o in zip(cams, corrs, strict=True)]
    placed = {ref: np.block([[np.asarray(mounts_r[ref], np.float64), np.asarray(mounts_t[ref], np.float64)[:, None]],
                             [np.zeros((1, 3)), np.ones((1, 1))]])}
    while True:
        grown = False
        for c in range(len(cams)):
            if c in placed:
                continue
            guesses = [placed[k] @ poses[k][v] @ np.linalg.inv(poses[c][v])
                       for k in placed for v in poses[c] if v in poses[k]]
            if not guesses:
                continue
            u, _, vt = np.linalg.svd(sum(g[:3, :3] for g in guesses))
            m = np.eye(4)
            m[:3, :3] = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
            m[:3, 3] = np.mean([g[:3, 3] for g in guesses], axis=0)
            placed[c] = m
            grown = True
        if not grown:
            break
    r = np.stack([placed[c][:3, :3] if c in placed else np.asarray(mounts_r[c]) for c in range(len(cams))])
    t = np.stack([placed[c][:3, 3] if c in placed else np.asarray(mounts_t[c]) for c in range(len(cams))])
    return jnp.asarray(r, dtype), jnp.asarray(t, dtype), sorted(set(range(len(cams))) - set(placed))


def refit_rig(
    calibrations: Sequence[Calibration] | Mapping[str, Calibration],
    observations: Sequence[Correspondences] | Mapping[str, Correspondences],
    *,
    target_poses: Pose | None = None,
    fit_targets: bool = True,
    reference: str | int | None = 0,
    fit_extrinsics: bool = True,
    estimate_mountings: bool = False,
    fixed: Mapping[str, Iterable[str]] | Iterable[str] | None = None,
    target_names: Sequence[str] | None = None,
    loss: str = "linear",
    loss_scale_px: float = 1.0,
    max_steps: int = 200,
    rtol: float | None = None,
    atol: float | None = None,
) -> RigRefitResult:
    """Fit every camera's intrinsics and mounting, and the target poses, to the correspondences of
    a rig (kalibr's multi-camera calibration).

    ``calibrations``: the start rig (a sequence, or a mapping such as `jaxfish.default_rig`'s).
    ``observations``: one `Correspondences` per camera (a sequence in ``calibrations``' order or a
    mapping by camera name; a camera without one sees nothing and keeps its calibration), whose
    ``view`` indexes the shared target views (``0 .. n_targets-1``; every camera's ``n_views`` is
    the number of target views): the points of a view are in that target's frame, and cameras that
    observe the same view share its pose. ``target_poses`` (target -> vehicle, ``(n_targets,)``):
    initial or, with ``fit_targets=False``, known poses (e.g. ``Pose.identity`` batched for points
    surveyed in the vehicle frame); without it each view's pose is estimated linearly from the
    camera that sees most of it (`estimate_pose`) and that camera's initial mounting.

    The gauge: ``reference`` (a camera name or index) holds that camera's mounting at its initial
    value, and the others are fitted relative to it (kalibr's cam0); ``None`` fits every mounting,
    which only known targets (``fit_targets=False``) determine. ``fit_extrinsics=False`` holds every
    mounting. ``estimate_mountings=True`` replaces the start mountings of the cameras other than the
    reference by kalibr's initialisation: each one placed through the target views it shares with
    an already placed camera (linear board poses from the initial intrinsics, averaged over the
    shared views); a camera sharing no view keeps its start value. ``fixed``: intrinsic parameter names held for every camera (``("k4",)``) or per camera
    (``{"FV": ("k4",)}``), also as ``"FV.k4"`` in a flat list. Runs in the dtype of the cameras
    (float64 recommended). Problems with the inputs raise `ValueError`.
    """
    calibs = list(calibrations.values()) if isinstance(calibrations, Mapping) else list(calibrations)
    if not calibs:
        raise ValueError("refit_rig: no calibrations")
    names = [c.name for c in calibs]
    if len(set(names)) != len(names):
        raise ValueError(f"refit_rig: camera names must differ, got {names}")
    if isinstance(observations, Mapping):
        unknown = sorted(set(observations) - set(names))
        if unknown:
            raise ValueError(f"refit_rig: observations of unknown camera(s) {unknown} (cameras: {', '.join(names)})")
        obs = [observations.get(n) for n in names]
    else:
        obs = list(observations)
        if len(obs) != len(calibs):
            raise ValueError(f"refit_rig: {len(obs)} observation sets for {len(calibs)} cameras")
    if loss not in LOSSES:
        raise ValueError(f"unknown robust loss {loss!r} (known: {', '.join(LOSSES)})")
    if not loss_scale_px > 0:
        raise ValueError(f"loss_scale_px must be positive, got {loss_scale_px}")
    seen = [o for o in obs if o is not None]
    if not seen:
        raise ValueError("refit_rig: no camera has observations")
    n_targets = max(o.n_views for o in seen) if target_poses is None else int(np.shape(target_poses.translation)[0])
    if any(o.n_views > n_targets for o in seen):
        raise ValueError(f"refit_rig: observations index {max(o.n_views for o in seen)} target views, "
                         f"target_poses has {n_targets}")
    tnames = tuple(target_names) if target_names is not None else tuple(f"target{v}" for v in range(n_targets))
    if len(tnames) != n_targets:
        raise ValueError(f"refit_rig: {len(tnames)} target names for {n_targets} target views")
    # The reference camera (gauge).
    if reference is None:
        ref = None
    elif isinstance(reference, str):
        if reference not in names:
            raise ValueError(f"refit_rig: reference camera {reference!r} is not one of {', '.join(names)}")
        ref = names.index(reference)
    else:
        ref = int(reference)
        if not 0 <= ref < len(names):
            raise ValueError(f"refit_rig: reference index {ref} outside 0..{len(names) - 1}")
    if fit_extrinsics and fit_targets and ref is None:
        raise ValueError("refit_rig: nothing fixes the gauge: with fitted target poses, hold a reference camera's "
                         "mounting (reference=...) or give known target poses (fit_targets=False)")
    # Per-camera fixed intrinsics.
    per_cam: dict[str, list[str]] = {n: [] for n in names}
    if fixed is not None:
        if isinstance(fixed, Mapping):
            for k, v in fixed.items():
                if k not in per_cam:
                    raise ValueError(f"refit_rig: fixed names unknown camera {k!r} (cameras: {', '.join(names)})")
                per_cam[k].extend([v] if isinstance(v, str) else list(v))
        else:
            for item in ([fixed] if isinstance(fixed, str) else list(fixed)):
                cam_name, dot, par = str(item).rpartition(".")
                if dot and cam_name in per_cam:
                    per_cam[cam_name].append(par)
                elif dot:
                    raise ValueError(f"refit_rig: fixed {item!r} names unknown camera {cam_name!r}")
                else:
                    for n in names:
                        per_cam[n].append(item)
    dtype = intrinsics_vector(calibs[0].camera).dtype
    cams, p0s, free_parts, pnames = [], [], [], []
    for c, o in zip(calibs, obs, strict=True):
        p0 = intrinsics_vector(c.camera).astype(dtype)
        cams.append(with_intrinsics(c.camera, p0))
        p0s.append(p0)
        pn = parameter_names(c.camera)
        mask = free_parameter_mask(pn, per_cam[c.name]) if o is not None else tuple(False for _ in pn)
        free_parts.append(np.asarray(mask, np.float64))
        pnames += [f"{c.name}.{n}" for n in pn]
    ext_free = []
    for i, (c, o) in enumerate(zip(calibs, obs, strict=True)):
        f = fit_extrinsics and o is not None and i != ref
        ext_free.append(np.full(6, float(f)))
        pnames += [f"{c.name}.{k}" for k in POSE_COMPONENTS]
    tgt_free = np.full(6 * n_targets, float(fit_targets))
    pnames += [f"{t}.{k}" for t in tnames for k in POSE_COMPONENTS]
    free = np.concatenate(free_parts + ext_free + [tgt_free])
    mounts_r = jnp.stack([jnp.asarray(c.camera_to_vehicle.rotation_matrix, dtype) for c in calibs])
    mounts_t = jnp.stack([jnp.asarray(c.camera_to_vehicle.translation, dtype) for c in calibs])
    empty = Correspondences(np.zeros((0, 3)), np.zeros((0, 2)), np.zeros(0, np.int32), np.zeros(0),
                            n_views=n_targets, dtype=dtype)
    corrs = tuple(Correspondences(o.points, o.pixels, o.view, o.weight, n_views=n_targets, dtype=dtype)
                  if o is not None else empty for o in obs)
    if estimate_mountings:
        if ref is None:
            raise ValueError("refit_rig: estimate_mountings needs a reference camera to start from")
        mounts_r, mounts_t, _ = _estimate_mountings(cams, mounts_r, mounts_t, corrs, n_targets, ref, dtype)
    if target_poses is None:
        if not fit_targets:
            raise ValueError("refit_rig: fit_targets=False needs target_poses")
        tgt_r0, tgt_t0 = _initial_target_poses(cams, mounts_r, mounts_t, corrs, n_targets, dtype)
    else:
        tgt_r0 = jnp.broadcast_to(jnp.asarray(target_poses.rotation_matrix, dtype), (n_targets, 3, 3))
        tgt_t0 = jnp.broadcast_to(jnp.asarray(target_poses.translation, dtype), (n_targets, 3))
    n_used = sum(int(np.sum(np.asarray(c.weight) > 0)) for c in corrs)
    n_free = int(free.sum())
    if 2 * n_used < n_free:
        raise ValueError(f"refit_rig: {n_used} correspondences cannot determine {n_free} free parameters")
    d_rtol, d_atol = default_tolerances(dtype)
    ps, er, et, tr, tt, cov, summaries, steps, ok = _solve_rig(
        tuple(cams), tuple(p0s), jnp.asarray(free, dtype), mounts_r, mounts_t, tgt_r0, tgt_t0, corrs,
        jnp.asarray(LOSSES.index(loss)), jnp.asarray(loss_scale_px, dtype), int(max_steps),
        d_rtol if rtol is None else float(rtol), d_atol if atol is None else float(atol))
    keep = np.flatnonzero(free > 0)
    cov = cov[np.ix_(keep, keep)]
    values = jnp.concatenate([*ps, jnp.zeros(6 * (len(calibs) + n_targets), dtype)])[keep]
    out_calibs = tuple(Calibration(c.name, with_intrinsics(cam, p), Pose(er[i], et[i]), c.flavor)
                       for i, (c, cam, p) in enumerate(zip(calibs, cams, ps, strict=True)))
    res = tuple(s[0] for s in summaries)
    valid = tuple(s[1] for s in summaries)
    sq = [jnp.where(v, jnp.sum(r * r, axis=-1), 0.0) for r, v in zip(res, valid, strict=True)]
    counts = jnp.stack([jnp.sum(v).astype(dtype) for v in valid])
    sums = jnp.stack([jnp.sum(s) for s in sq])
    per_cam_rms = jnp.sqrt(sums / jnp.maximum(counts, 1.0))
    rms = jnp.sqrt(jnp.sum(sums) / jnp.maximum(jnp.sum(counts), 1.0))
    return RigRefitResult(
        calibrations=out_calibs, target_poses=Pose(tr, tt), residuals=res, valid=valid, rms_px=rms,
        per_camera_rms_px=per_cam_rms, parameters=values, covariance=cov,
        standard_deviations=jnp.sqrt(jnp.maximum(jnp.diag(cov), 0.0)), num_steps=steps, converged=ok,
        parameter_names=tuple(pnames[i] for i in keep), target_names=tnames,
    )
