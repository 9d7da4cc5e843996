"""Least-squares refitting of intrinsics (and poses) to 2D-3D correspondences.

The problem is one optimistix Levenberg-Marquardt solve over the *free* parameters (a mask fixes
the others), with optional robust loss, in Jacobi-scaled coordinates so that pixels, radians and
dimensionless coefficients are equally well conditioned.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._numerics import resolve_dtype
from ..cameras import AbstractCamera
from ..transforms import Pose
from ._parameters import APPROXIMATION_PARAMETERS, intrinsics_vector, parameter_names, with_intrinsics

LOSSES: tuple[str, ...] = ("linear", "huber", "cauchy", "soft_l1")
"""Robust losses: rho(s) of the squared per-point residual norm s (pixels²), scale c (pixels)."""


def robust_rho(s: Array, loss: str, scale: float | Array) -> Array:
    """``rho(s)`` of a squared residual norm ``s``: linear ``s``; huber ``s`` if ``s <= c²`` else
    ``2 c sqrt(s) - c²``; cauchy ``c² log(1 + s/c²)``; soft_l1 ``2 c² (sqrt(1 + s/c²) - 1)``."""
    c2 = jnp.asarray(scale, s.dtype) ** 2
    if loss == "linear":
        return s
    if loss == "huber":
        safe = jnp.where(s > c2, s, c2)
        return jnp.where(s <= c2, s, 2 * jnp.sqrt(c2) * jnp.sqrt(safe) - c2)
    if loss == "cauchy":
        return c2 * jnp.log1p(s / c2)
    if loss == "soft_l1":
        return 2 * c2 * (jnp.sqrt(1 + s / c2) - 1)
    raise ValueError(f"unknown robust loss {loss!r} (known: {', '.join(LOSSES)})")


def robust_factor(s: Array, code: Array, scale: Array) -> Array:
    """``sqrt(rho(s)/s)`` for the loss ``LOSSES[code]`` (traced: one compile for every loss);
    1 at s = 0, where every loss is quadratic."""
    c2 = scale * scale
    small = s < 1e-12 * c2
    safe_s = jnp.where(small, jnp.ones_like(s), s)
    big = safe_s > c2
    huber = jnp.where(big, 2 * jnp.sqrt(c2) * jnp.sqrt(jnp.where(big, safe_s, c2)) - c2, safe_s)
    cauchy = c2 * jnp.log1p(safe_s / c2)
    soft_l1 = 2 * c2 * (jnp.sqrt(1 + safe_s / c2) - 1)
    rho = jnp.select([code == 1, code == 2, code == 3], [huber, cauchy, soft_l1], safe_s)
    return jnp.where(small | (code == 0), jnp.ones_like(s), jnp.sqrt(rho / safe_s))


def rotation_from_vector(omega: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
    """Rodrigues' formula ``exp([omega]x)``; values and gradients finite at omega = 0."""
    dtype = omega.dtype
    t2 = jnp.sum(omega * omega, axis=-1)
    small = t2 < jnp.asarray(1e-8, dtype)
    safe_t2 = jnp.where(small, jnp.ones_like(t2), t2)
    t = jnp.sqrt(safe_t2)
    a = jnp.where(small, 1 - t2 / 6, jnp.sin(t) / t)
    b = jnp.where(small, 0.5 - t2 / 24, (1 - jnp.cos(t)) / safe_t2)
    x, y, z = omega[..., 0], omega[..., 1], omega[..., 2]
    zero = jnp.zeros_like(x)
    k = jnp.stack([jnp.stack([zero, -z, y], -1), jnp.stack([z, zero, -x], -1), jnp.stack([-y, x, zero], -1)], -2)
    eye = jnp.eye(3, dtype=dtype)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


MAX_CORRESPONDENCE_VALUE = 1e7
"""Largest magnitude of a correspondence's coordinate (metres, pixels) or weight: beyond any real
calibration target, and small enough that squared residuals stay finite."""


