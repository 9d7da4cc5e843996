"""Convert a calibration from one lens model to another by fitting over the field of view."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._numerics import positive_integer
from ..cameras import AbstractCamera, CarlaWideAngle, FTheta, OCamCalib
from ._fit import Correspondences, default_tolerances, free_parameter_mask, jit_project, jit_unproject, solve_refit
from ._initial import INITIAL_FROM_PROFILE, initial_vector
from ._parameters import (
    camera_from_intrinsics,
    canonical_model_name,
    intrinsics_vector,
    parameter_names,
    with_intrinsics,
)

BEHIND_AXIS_MARGIN_RAD = 1e-3
"""Incidence angles closer than this to pi (radians) are not sampled: the ray straight behind the
optical axis has no azimuth, and is invalid in every model."""
SOURCE_THETA_MARGIN_RAD = 1e-3
"""Margin below a source model's own theta_max (for models whose theta_max is a supremum)."""
MIN_AZIMUTHS = 3
"""Fewest azimuths (``n_phi``) `convert_camera` samples over the lens (``fov="lens"`` or
``theta_max``): the rays of one or two azimuths lie in one plane through the optical axis, which
leaves the focal length across that plane (or the aspect ratio) undetermined."""
MIN_RAYS_PER_PARAMETER = 3
"""Fewest rays the source projects that `convert_camera` fits per free parameter of the target."""


class ConversionResult(eqx.Module):
    """The outcome of `convert_camera`.

    - `camera`: the fitted camera of the target model (the best of its starts);
    - `max_px`, `rms_px`: largest and RMS pixel distance between the source's and the target's
      projections of the sampled rays both models project (``sqrt(mean |d|²)``): the error over
      the fitted domain; `max_px_in_image`, `rms_px_in_image`: the same over rays whose source
      pixel lies inside the image;
    - `theta_max`: the largest sampled incidence angle (radians); `max_radius_px`: the largest
      distance of a sampled source pixel from the source's principal point (pixels);
      `num_samples` sampled rays (those the source can project); `num_target_invalid`: sampled
      rays the target model reports invalid (outside its own domain; 0 for a good conversion);
    - `num_steps`, `converged`: of the Levenberg-Marquardt fit that was kept; `num_starts`: how
      many starts were fitted.
    """

    camera: AbstractCamera
    max_px: Float[Array, ""]
    rms_px: Float[Array, ""]
    max_px_in_image: Float[Array, ""]
    rms_px_in_image: Float[Array, ""]
    theta_max: Float[Array, ""]
    max_radius_px: Float[Array, ""]
    num_samples: Int[Array, ""]
    num_target_invalid: Int[Array, ""]
    num_steps: Int[Array, ""]
    converged: Bool[Array, ""]
    num_starts: int = eqx.field(static=True, default=1)


def image_pixel_grid(width: int, height: int, n: int) -> np.ndarray:
    """About ``n`` pixel centres on a regular grid spanning the image, corners and border
    pixels included (``(M, 2)``, pixel-centre convention)."""
    nu = max(2, round(math.sqrt(n * width / height)))
    nv = max(2, round(n / nu))
    u = np.linspace(0.0, width - 1.0, min(nu, width)) if width > 1 else np.zeros(1)
    v = np.linspace(0.0, height - 1.0, min(nv, height)) if height > 1 else np.zeros(1)
    uu, vv = np.meshgrid(u, v)
    return np.stack([uu.ravel(), vv.ravel()], -1)


def _image_rays(camera: AbstractCamera, n: int, dtype) -> Array:
    """The source's rays of a grid of about ``n`` pixels over the image: the image's valid
    pixels (pixels without a ray are dropped)."""
    grid = image_pixel_grid(camera.width, camera.height, n)
    rays, valid = jit_unproject(camera, jnp.asarray(grid, dtype))
    rays, valid = np.asarray(rays), np.asarray(valid)
    return jnp.asarray(rays[valid], dtype)


def camera_theta_max(camera: AbstractCamera, dtype=None) -> Float[Array, ""]:
    """A camera's largest valid incidence angle: its ``theta_max()`` if it has one, else 90 degrees."""
    fn = getattr(camera, "theta_max", None)
    if fn is None:
        return jnp.asarray(math.pi / 2, dtype)
    return jnp.asarray(fn(dtype), dtype)


