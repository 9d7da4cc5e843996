"""Convert a calibration from one lens model to another by fitting over the field of view."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ..cameras import AbstractCamera, CarlaWideAngle, FTheta, OCamCalib
from ._fit import Correspondences, _default_tolerances, _free_mask, _solve, jit_project, jit_unproject
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


class ConversionResult(eqx.Module):
    """The outcome of `convert_camera`.

    - `camera`: the fitted camera of the target model;
    - `max_px`, `rms_px`: largest and RMS pixel distance between the source's and the target's
      projections of every sampled ray (``sqrt(mean |d|²)``); `max_px_in_image`,
      `rms_px_in_image`: the same over rays whose source pixel lies inside the image;
    - `theta_max`: the largest sampled incidence angle (radians); `num_samples` sampled rays
      (those the source can project); `num_target_invalid`: sampled rays the target model
      reports invalid (outside its own domain; 0 for a good conversion);
    - `num_steps`, `converged`: of the Levenberg-Marquardt fit.
    """

    camera: AbstractCamera
    max_px: Float[Array, ""]
    rms_px: Float[Array, ""]
    max_px_in_image: Float[Array, ""]
    rms_px_in_image: Float[Array, ""]
    theta_max: Float[Array, ""]
    num_samples: Int[Array, ""]
    num_target_invalid: Int[Array, ""]
    num_steps: Int[Array, ""]
    converged: Bool[Array, ""]


def _image_theta_max(camera: AbstractCamera, dtype) -> float:
    """Largest incidence angle among the valid pixels of the image border (radians)."""
    w, h = camera.width, camera.height
    n = 256
    u = np.linspace(-0.5, w - 0.5, n)
    v = np.linspace(-0.5, h - 0.5, n)
    border = np.concatenate([
        np.stack([u, np.full(n, -0.5)], -1), np.stack([u, np.full(n, h - 0.5)], -1),
        np.stack([np.full(n, -0.5), v], -1), np.stack([np.full(n, w - 0.5), v], -1),
    ])
    rays, valid = jit_unproject(camera, jnp.asarray(border, dtype))
    theta = np.arccos(np.clip(np.asarray(rays[..., 2]), -1.0, 1.0))
    valid = np.asarray(valid)
    if not valid.all():  # the lens boundary crosses the image: the source's own domain limits it
        return float(camera_theta_max(camera, dtype)) - SOURCE_THETA_MARGIN_RAD
    return float(theta[valid].max())


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
    elif model == "unified":
        vec = [fx, fy, cx, cy, 0.5]
    elif model == "extended_unified":
        vec = [fx, fy, cx, cy, 0.5, 1.0]
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


def initial_camera(source: AbstractCamera, model: str, *, theta_top: float | None = None) -> AbstractCamera:
    """A starting point for fitting ``model`` to ``source``: the source's principal point and
    focal lengths at the optical axis, radial coefficients by a linear least-squares fit of the
    source's radius along +x up to ``theta_top`` (radial_poly and kannala_brandt), neutral shape
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
    """Fit a camera of model ``target`` to ``source`` over the field of view.

    Rays are sampled densely (``n_theta`` incidence angles x ``n_phi`` azimuths) up to:
    ``fov="lens"`` the source's own ``theta_max`` (its whole lens domain, the default; capped
    ``BEHIND_AXIS_MARGIN_RAD`` below pi), ``fov="image"`` the largest incidence angle seen by
    the image border, or an explicit ``theta_max`` (radians). The target's parameters minimise
    the squared pixel distance between the two projections (Levenberg-Marquardt, see `refit`);
    ``target`` is a model name (`MODEL_CLASSES`, aliases such as ``"kb"``), a camera class, or a
    camera instance used as the initial guess. The same image size is kept.
    """
    dtype = _source_dtype(source)
    if theta_max is not None:
        top = float(theta_max)
    elif fov == "lens":
        top = float(camera_theta_max(source, dtype)) - SOURCE_THETA_MARGIN_RAD
    elif fov == "image":
        top = _image_theta_max(source, dtype)
    else:
        raise ValueError(f"convert_camera: fov must be 'lens' or 'image', got {fov!r}")
    top = min(top, math.pi - BEHIND_AXIS_MARGIN_RAD)
    if not top > 0:
        raise ValueError(f"convert_camera: nothing to sample (theta_max = {top})")
    rays = sample_rays(top, int(n_theta), int(n_phi), dtype)
    # One projection (one compile per source model) for the initial guess and the samples.
    uv_all, ok_all = jit_project(source, jnp.concatenate([_init_rays(top, dtype), rays]))
    n_init = _PROFILE + 3
    uv_src, ok = uv_all[n_init:], ok_all[n_init:]
    if isinstance(target, AbstractCamera):
        init = target
    else:
        init = _initial_from(source, canonical_model_name(target), uv_all[:n_init], ok_all[:n_init], top, dtype)
    # The refit solve without covariance or residual summary (conversion reports its own errors).
    p0 = intrinsics_vector(init).astype(dtype)
    init = with_intrinsics(init, p0)
    corr = Correspondences(rays, uv_src, None, ok.astype(dtype))
    free = jnp.asarray(_free_mask(parameter_names(init), fixed))
    rtol, atol = _default_tolerances(dtype)
    p, _, _, _, steps, converged = _solve(
        init, p0, free, jnp.eye(3, dtype=dtype)[None], jnp.zeros((1, 3), dtype), corr, False, jnp.asarray(0),
        jnp.asarray(1.0, dtype), int(max_steps), rtol, atol, with_covariance=False,
    )
    camera = refresh_approximations(with_intrinsics(init, p))
    stats = _compare(camera, source, rays, uv_src, ok)
    return ConversionResult(
        camera, *stats[:4], theta_max=jnp.asarray(top, dtype), num_samples=jnp.sum(ok),
        num_target_invalid=stats[-1], num_steps=steps, converged=converged,
    )


@eqx.filter_jit
def _compare(cam, source, rays, uv_src, ok):
    uv_dst, valid_dst = cam.project(rays)
    zero = jnp.zeros((), uv_src.dtype)
    d = jnp.where(ok, jnp.sqrt(jnp.sum((uv_dst - uv_src) ** 2, axis=-1)), zero)
    inside = source.contains(uv_src) & ok
    return (
        jnp.max(d),
        jnp.sqrt(jnp.sum(d * d) / jnp.maximum(jnp.sum(ok).astype(d.dtype), 1.0)),
        jnp.max(jnp.where(inside, d, zero)),
        jnp.sqrt(jnp.sum(jnp.where(inside, d * d, zero)) / jnp.maximum(jnp.sum(inside).astype(d.dtype), 1.0)),
        jnp.sum(ok & ~valid_dst),
    )