def _checked_values(name: str, a: Array, weight: Array | None = None) -> Array:
    """``a`` (a `Correspondences` field: the weights themselves when ``weight`` is None) checked to
    be finite and, in its rows of positive ``weight``, at most `MAX_CORRESPONDENCE_VALUE` in
    magnitude; weights also non-negative. ValueError when concrete, `eqx.error_if` (a runtime
    error) when traced."""
    is_weight = weight is None
    if isinstance(a, jax.core.Tracer) or isinstance(weight, jax.core.Tracer):
        w = a if is_weight else weight
        big = jnp.abs(a) > MAX_CORRESPONDENCE_VALUE
        if not is_weight:
            big = jnp.any(big, axis=-1) & (w > 0)
        bad = jnp.any(~jnp.isfinite(a)) | jnp.any(big) | (jnp.any(a < 0) if is_weight else False)
        return eqx.error_if(a, bad, f"Correspondences: {name}: values must be finite, at most "
                                    f"{MAX_CORRESPONDENCE_VALUE:g} in magnitude"
                                    + (" and non-negative" if is_weight else " where the weight is positive"))
    v = np.asarray(a).reshape(a.shape[0], int(np.prod(a.shape[1:])))  # rows: (N, 3), (N, 2) or (N, 1)
    if not np.all(np.isfinite(v)):
        i = int(np.argmax(~np.isfinite(v).all(axis=1)))
        raise ValueError(f"Correspondences: {name}: values must be finite (row {i}: {v[i].tolist()})")
    rows = np.abs(v).max(axis=1, initial=0.0)
    if not is_weight:
        rows = np.where(np.asarray(weight) > 0, rows, 0.0)
    if rows.size and rows.max() > MAX_CORRESPONDENCE_VALUE:
        i = int(np.argmax(rows))
        raise ValueError(f"Correspondences: {name}: values must be at most {MAX_CORRESPONDENCE_VALUE:g} in magnitude, "
                         f"got {rows[i]:g} in row {i}" + ("" if is_weight else " (weight > 0)"))
    if is_weight and v.size and v.min() < 0:
        i = int(np.argmin(v[:, 0]))
        raise ValueError(f"Correspondences: {name}: expected {v.shape[0]} non-negative numbers, got {v[i, 0]:g} at index {i}")
    return a


class Correspondences(eqx.Module):
    """2D-3D correspondences: ``pixels[i]`` observes ``points[i]`` in view ``view[i]``.

    `points` ``(N, 3)`` are in the frame of their view's pose (a calibration board, the vehicle,
    or the camera itself with identity poses), metres; `pixels` ``(N, 2)`` in jaxfish's
    pixel-centre convention; `view` ``(N,)`` integer view index in ``[0, n_views)``; `weight`
    ``(N,)`` non-negative per-point weights (default 1; 0 drops a point without changing shapes,
    so one compiled solve serves every subset).

    Points, pixels and weights must be finite (even at weight 0) and, in the rows of positive
    weight, at most `MAX_CORRESPONDENCE_VALUE` in magnitude; weights non-negative (the rules of
    the correspondence files, whose rows all count): ValueError otherwise (a runtime error from
    `eqx.error_if` for traced values).
    """

    points: Float[Array, "N 3"]
    pixels: Float[Array, "N 2"]
    view: Int[Array, " N"]
    weight: Float[Array, " N"]
    n_views: int = eqx.field(static=True)

    def __init__(self, points: Float[ArrayLike, "N 3"], pixels: Float[ArrayLike, "N 2"],
                 view: Int[ArrayLike, " N"] | None = None, weight: Float[ArrayLike, " N"] | None = None, *,
                 n_views: int | None = None, dtype=None):
        dtype = resolve_dtype(dtype, points, pixels)
        points = jnp.asarray(points, dtype=dtype)
        pixels = jnp.asarray(pixels, dtype=dtype)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"Correspondences: points must have shape (N, 3), got {points.shape}")
        if pixels.shape != (points.shape[0], 2):
            raise ValueError(f"Correspondences: pixels must have shape ({points.shape[0]}, 2), got {pixels.shape}")
        if view is None:
            view = np.zeros(points.shape[0], dtype=np.int32)
        view = np.asarray(view)
        if view.shape != (points.shape[0],) or not np.issubdtype(view.dtype, np.integer):
            raise ValueError(f"Correspondences: view must be ({points.shape[0]},) integers, got {view.shape} {view.dtype}")
        if view.size and view.min() < 0:
            raise ValueError("Correspondences: view indices must be >= 0")
        n = int(view.max()) + 1 if view.size else 1
        n_views = n if n_views is None else int(n_views)
        if n_views < n:
            raise ValueError(f"Correspondences: n_views={n_views} but view indices go up to {n - 1}")
        self.view = jnp.asarray(view, dtype=jnp.int32)
        if weight is None:
            weight = np.ones(points.shape[0])
        weight = jnp.asarray(weight, dtype=dtype)
        if weight.shape != (points.shape[0],):
            raise ValueError(f"Correspondences: weight must have shape ({points.shape[0]},), got {weight.shape}")
        self.weight = _checked_values("weight", weight)
        self.points = _checked_values("points", points, weight)
        self.pixels = _checked_values("pixels", pixels, weight)
        self.n_views = n_views

    @property
    def size(self) -> int:
        """Number of correspondences N."""
        return self.points.shape[0]