def sample_rays(theta_top: float, n_theta: int, n_phi: int, dtype) -> Float[Array, "M 3"]:
    """Unit rays on ``n_theta`` incidence angles in ``(0, theta_top]`` (uniform) times ``n_phi``
    azimuths, plus the optical axis."""
    theta = np.linspace(0.0, theta_top, n_theta + 1)[1:]
    phi = np.linspace(0.0, 2 * math.pi, n_phi, endpoint=False)
    tt, pp = np.meshgrid(theta, phi, indexing="ij")
    rays = np.stack([np.sin(tt) * np.cos(pp), np.sin(tt) * np.sin(pp), np.cos(tt)], -1).reshape(-1, 3)
    rays = np.concatenate([np.array([[0.0, 0.0, 1.0]]), rays])
    return jnp.asarray(rays, dtype)


_PROBE_EPS = 1e-5
_PROFILE = 63


def _init_rays(top: float, dtype) -> Array:
    """The optical axis, two rays ``_PROBE_EPS`` off it (focal lengths), and a profile of
    ``_PROFILE`` rays along +x up to ``top`` (radial coefficients)."""
    e = _PROBE_EPS
    theta = np.linspace(0.0, top, _PROFILE + 1)[1:]
    profile = np.stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)], -1)
    probe = np.array([[0.0, 0.0, 1.0], [math.sin(e), 0.0, math.cos(e)], [0.0, math.sin(e), math.cos(e)]])
    return jnp.asarray(np.concatenate([probe, profile]), dtype)


def _initial_from(source: AbstractCamera, model: str, uv, valid, top: float, dtype) -> AbstractCamera:
    uv = np.asarray(uv, dtype=np.float64)
    valid = np.asarray(valid)
    cx, cy = uv[0]
    fx = (uv[1, 0] - cx) / math.tan(_PROBE_EPS)
    fy = (uv[2, 1] - cy) / math.tan(_PROBE_EPS)
    theta = np.linspace(0.0, top, _PROFILE + 1)[1:][valid[3:]]
    radius = (uv[3:, 0] - cx)[valid[3:]]
    w, h = source.width, source.height
    if model == "radial_poly":
        k = [fx, 0.0, 0.0, 0.0]
        if theta.size >= 8:
            k = np.linalg.lstsq(np.stack([theta**i for i in range(1, 5)], -1), radius, rcond=None)[0]
        vec = [*k, cx - (w / 2 - 0.5), cy - (h / 2 - 0.5), fy / fx]
    elif model == "kannala_brandt":
        k = [0.0, 0.0, 0.0, 0.0]
        if theta.size >= 8:
            k = np.linalg.lstsq(np.stack([theta ** (2 * i + 3) for i in range(4)], -1), radius / fx - theta,
                                rcond=None)[0]
        vec = [fx, fy, cx, cy, *k]
    elif model in INITIAL_FROM_PROFILE:
        vec = initial_vector(model, fx, fy, cx, cy, theta, radius)
    elif model == "unified":
        vec = [fx, fy, cx, cy, 0.5]
    elif model == "extended_unified":
        vec = [fx, fy, cx, cy, 0.5, 1.0]
    elif model == "pinhole":
        vec = [fx, fy, cx, cy]
    elif model in ("ocamcalib", "ftheta", "carla_wide_angle"):
        return _initial_radial_polynomial(model, fx, fy, cx, cy, theta, radius, w, h, dtype)
    else:
        vec = [fx, fy, cx, cy, 0.0, 0.5]
    return camera_from_intrinsics(model, np.asarray(vec, dtype=np.float64), width=w, height=h, dtype=dtype)


