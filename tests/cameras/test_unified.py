"""UnifiedCamera (UCM / Mei) and ExtendedUnifiedCamera (EUCM) against the paper's formulas and their laws."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish as jf
import jaxfish.cameras as jc
from tests import tolerances as tol
from tests.helpers import central_difference_jacobian, three_ways

N = 512


def _rays(theta_max: float, n: int = N, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    theta = rng.uniform(0.0, theta_max, n)
    phi = rng.uniform(0.0, 2 * np.pi, n)
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)


def _mei_reference(p, xi, gx, gy, cx, cy):
    """Mei's projection (Mei & Rives 2007, no distortion): u = γx X / (Z + ξ |p|) + cx."""
    d = np.linalg.norm(p, axis=-1)
    return np.stack([gx * p[:, 0] / (p[:, 2] + xi * d) + cx, gy * p[:, 1] / (p[:, 2] + xi * d) + cy], -1)


def _eucm_reference(p, fx, fy, cx, cy, a, b):
    d = np.sqrt(b * (p[:, 0] ** 2 + p[:, 1] ** 2) + p[:, 2] ** 2)
    den = a * d + (1 - a) * p[:, 2]
    return np.stack([fx * p[:, 0] / den + cx, fy * p[:, 1] / den + cy], -1)


CAMERAS = {
    "ucm_wide": jc.UnifiedCamera(280.0, 285.0, 640.2, 481.7, 0.62, width=1280, height=966),
    "ucm_narrow": jc.UnifiedCamera(280.0, 285.0, 640.2, 481.7, 0.35, width=1280, height=966),
    "eucm": jc.ExtendedUnifiedCamera(280.0, 285.0, 640.2, 481.7, 0.63, 1.15, width=1280, height=966),
    "eucm_low_alpha": jc.ExtendedUnifiedCamera(280.0, 285.0, 640.2, 481.7, 0.4, 0.8, width=1280, height=966),
}