class RefitResult(eqx.Module):
    """The outcome of `refit`.

    - `camera`: the fitted camera (same model as the initial one);
    - `poses`: fitted (or given) world-to-camera poses, batched ``(n_views,)``:
      ``p_cam = R p + t`` with ``p`` the correspondences' 3D points;
    - `residuals` ``(N, 2)``: ``project(p_cam) - pixels`` in pixels (plain, not robustified);
      `valid` ``(N,)``: the camera's validity of each projected point;
    - `rms_px`: ``sqrt(mean_i |residual_i|²)`` over valid points; `per_view_rms_px` ``(n_views,)``;
    - `parameter_names`: the free parameters, intrinsics first (`parameter_names` of the model)
      then ``view{v}.rx, .ry, .rz`` (radians, a rotation-vector perturbation ``R <- exp(ω) R``)
      and ``view{v}.tx, .ty, .tz`` (metres) for fitted poses; `parameters` their values (pose
      perturbations are 0 at the solution);
    - `covariance` ``(P, P)`` of the free parameters: ``σ² (JᵀJ)⁺`` at the solution with
      ``σ² = sum rho / (2N - P)`` (Gauss-Newton approximation, robust weights included); NaN
      throughout when the data do not determine the free parameters (the Jacobian's rank is below
      ``P``: e.g. copies of one correspondence, see `determined`);
      `standard_deviations` its root diagonal (NaN then too);
    - `num_steps`, `converged`: from optimistix (``converged`` = solver reported success).
    """

    camera: AbstractCamera
    poses: Pose
    residuals: Float[Array, "N 2"]
    valid: Bool[Array, " N"]
    rms_px: Float[Array, ""]
    per_view_rms_px: Float[Array, " V"]
    parameters: Float[Array, " P"]
    covariance: Float[Array, "P P"]
    standard_deviations: Float[Array, " P"]
    num_steps: Int[Array, ""]
    converged: Bool[Array, ""]
    parameter_names: tuple[str, ...] = eqx.field(static=True)

    @property
    def determined(self) -> bool:
        """Whether the data determine every free parameter (the covariance is finite); False for a
        degenerate set of correspondences, whose fitted values are one solution among many."""
        return bool(np.all(np.isfinite(np.asarray(self.covariance))))

    def standard_deviation(self, name: str) -> float:
        """The standard deviation of one free parameter, by name."""
        if name not in self.parameter_names:
            raise KeyError(f"{name!r} is not a free parameter (free: {', '.join(self.parameter_names)})")
        return float(self.standard_deviations[self.parameter_names.index(name)])