def _initial_radial_polynomial(model, fx, fy, cx, cy, theta, radius, w, h, dtype) -> AbstractCamera:
    """Starting points of the pixel-radius polynomial models (OCamCalib, f-theta) and of CARLA's
    Kannala-Brandt lens, from the source's focal lengths and its radius profile along +x."""
    x = radius * (fy / fx)  # the profile in v-units (OCamCalib's c, NCore's c carry fx / fy)
    enough = theta.size >= 8
    if model == "ocamcalib":
        pol = [-fy, 0.0, 0.0, 0.0, 0.0]
        if enough:  # pol(rho) = -rho cos(alpha) / sin(alpha), with a1 = 0 as OCamCalib
            scale = max(float(x.max()), 1.0)
            s_ = x / scale
            a = np.stack([np.ones_like(s_), s_**2, s_**3, s_**4], -1)
            coef = np.linalg.lstsq(a, -x * np.cos(theta) / np.sin(theta), rcond=None)[0]
            pol = [coef[0], 0.0, coef[1] / scale**2, coef[2] / scale**3, coef[3] / scale**4]
        cam = OCamCalib(np.asarray(pol), xc=cy, yc=cx, c=fy / fx, width=w, height=h, dtype=dtype)
        return cam.with_fitted_inverse()
    if model == "ftheta":
        bw = [1.0 / fy]
        if enough:
            scale = max(float(x.max()), 1.0)
            s_ = x / scale
            coef = np.linalg.lstsq(np.stack([s_**i for i in range(1, 6)], -1), theta, rcond=None)[0]
            bw = [coef[i] / scale ** (i + 1) for i in range(5)]
        cam = FTheta(cx, cy, np.asarray(bw), max_angle=math.pi, c=fx / fy, width=w, height=h, dtype=dtype)
        return cam.with_fitted_inverse()
    f = 0.5 * (fx + fy)
    k = np.zeros(4)
    if enough:
        k = np.linalg.lstsq(np.stack([theta ** (2 * i + 3) for i in range(4)], -1), radius / fx - theta,
                            rcond=None)[0]
    grid = np.linspace(0.0, math.pi, 4097)
    r = f * grid * (1 + k[0] * grid**2 + k[1] * grid**4 + k[2] * grid**6 + k[3] * grid**8)
    rising = np.concatenate([[True], np.diff(r) > 0])
    last = int(np.argmin(rising)) if not rising.all() else len(grid)
    half = float(np.interp(h / 2, r[:last], grid[:last]))
    return CarlaWideAngle("kannala-brandt", 2 * math.degrees(half), k, width=w, height=h, dtype=dtype)


def refresh_approximations(camera: AbstractCamera) -> AbstractCamera:
    """``camera`` with its approximate inverse polynomials (`APPROXIMATION_PARAMETERS`: OCamCalib's
    ``invpol``, f-theta's forward polynomial) fitted again to its exact model; other cameras
    unchanged. Conversions call it after fitting, so that the files they write carry inverse
    polynomials the other tools can use."""
    fit = getattr(camera, "with_fitted_inverse", None)
    return camera if fit is None else fit()


def _source_dtype(source: AbstractCamera):
    return jnp.result_type(*[x for x in jax.tree_util.tree_leaves(source) if eqx.is_inexact_array(x)][:1])


SHAPE_GRIDS: dict[str, dict[str, np.ndarray]] = {
    "unified": {"alpha": np.linspace(0.0, 0.99, 100)},
    "extended_unified": {"beta": np.geomspace(0.25, 4.0, 17), "alpha": np.linspace(0.0, 0.99, 100)},
    "double_sphere": {"xi": np.linspace(-0.8, 0.9, 18), "alpha": np.linspace(0.0, 0.995, 200)},
}
"""Grids of the shape parameters scanned for starts (`shape_scan_starts`), per model: the first
is scanned, the others (finely sampled: the cost valley is narrow in α) are profiled out with the
focal lengths (the projection is linear in those)."""
NUM_STARTS = 3
"""At most this many starts (the best local minima of the scan) are fitted besides the initial
guess; the best fit is kept."""
_SCAN_RAYS = 1024
"""Rays (a subsample of the conversion's) used for the scan."""