def _wide_grid() -> jnp.ndarray:
    """N pixels on a 32 x 16 lattice reaching far beyond the 1280 x 966 image."""
    u, v = np.meshgrid(np.linspace(-900.0, 2200.0, 32), np.linspace(-900.0, 1900.0, N // 32))
    return jnp.asarray(np.stack([u, v], -1).reshape(-1, 2))


def _reference(cam, p):
    if isinstance(cam, jc.UnifiedCamera):
        a = float(cam.alpha)
        return _mei_reference(p, a / (1 - a), float(cam.fx) / (1 - a), float(cam.fy) / (1 - a), float(cam.cx), float(cam.cy))
    return _eucm_reference(p, *(float(x) for x in (cam.fx, cam.fy, cam.cx, cam.cy, cam.alpha, cam.beta)))


@pytest.mark.parametrize("name", list(CAMERAS))
def test_project_matches_closed_form_beyond_90_degrees(name, jit_project, jit_unproject):
    cam = CAMERAS[name]
    tm = float(cam.theta_max())
    assert tm > math.pi / 2, "valid beyond 90 degrees for every alpha > 0"
    rays = _rays(tm - 1e-3) * 2.5
    uv, valid = jit_project(cam, jnp.asarray(rays))
    assert bool(jnp.all(valid))
    np.testing.assert_allclose(np.asarray(uv), _reference(cam, rays), rtol=0, atol=tol.MODEL_PX_F64)
    back, valid = jit_unproject(cam, uv)
    assert bool(jnp.all(valid))
    np.testing.assert_allclose(np.asarray(back), rays / 2.5, rtol=0, atol=tol.MODEL_RAY_F64 * 100)
    # Just beyond the domain: invalid.
    over = np.tile([math.sin(tm + 1e-3), 0.0, math.cos(tm + 1e-3)], (N, 1))
    assert not np.asarray(jit_project(cam, jnp.asarray(over))[1]).any()


@pytest.mark.parametrize("name", list(CAMERAS))
def test_pixel_ray_pixel_and_unprojection_domain(name, jit_project, jit_unproject):
    cam = CAMERAS[name]
    grid = _wide_grid()  # reaches past the image
    rays, valid = jit_unproject(cam, grid)
    uv, valid2 = jit_project(cam, rays)
    ok = np.asarray(valid)
    assert np.asarray(valid2)[ok].all()
    np.testing.assert_allclose(np.asarray(uv)[ok], np.asarray(grid)[ok], rtol=0, atol=tol.MODEL_PX_F64)
    assert np.isfinite(np.asarray(rays)).all()
    if float(cam.alpha) > 0.5:  # pixels outside the disc r^2 <= 1 / (beta (2 alpha - 1)) have no ray
        beta = float(getattr(cam, "beta", 1.0))
        m = (np.asarray(grid) - [float(cam.cx), float(cam.cy)]) / [float(cam.fx), float(cam.fy)]
        r2 = np.sum(m * m, -1)
        outside = r2 > 1.0 / (beta * (2 * float(cam.alpha) - 1)) * 1.001
        assert outside.any() and not ok[outside].any()


def test_float32_roundtrip(jit_project, jit_unproject):
    cam = CAMERAS["eucm"].astype(jnp.float32)
    u, v = np.meshgrid(np.linspace(-0.5, 1279.5, 32), np.linspace(-0.5, 965.5, N // 32))
    grid = jnp.asarray(np.stack([u, v], -1).reshape(-1, 2), jnp.float32)
    rays, valid = jit_unproject(cam, grid)
    assert rays.dtype == jnp.float32
    uv, _ = jit_project(cam, rays)
    ok = np.asarray(valid)
    np.testing.assert_allclose(np.asarray(uv)[ok], np.asarray(grid)[ok], rtol=0, atol=tol.MODEL_PX_F32)


def test_special_cases():
    rays = jnp.asarray(_rays(1.2, 64, seed=5))
    ucm = jc.UnifiedCamera(280.0, 285.0, 640.2, 481.7, 0.6, width=1280, height=966)
    eucm = jc.ExtendedUnifiedCamera(280.0, 285.0, 640.2, 481.7, 0.6, 1.0, width=1280, height=966)
    np.testing.assert_allclose(np.asarray(ucm.project(rays)[0]), np.asarray(eucm.project(rays)[0]), atol=1e-12)
    mei = jc.UnifiedCamera.from_mei(1.5, 700.0, 712.5, 640.2, 481.7, width=1280, height=966)
    assert float(mei.alpha) == pytest.approx(0.6) and float(mei.fx) == pytest.approx(280.0)
    assert float(mei.xi) == pytest.approx(1.5)
    pinhole = jf.Pinhole(280.0, 285.0, 640.2, 481.7, width=1280, height=966)
    ucm0 = jc.UnifiedCamera(280.0, 285.0, 640.2, 481.7, 0.0, width=1280, height=966)
    np.testing.assert_allclose(np.asarray(ucm0.project(rays)[0]), np.asarray(pinhole.project(rays)[0]), atol=1e-12)
    assert float(ucm0.theta_max()) == pytest.approx(math.pi / 2)


@pytest.mark.parametrize("name", ["eucm"])
def test_eager_jit_vmap_and_gradients(name):
    cam = CAMERAS[name]
    rays = jnp.asarray(_rays(2.0, 16, seed=6))
    ref = _reference(cam, np.asarray(rays))
    for uv, valid in three_ways(lambda c, p: c.project(p), cam, rays):
        assert valid.all()
        np.testing.assert_allclose(uv, ref, atol=tol.MODEL_PX_F64)
    for rays_back, valid in three_ways(lambda c, u: c.unproject(u), cam, jnp.asarray(ref)):
        assert valid.all()
        np.testing.assert_allclose(rays_back, np.asarray(rays), atol=tol.MODEL_RAY_F64 * 100)
    # Finite gradients at the principal point; d uv / d params vs finite differences.
    g = jax.jit(jax.jacfwd(lambda p: cam.project(p)[0]))(jnp.asarray([0.0, 0.0, 1.0]))
    gu = jax.jit(jax.jacfwd(lambda u: cam.unproject(u)[0]))(cam.principal_point)
    assert np.isfinite(np.asarray(g)).all() and np.isfinite(np.asarray(gu)).all()
    leaves, treedef = jax.tree_util.tree_flatten(cam)
    flat = np.array([float(x) for x in leaves])

    def project_of(params):
        c = jax.tree_util.tree_unflatten(treedef, [jnp.asarray(x) for x in params])
        return c.project(rays)[0].ravel()

    project_of = jax.jit(project_of)
    analytic = jax.jit(jax.jacfwd(project_of))(jnp.asarray(flat))
    numeric = central_difference_jacobian(lambda p: np.asarray(project_of(jnp.asarray(p))), flat, eps=1e-6)
    np.testing.assert_allclose(np.asarray(analytic), numeric, rtol=tol.JAC_FINITE_DIFF_REL, atol=1e-5)