@eqx.filter_jit
def jit_project(camera: AbstractCamera, points):
    """``camera.project(points)`` compiled once per camera structure and shape (eager calls of a
    camera with an iterative ``theta_max`` or inversion would dispatch op by op)."""
    return camera.project(points)


@eqx.filter_jit
def jit_unproject(camera: AbstractCamera, uv):
    """``camera.unproject(uv)``, compiled (see `jit_project`)."""
    return camera.unproject(uv)


def _summarise(cam, rot, t, corr):
    v = rot.shape[0]
    pc = jnp.einsum("nij,nj->ni", rot[corr.view], corr.points) + t[corr.view]
    uv, valid = cam.project(pc)
    res = uv - corr.pixels
    valid = valid & (corr.weight > 0)
    sq = jnp.where(valid, jnp.sum(res * res, axis=-1), 0.0)
    count = jnp.maximum(jnp.sum(valid).astype(sq.dtype), 1.0)
    rms = jnp.sqrt(jnp.sum(sq) / count)
    onehot = ((corr.view[:, None] == jnp.arange(v, dtype=corr.view.dtype)[None, :]) & valid[:, None]).astype(sq.dtype)
    per_view = jnp.sqrt(jnp.sum(onehot * sq[:, None], axis=0) / jnp.maximum(jnp.sum(onehot, axis=0), 1.0))
    return res, valid, rms, per_view


def free_parameter_mask(names: tuple[str, ...], fixed: Iterable[str] | Sequence[bool] | str | None) -> tuple[bool, ...]:
    """Which of a model's parameters (``names``, in `parameter_names` order) a fit may move:
    ``fixed`` is None (all free), parameter names to hold, or a boolean mask over ``names`` (True:
    held). Parameters that move no projection (`APPROXIMATION_PARAMETERS`: approximate inverse
    polynomials) stay held unless a boolean mask frees them. ValueError for an unknown name or a
    mask of the wrong length."""
    approximations = {n for group in APPROXIMATION_PARAMETERS.values() for n in group}
    if fixed is None:
        return tuple(n not in approximations for n in names)
    if isinstance(fixed, str):
        fixed = (fixed,)
    fixed = list(fixed)
    if fixed and all(isinstance(f, (bool, np.bool_)) for f in fixed):
        if len(fixed) != len(names):
            raise ValueError(f"fixed mask has {len(fixed)} entries, the model has {len(names)} parameters {names}")
        return tuple(not bool(f) for f in fixed)
    unknown = [f for f in fixed if f not in names]
    if unknown:
        raise ValueError(f"unknown parameter(s) {unknown} in fixed (parameters: {', '.join(names)})")
    return tuple(n not in fixed and n not in approximations for n in names)


def _unpack(z, p0, scales, rot0, t0, fit_pose):
    n_par = p0.shape[0]
    p = p0 + scales[:n_par] * z[:n_par]
    if fit_pose:
        dz = (scales[n_par:] * z[n_par:]).reshape(rot0.shape[0], 6)
        return p, rotation_from_vector(dz[:, :3]) @ rot0, t0 + dz[:, 3:]
    return p, rot0, t0


def _residuals(cam, rot, t, corr, loss_code, loss_scale):
    pc = jnp.einsum("nij,nj->ni", rot[corr.view], corr.points) + t[corr.view]
    uv, _ = cam.project(pc)
    res = uv - corr.pixels
    w = corr.weight
    root_w = jnp.where(w > 0, jnp.sqrt(jnp.where(w > 0, w, 1.0)), 0.0)  # d sqrt(w)/dw is infinite at 0: 0, not NaN
    factor = robust_factor(jnp.sum(res * res, axis=-1), loss_code, loss_scale) * root_w
    return res * factor[:, None]