@eqx.filter_jit
def _profile(cams, rays, du, dv, w):
    """Per scanned camera (``fx = fy = 1``, principal point 0): the least-squares focal lengths,
    the residual sum of squares with them over target-valid rays, and the count of rays the
    camera cannot project."""

    def one(c):
        m, valid = c.project(rays)
        wv = jnp.where(valid, w, 0.0)
        mx, my = m[..., 0], m[..., 1]
        tiny = jnp.finfo(m.dtype).tiny
        fx = jnp.sum(wv * mx * du) / jnp.maximum(jnp.sum(wv * mx * mx), tiny)
        fy = jnp.sum(wv * my * dv) / jnp.maximum(jnp.sum(wv * my * my), tiny)
        sse = jnp.sum(wv * ((fx * mx - du) ** 2 + (fy * my - dv) ** 2))
        return fx, fy, sse, jnp.sum((w > 0) & ~valid)

    return jax.lax.map(one, cams, batch_size=256)


def shape_scan_starts(model: str, cx: float, cy: float, rays, uv_src, ok, *, width: int, height: int, dtype,
                      num_starts: int = NUM_STARTS) -> list[AbstractCamera]:
    """Starts for fitting ``model`` to the source pixels ``uv_src`` of ``rays`` (``ok``: the
    source projects them), from the model's `SHAPE_GRIDS`: every grid point gets the source's
    principal point and the focal lengths that fit best for it (linear least squares) and is
    ranked by (rays it cannot project, residual sum of squares); the other shape parameters are
    profiled out (the best grid point for each value of the first); the starts are the best
    ``num_starts`` local minima of that profile along the first parameter. Empty for models
    without a grid."""
    grid = SHAPE_GRIDS.get(model)
    if grid is None:
        return []
    names = parameter_names(model)[4:]
    order_names = list(grid)
    mesh = np.meshgrid(*[np.asarray(grid[n], dtype=np.float64) for n in order_names], indexing="ij")
    shape = mesh[0].shape
    columns = {n: g.ravel() for n, g in zip(order_names, mesh, strict=True)}
    flat = np.stack([columns[n] for n in names], -1)  # parameter-vector order
    cams = [camera_from_intrinsics(model, np.r_[1.0, 1.0, 0.0, 0.0, row], width=width, height=height, dtype=dtype)
            for row in flat]
    stacked = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *cams)
    step = max(1, int(rays.shape[0]) // _SCAN_RAYS)
    uv = jnp.asarray(uv_src)[::step]
    w = jnp.asarray(ok)[::step].astype(dtype)
    du = jnp.where(w > 0, uv[:, 0] - cx, 0.0)
    dv = jnp.where(w > 0, uv[:, 1] - cy, 0.0)
    fx, fy, sse, bad = (np.asarray(x) for x in _profile(stacked, jnp.asarray(rays)[::step], du, dv, w))
    usable = (fx > 0) & (fy > 0) & np.isfinite(sse)
    if not usable.any():
        return []
    fewest = bad[usable].min()
    score = np.where(usable & (bad == fewest), sse, np.inf).reshape(shape[0], -1)
    best_rest = np.argmin(score, axis=1)  # the profile along the first grid parameter
    profile = score[np.arange(shape[0]), best_rest]
    left = np.r_[np.inf, profile[:-1]]
    right = np.r_[profile[1:], np.inf]
    local = np.isfinite(profile) & (profile <= left) & (profile <= right)
    picks = [i for i in np.argsort(profile) if local[i]][:num_starts]
    starts = []
    for i in picks:
        k = np.ravel_multi_index((i, best_rest[i]), (shape[0], score.shape[1]))
        starts.append(camera_from_intrinsics(model, np.r_[fx[k], fy[k], cx, cy, flat[k]], width=width, height=height,
                                             dtype=dtype))
    return starts


def initial_camera(source: AbstractCamera, model: str, *, theta_top: float | None = None) -> AbstractCamera:
    """A starting point for fitting ``model`` to ``source``: the source's principal point and
    focal lengths at the optical axis, radial coefficients by a linear least-squares fit of the
    source's radius along +x up to ``theta_top`` (radial_poly and kannala_brandt), a fit of that
    profile for mei, opencv, fov and fisheye624 (`_initial.initial_vector`), neutral shape
    parameters otherwise (α = 0.5, β = 1, ξ = 0)."""
    model = canonical_model_name(model)
    dtype = _source_dtype(source)
    top = float(camera_theta_max(source, dtype)) if theta_top is None else theta_top
    top = min(top, math.pi - BEHIND_AXIS_MARGIN_RAD)
    uv, valid = jit_project(source, _init_rays(top, dtype))
    return _initial_from(source, model, uv, valid, top, dtype)


def convert_camera(
    source: AbstractCamera,
    target: str | type | AbstractCamera,
    *,
    fov: str = "lens",
    theta_max: float | None = None,
    n_theta: int = 256,
    n_phi: int = 32,
    fixed: Iterable[str] | Sequence[bool] | None = None,
    max_steps: int = 200,
) -> ConversionResult:
    """Fit a camera of model ``target`` to ``source`` over a domain of rays.

    The domain: ``fov="lens"`` rays on ``n_theta`` incidence angles x ``n_phi`` azimuths up to the
    source's own ``theta_max`` (its whole lens domain, the default; capped
    ``BEHIND_AXIS_MARGIN_RAD`` below pi); ``fov="image"`` the image's valid pixels: the source's
    rays of a grid of about ``n_theta * n_phi`` pixels spanning the image (corners and border
    included; pixels without a ray dropped); an explicit ``theta_max`` (radians) rays up to that
    angle. The target's parameters minimise the squared pixel distance between the two
    projections (Levenberg-Marquardt, see `refit`) from several starts, keeping the best (fewest
    rays outside the target's domain, then the smallest RMS): the initial guess (`initial_camera`)
    and, for models with shape parameters, the best local minima of a scan of those parameters
    with the focal lengths profiled out (`shape_scan_starts`), so the fit reaches the global
    optimum rather than the local minimum next to a neutral start. ``target`` is a model name
    (`MODEL_CLASSES`, aliases such as ``"kb"``), a camera class, or a camera instance (then the
    only start). Parameters named in ``fixed`` keep the initial guess's values in every start.
    The same image size is kept.

    Samples too few to determine the target's free parameters are refused (ValueError):
    ``n_theta`` and ``n_phi`` must be integers >= 1; over the lens, at least one incidence angle
    per free parameter and `MIN_AZIMUTHS` azimuths; in every domain, at least
    `MIN_RAYS_PER_PARAMETER` rays the source projects per free parameter.
    """
    n_theta = positive_integer(n_theta, "convert_camera: n_theta")
    n_phi = positive_integer(n_phi, "convert_camera: n_phi")
    names = parameter_names(target)
    n_free = sum(free_parameter_mask(names, fixed))
    model_name = canonical_model_name(target)
    if fov != "image" or theta_max is not None:
        if n_theta < n_free:
            raise ValueError(f"convert_camera: n_theta={n_theta} incidence angles cannot determine the {n_free} free "
                             f"parameters of {model_name}: use n_theta >= {n_free}")
        if n_phi < MIN_AZIMUTHS:
            raise ValueError(f"convert_camera: n_phi={n_phi} azimuths lie in one plane through the optical axis and "
                             f"cannot determine {model_name}: use n_phi >= {MIN_AZIMUTHS}")
    dtype = _source_dtype(source)
    if theta_max is not None:
        top = min(float(theta_max), math.pi - BEHIND_AXIS_MARGIN_RAD)
        if not top > 0:
            raise ValueError(f"convert_camera: nothing to sample (theta_max = {top})")
        rays = sample_rays(top, n_theta, n_phi, dtype)
    elif fov == "lens":
        top = min(float(camera_theta_max(source, dtype)) - SOURCE_THETA_MARGIN_RAD, math.pi - BEHIND_AXIS_MARGIN_RAD)
        if not top > 0:
            raise ValueError(f"convert_camera: nothing to sample (theta_max = {top})")
        rays = sample_rays(top, n_theta, n_phi, dtype)
    elif fov == "image":
        rays = _image_rays(source, n_theta * n_phi, dtype)
        if rays.shape[0] == 0:
            raise ValueError("convert_camera: no pixel of the image has a ray")
        top = min(float(np.max(np.arccos(np.clip(np.asarray(rays[:, 2]), -1.0, 1.0)))),
                  math.pi - BEHIND_AXIS_MARGIN_RAD)
    else:
        raise ValueError(f"convert_camera: fov must be 'lens' or 'image', got {fov!r}")
    # One projection (one compile per source model) for the initial guess and the samples.
    uv_all, ok_all = jit_project(source, jnp.concatenate([_init_rays(top, dtype), rays]))
    n_init = _PROFILE + 3
    uv_src, ok = uv_all[n_init:], ok_all[n_init:]
    projected = int(jnp.sum(ok))
    if projected < MIN_RAYS_PER_PARAMETER * n_free:
        raise ValueError(f"convert_camera: the source projects {projected} of the {rays.shape[0]} sampled rays, too few "
                         f"to determine the {n_free} free parameters of {model_name} (at least "
                         f"{MIN_RAYS_PER_PARAMETER * n_free}: sample more rays with n_theta, n_phi)")
    uv_src = jnp.where(ok[:, None], uv_src, jnp.zeros((), dtype))  # the rays it cannot project have weight 0
    if isinstance(target, AbstractCamera):
        starts = [target]
    else:
        model = canonical_model_name(target)
        first = _initial_from(source, model, uv_all[:n_init], ok_all[:n_init], top, dtype)
        cx, cy = (float(x) for x in np.asarray(uv_all[0]))
        starts = [first, *shape_scan_starts(model, cx, cy, rays, uv_src, ok, width=source.width,
                                            height=source.height, dtype=dtype)]
    corr = Correspondences(rays, uv_src, None, ok.astype(dtype))
    rtol, atol = default_tolerances(dtype)
    free = jnp.asarray(free_parameter_mask(parameter_names(starts[0]), fixed))
    held = intrinsics_vector(starts[0]).astype(dtype)
    best = None
    for init in starts:
        # The refit solve without covariance or residual summary (conversion reports its own errors).
        p0 = jnp.where(free, intrinsics_vector(init).astype(dtype), held)  # fixed: the initial guess's values
        init = with_intrinsics(init, p0)
        p, _, _, _, steps, converged = solve_refit(
            init, p0, free, jnp.eye(3, dtype=dtype)[None], jnp.zeros((1, 3), dtype), corr, False, jnp.asarray(0),
            jnp.asarray(1.0, dtype), int(max_steps), rtol, atol, with_covariance=False,
        )
        camera = refresh_approximations(with_intrinsics(init, p))
        stats = _compare(camera, source, rays, uv_src, ok)
        key = (int(stats[-1]), float(stats[1]) if np.isfinite(float(stats[1])) else math.inf)
        if best is None or key < best[0]:
            best = (key, camera, stats, steps, converged)
    _, camera, stats, steps, converged = best
    return ConversionResult(
        camera, *stats[:4], theta_max=jnp.asarray(top, dtype), max_radius_px=stats[4], num_samples=jnp.sum(ok),
        num_target_invalid=stats[-1], num_steps=steps, converged=converged, num_starts=len(starts),
    )


@eqx.filter_jit
def _compare(cam, source, rays, uv_src, ok):
    uv_dst, valid_dst = cam.project(rays)
    zero = jnp.zeros((), uv_src.dtype)
    both = ok & valid_dst
    d = jnp.where(both, jnp.sqrt(jnp.sum((uv_dst - uv_src) ** 2, axis=-1)), zero)
    inside = source.contains(uv_src) & both
    axis_px = source.project(jnp.asarray([0.0, 0.0, 1.0], rays.dtype))[0]
    radius = jnp.where(ok, jnp.sqrt(jnp.sum((uv_src - axis_px) ** 2, axis=-1)), zero)
    return (
        jnp.max(d),
        jnp.sqrt(jnp.sum(d * d) / jnp.maximum(jnp.sum(both).astype(d.dtype), 1.0)),
        jnp.max(jnp.where(inside, d, zero)),
        jnp.sqrt(jnp.sum(jnp.where(inside, d * d, zero)) / jnp.maximum(jnp.sum(inside).astype(d.dtype), 1.0)),
        jnp.max(radius),
        jnp.sum(ok & ~valid_dst),
    )
