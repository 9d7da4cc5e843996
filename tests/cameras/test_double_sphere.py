"""DoubleSphere against the paper's formulas (Usenko et al. 2018) and its laws."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish.cameras as jc
from tests import tolerances as tol
from tests.helpers import central_difference_jacobian, three_ways

N = 512


def _rays(theta_max: float, n: int = N, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    theta = rng.uniform(0.0, theta_max, n)
    phi = rng.uniform(0.0, 2 * np.pi, n)
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)


def _wide_grid() -> jnp.ndarray:
    """N pixels on a 32 x 16 lattice reaching far beyond the 1280 x 966 image."""
    u, v = np.meshgrid(np.linspace(-900.0, 2200.0, 32), np.linspace(-900.0, 1900.0, N // 32))
    return jnp.asarray(np.stack([u, v], -1).reshape(-1, 2))


def _reference(cam, p):
    fx, fy, cx, cy, xi, a = (float(x) for x in (cam.fx, cam.fy, cam.cx, cam.cy, cam.xi, cam.alpha))
    d1 = np.linalg.norm(p, axis=-1)
    zz = xi * d1 + p[:, 2]
    d2 = np.sqrt(p[:, 0] ** 2 + p[:, 1] ** 2 + zz**2)
    den = a * d2 + (1 - a) * zz
    return np.stack([fx * p[:, 0] / den + cx, fy * p[:, 1] / den + cy], -1)


CAMERAS = {
    # Usenko et al.'s fitted EuRoC/BF2M2020S23 values are of this order (xi ~ -0.2, alpha ~ 0.6).
    "negative_xi": jc.DoubleSphere(156.0, 155.8, 639.5, 482.3, -0.18, 0.59, width=1280, height=966),
    "positive_xi": jc.DoubleSphere(230.0, 231.0, 639.5, 482.3, 0.35, 0.57, width=1280, height=966),
    "low_alpha": jc.DoubleSphere(300.0, 301.0, 639.5, 482.3, 0.1, 0.4, width=1280, height=966),
}


@pytest.mark.parametrize("name", list(CAMERAS))
def test_project_matches_closed_form_and_roundtrips(name, jit_project, jit_unproject):
    cam = CAMERAS[name]
    tm = float(cam.theta_max())
    assert tm > math.pi / 2
    xi, a = float(cam.xi), float(cam.alpha)
    w1 = a / (1 - a) if a <= 0.5 else (1 - a) / a
    w2 = (w1 + xi) / math.sqrt(2 * w1 * xi + xi * xi + 1)
    assert tm == pytest.approx(math.acos(-w2), abs=1e-12)
    rays = _rays(tm - 1e-3) * 4.0
    uv, valid = jit_project(cam, jnp.asarray(rays))
    assert bool(jnp.all(valid))
    np.testing.assert_allclose(np.asarray(uv), _reference(cam, rays), rtol=0, atol=tol.MODEL_PX_F64)
    back, valid = jit_unproject(cam, uv)
    assert bool(jnp.all(valid))
    np.testing.assert_allclose(np.asarray(back), rays / 4.0, rtol=0, atol=tol.MODEL_RAY_F64 * 100)
    over = np.tile([math.sin(tm + 1e-3), 0.0, math.cos(tm + 1e-3)], (N, 1))
    assert not np.asarray(jit_project(cam, jnp.asarray(over))[1]).any()


@pytest.mark.parametrize("name", list(CAMERAS))
def test_pixel_ray_pixel(name, jit_project, jit_unproject):
    cam = CAMERAS[name]
    grid = _wide_grid()
    rays, valid = jit_unproject(cam, grid)
    uv, valid2 = jit_project(cam, rays)
    ok = np.asarray(valid)
    assert ok.any() and np.asarray(valid2)[ok].all() and np.isfinite(np.asarray(rays)).all()
    np.testing.assert_allclose(np.asarray(uv)[ok], np.asarray(grid)[ok], rtol=0, atol=tol.MODEL_PX_F64)
    if float(cam.alpha) > 0.5:
        m = (np.asarray(grid) - [float(cam.cx), float(cam.cy)]) / [float(cam.fx), float(cam.fy)]
        outside = np.sum(m * m, -1) > 1.0 / (2 * float(cam.alpha) - 1) * 1.001
        assert outside.any() and not ok[outside].any()


def test_xi_zero_is_the_unified_model():
    rays = jnp.asarray(_rays(2.0, 64, seed=3))
    ds = jc.DoubleSphere(280.0, 285.0, 640.2, 481.7, 0.0, 0.6, width=1280, height=966)
    ucm = jc.UnifiedCamera(280.0, 285.0, 640.2, 481.7, 0.6, width=1280, height=966)
    np.testing.assert_allclose(np.asarray(ds.project(rays)[0]), np.asarray(ucm.project(rays)[0]), atol=1e-12)
    assert float(ds.theta_max()) == pytest.approx(float(ucm.theta_max()), abs=1e-12)


def test_eager_jit_vmap_gradients_and_shapes():
    cam = CAMERAS["negative_xi"]
    rays = jnp.asarray(_rays(2.0, 16, seed=6))
    ref = _reference(cam, np.asarray(rays))
    for uv, valid in three_ways(lambda c, p: c.project(p), cam, rays):
        assert valid.all()
        np.testing.assert_allclose(uv, ref, atol=tol.MODEL_PX_F64)
    for back, valid in three_ways(lambda c, u: c.unproject(u), cam, jnp.asarray(ref)):
        assert valid.all()
        np.testing.assert_allclose(back, np.asarray(rays), atol=tol.MODEL_RAY_F64 * 100)
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
    uv, valid = cam.project(jnp.ones((2, 3, 3)))
    assert uv.shape == (2, 3, 2) and valid.shape == (2, 3)
    with pytest.raises(ValueError, match="shape"):
        cam.unproject(jnp.ones((4, 3)))