def _residual_fn(z, args):
    (camera, p0, scales, rot0, t0, corr, fit_pose, loss_code, loss_scale) = args
    p, rot, t = _unpack(z, p0, scales, rot0, t0, fit_pose)
    return _residuals(with_intrinsics(camera, p), rot, t, corr, loss_code, loss_scale)


def reprojection_residuals(
    camera: AbstractCamera,
    correspondences: Correspondences,
    poses: Pose | None = None,
    *,
    loss: str = "linear",
    loss_scale_px: float | Array = 1.0,
) -> Float[Array, "N 2"]:
    """The residuals `refit` minimises: ``project(R_v p_i + t_v) - pixel_i`` (pixels), each point
    scaled by ``sqrt(weight_i rho(s_i) / s_i)`` so that ``sum |r_i|²`` is the robust objective.

    Differentiable in the camera, the poses (world-to-camera, batched ``(n_views,)``; identity
    if None) and the correspondences (the gradient with respect to a weight of exactly 0 is 0:
    the residual's own derivative there is infinite). Points the camera reports invalid keep
    the camera's finite placeholder residual (see ``docs/refit.md``)."""
    if loss not in LOSSES:
        raise ValueError(f"unknown robust loss {loss!r} (known: {', '.join(LOSSES)})")
    corr = correspondences
    dtype = corr.points.dtype
    v = corr.n_views
    if poses is None:
        rot, t = jnp.broadcast_to(jnp.eye(3, dtype=dtype), (v, 3, 3)), jnp.zeros((v, 3), dtype)
    else:
        rot = jnp.broadcast_to(poses.rotation_matrix, (v, 3, 3))
        t = jnp.broadcast_to(poses.translation, (v, 3))
    return _residuals(camera, rot, t, corr, jnp.asarray(LOSSES.index(loss)), jnp.asarray(loss_scale_px, dtype))


@eqx.filter_jit
def solve_refit(
    camera: AbstractCamera,
    p0: Float[Array, " P"],
    free: Bool[Array, " P"],
    rot0: Float[Array, "V 3 3"],
    t0: Float[Array, "V 3"],
    corr: Correspondences,
    fit_pose: bool,
    loss_code: Int[ArrayLike, ""],
    loss_scale: Float[ArrayLike, ""],
    max_steps: int,
    rtol: float,
    atol: float,
    with_covariance: bool = True,
):
    """The Levenberg-Marquardt solve behind `refit`: ``camera``'s intrinsics from ``p0``
    (`intrinsics_vector` order; only the ``free`` ones move) and, when ``fit_pose``, the ``V``
    world-to-camera poses from ``(rot0, t0)``, minimising `reprojection_residuals` of ``corr``
    with the robust loss ``LOSSES[loss_code]`` at ``loss_scale`` pixels.

    Returns ``(p (P,), rot (V, 3, 3), t (V, 3), extras, num_steps, converged)``; ``extras`` is
    ``(covariance (P + 6 V, P + 6 V), residual summary)`` with ``with_covariance``, else None.
    One compile per (model, N, V, fit_pose): the mask, the loss and its scale are traced."""
    dtype = p0.dtype
    n_pose = rot0.shape[0] * 6 if fit_pose else 0
    free_all = jnp.concatenate([free.astype(dtype), jnp.ones(n_pose, dtype)])
    z0 = jnp.zeros(free_all.shape[0], dtype)

    def fn(z, scales):
        return _residual_fn(z, (camera, p0, scales, rot0, t0, corr, fit_pose, loss_code, loss_scale)).ravel()

    # Jacobi scaling: every free variable moves the residuals by about one unit per unit step;
    # fixed ones get scale 0 (they cannot move).
    jac0 = jax.jacfwd(fn)(z0, free_all)
    col = jnp.sqrt(jnp.sum(jac0 * jac0, axis=0))
    scales = free_all * jnp.where(col > 0, 1.0 / jnp.where(col > 0, col, 1.0), 1.0)
    args = (camera, p0, scales, rot0, t0, corr, fit_pose, loss_code, loss_scale)
    sol = optx.least_squares(
        _residual_fn, optx.LevenbergMarquardt(rtol=rtol, atol=atol), z0, args=args,
        max_steps=max_steps, throw=False,
    )
    p, rot, t = _unpack(sol.value, p0, scales, rot0, t0, fit_pose)
    steps, ok = sol.stats["num_steps"], sol.result == optx.RESULTS.successful
    if not with_covariance:
        return p, rot, t, None, steps, ok
    # Covariance in natural units around the solution (pose perturbations re-based at 0).
    args_sol = (camera, p, free_all, rot, t, corr, fit_pose, loss_code, loss_scale)
    jac = jax.jacfwd(lambda zz: _residual_fn(zz, args_sol).ravel())(z0)
    r = _residual_fn(z0, args_sol).ravel()
    dof = jnp.maximum(2 * jnp.sum(corr.weight > 0).astype(dtype) - jnp.sum(free_all), 1.0)
    sigma2 = jnp.sum(r * r) / dof
    # Fixed parameters have zero columns: put 1 on their diagonal, invert, zero them again.
    fixed_diag = jnp.diag(1.0 - free_all)
    cov = sigma2 * (jnp.linalg.inv(jac.T @ jac + fixed_diag) - fixed_diag)
    cov = 0.5 * (cov + cov.T)
    # Data that do not determine the free parameters (a rank-deficient Jacobian: e.g. copies of
    # one correspondence) have no covariance: NaN, never the finite numbers a singular inverse
    # happens to give. Rank of the column-normalised Jacobian, NumPy's `matrix_rank` tolerance.
    norms = jnp.sqrt(jnp.sum(jac * jac, axis=0))
    singular = jnp.linalg.svd(jac / jnp.where(norms > 0, norms, 1.0), compute_uv=False)
    tol = jnp.max(singular) * max(jac.shape) * jnp.finfo(dtype).eps
    determined = jnp.sum(singular > tol).astype(dtype) >= jnp.sum(free_all)
    cov = jnp.where(determined, cov, jnp.nan)
    return p, rot, t, (cov, _summarise(with_intrinsics(camera, p), rot, t, corr)), steps, ok


def default_tolerances(dtype) -> tuple[float, float]:
    """``(rtol, atol)`` of the fit for a floating dtype: 1e-10 in float64, 1e-6 otherwise."""
    return (1e-10, 1e-10) if jnp.dtype(dtype) == jnp.float64 else (1e-6, 1e-6)


def refit(
    camera: AbstractCamera,
    correspondences: Correspondences,
    *,
    poses: Pose | None = None,
    fit_pose: bool = True,
    fixed: Iterable[str] | Sequence[bool] | None = None,
    loss: str = "linear",
    loss_scale_px: float = 1.0,
    max_steps: int = 200,
    rtol: float | None = None,
    atol: float | None = None,
) -> RefitResult:
    """Fit a camera's intrinsics (and optionally one pose per view) to 2D-3D correspondences.

    Minimises ``sum_i rho(|project(R_v p_i + t_v) - pixel_i|²)`` with optimistix's
    Levenberg-Marquardt. ``camera`` is the initial guess and fixes the model; ``poses``
    (world-to-camera, batched ``(n_views,)``) the initial poses. Without ``poses``: with
    ``fit_pose`` they are estimated from the initial camera by `estimate_pose` (linear, from the
    unprojected rays), without it identity (points already in the camera frame).

    ``fixed``: parameter names to hold (e.g. ``("k4", "aspect_ratio")``; see `parameter_names`),
    or a boolean mask over the model's parameters (True = fixed). ``loss``: one of `LOSSES`, with
    scale ``loss_scale_px``. Runs in the dtype of the camera parameters (float64 recommended).
    """
    names = parameter_names(camera)
    free = free_parameter_mask(names, fixed)
    p0 = intrinsics_vector(camera)
    dtype = p0.dtype
    camera = with_intrinsics(camera, p0)  # canonical leaves (no weak types): one compile per model
    corr = Correspondences(correspondences.points, correspondences.pixels, correspondences.view,
                           correspondences.weight, n_views=correspondences.n_views, dtype=dtype)
    if loss not in LOSSES:
        raise ValueError(f"unknown robust loss {loss!r} (known: {', '.join(LOSSES)})")
    if not loss_scale_px > 0:
        raise ValueError(f"loss_scale_px must be positive, got {loss_scale_px}")
    v = corr.n_views
    used = np.asarray(corr.weight) > 0
    if poses is None:
        if fit_pose:
            rays, ok = jit_unproject(camera, corr.pixels)
            view_np, pts_np = np.asarray(corr.view), np.asarray(corr.points)
            rays_np, ok_np = np.asarray(rays), np.asarray(ok) & used
            est = [pose_from_rays(pts_np[view_np == i], rays_np[view_np == i], ok_np[view_np == i], dtype)
                   for i in range(v)]
            rot0 = jnp.stack([e.rotation_matrix for e in est]).astype(dtype)
            t0 = jnp.stack([e.translation for e in est]).astype(dtype)
        else:
            rot0 = jnp.broadcast_to(jnp.eye(3, dtype=dtype), (v, 3, 3))
            t0 = jnp.zeros((v, 3), dtype)
    else:
        rot0 = jnp.broadcast_to(jnp.asarray(poses.rotation_matrix, dtype), (v, 3, 3))
        t0 = jnp.broadcast_to(jnp.asarray(poses.translation, dtype), (v, 3))
    n_params = sum(free) + (6 * v if fit_pose else 0)
    if 2 * int(used.sum()) < n_params:
        raise ValueError(f"refit: {int(used.sum())} correspondences cannot determine {n_params} free parameters")
    default_rtol, default_atol = default_tolerances(dtype)
    p, rot, t, (cov, summary), steps, ok = solve_refit(
        camera, p0, jnp.asarray(free), rot0, t0, corr, bool(fit_pose), jnp.asarray(LOSSES.index(loss)),
        jnp.asarray(loss_scale_px, dtype), int(max_steps),
        default_rtol if rtol is None else float(rtol), default_atol if atol is None else float(atol),
    )
    keep = [i for i, f in enumerate(free) if f] + list(range(len(names), len(names) + (6 * v if fit_pose else 0)))
    cov = cov[np.ix_(keep, keep)]
    free_idx = np.asarray([i for i, f in enumerate(free) if f], dtype=np.int32)
    cam = with_intrinsics(camera, p)
    res, valid, rms, per_view = summary
    n_valid = int(jnp.sum(valid))
    if 2 * n_valid < n_params:  # an RMS over nothing would read as a perfect fit
        raise ValueError(f"refit: only {n_valid} of {int(used.sum())} correspondences project validly, too few for "
                         f"{n_params} free parameters (points at the camera centre or outside the lens domain?)")
    pose_names = tuple(f"view{i}.{c}" for i in range(v) for c in ("rx", "ry", "rz", "tx", "ty", "tz")) if fit_pose else ()
    free_names = tuple(n for n, f in zip(names, free, strict=True) if f) + pose_names
    values = jnp.concatenate([p[free_idx], jnp.zeros(len(pose_names), dtype)])
    return RefitResult(
        camera=cam, poses=Pose(rot, t), residuals=res, valid=valid, rms_px=rms, per_view_rms_px=per_view,
        parameters=values, covariance=cov, standard_deviations=jnp.sqrt(jnp.maximum(jnp.diag(cov), 0.0)),
        num_steps=steps, converged=ok, parameter_names=free_names,
    )


def estimate_pose(camera: AbstractCamera, points: Float[ArrayLike, "N 3"], pixels: Float[ArrayLike, "N 2"]) -> Pose:
    """A linear world-to-camera pose from 2D-3D correspondences, for any central camera model.

    Pixels are unprojected to rays with the (initial) intrinsics; then a direct linear transform
    ``ray x (R p + t) = 0`` (8+ non-coplanar points) or, for coplanar points (a calibration
    board; 4+ points), a plane homography decomposed into ``R, t``. Works for rays beyond 90
    degrees. The result is the starting point of `refit`, not a final estimate.
    """
    dtype = intrinsics_vector(camera).dtype
    rays, valid = jit_unproject(camera, jnp.asarray(pixels, dtype))
    return pose_from_rays(np.asarray(points), np.asarray(rays), np.asarray(valid), dtype)


def _cross_matrices(r: np.ndarray) -> np.ndarray:
    z = np.zeros(len(r))
    return np.stack([np.stack([z, -r[:, 2], r[:, 1]], -1), np.stack([r[:, 2], z, -r[:, 0]], -1),
                     np.stack([-r[:, 1], r[:, 0], z], -1)], -2)


def pose_from_rays(pts: np.ndarray, rays: np.ndarray, keep: np.ndarray, dtype) -> Pose:
    pts = np.asarray(pts, dtype=np.float64)[keep]
    rays = np.asarray(rays, dtype=np.float64)[keep]
    if pts.shape[0] < 4:
        raise ValueError(f"estimate_pose: need at least 4 points with a valid ray, got {pts.shape[0]}")
    centre = pts.mean(axis=0)
    _, sv, vt = np.linalg.svd(pts - centre)
    spread = sv[0] if sv[0] > 0 else 1.0
    planar = sv[2] <= 1e-6 * spread or pts.shape[0] < 8
    if planar:
        e = vt.T  # columns: in-plane axes e1, e2 and the normal
        ab = (pts - centre) @ e[:, :2] / spread
        x = np.c_[ab, np.ones(len(ab))]
        rows = np.einsum("nij,nk->nijk", _cross_matrices(rays), x).reshape(-1, 9)  # rx @ H x, H row-major
        h = np.linalg.svd(rows, full_matrices=False)[2][-1].reshape(3, 3)
        lam = (np.linalg.norm(h[:, 0]) + np.linalg.norm(h[:, 1])) / 2
        h = h / lam
        if np.sum(np.einsum("ij,nj->ni", h, np.c_[ab, np.ones(len(ab))]) * rays) < 0:
            h = -h
        r1, r2 = h[:, 0], h[:, 1]
        m = np.stack([r1, r2, np.cross(r1, r2)], axis=1)
        u_, _, vt_ = np.linalg.svd(m)
        rp = u_ @ np.diag([1, 1, np.linalg.det(u_ @ vt_)]) @ vt_
        tp = h[:, 2] * spread
        rot = rp @ e.T
        t = tp - rot @ centre
    else:
        q = (pts - centre) / spread
        x = np.c_[q, np.ones(len(q))]
        rows = np.einsum("nij,nk->nijk", _cross_matrices(rays), x).reshape(-1, 12)
        pm = np.linalg.svd(rows, full_matrices=False)[2][-1].reshape(3, 4)
        u_, s_, vt_ = np.linalg.svd(pm[:, :3])
        scale = s_.mean()
        pm = pm / scale
        if np.linalg.det(u_ @ vt_) < 0:
            pm = -pm
            u_ = -u_
        rot = u_ @ vt_
        tq = pm[:, 3]
        if np.sum((q @ rot.T + tq) * rays) < 0:  # cannot happen for a proper rotation; guard anyway
            tq = -tq
        t = tq * spread - rot @ centre
    if not np.all(np.isfinite(rot)) or not np.all(np.isfinite(t)):
        raise ValueError("estimate_pose: degenerate correspondences (no finite pose)")
    return Pose(jnp.asarray(rot, dtype), jnp.asarray(t, dtype))
