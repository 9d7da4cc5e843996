"""KannalaBrandt against cv2.fisheye (theta < 90 deg), closed forms beyond, and its own laws."""

from __future__ import annotations

import math

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish.cameras as jc
from tests import tolerances as tol
from tests.helpers import central_difference_jacobian, three_ways

K = (0.03, -0.006, 0.001, -0.0001)
#: One batch size for every test: the session's compiled project/unproject are reused.
N = 512


def _camera(k=K, dtype=jnp.float64) -> jc.KannalaBrandt:
    return jc.KannalaBrandt(310.0, 305.0, 641.3, 479.8, k, width=1280, height=966, dtype=dtype)


def _rays(theta_max: float, n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    theta = rng.uniform(0.0, theta_max, n)
    phi = rng.uniform(0.0, 2 * np.pi, n)
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)


def _reference_project(cam, p: np.ndarray) -> np.ndarray:
    """The textbook formula, float64 numpy (division by chi: no point on the axis here)."""
    k = np.asarray(cam.k)
    chi = np.hypot(p[:, 0], p[:, 1])
    t = np.arctan2(chi, p[:, 2])
    td = t * (1 + k[0] * t**2 + k[1] * t**4 + k[2] * t**6 + k[3] * t**8)
    return np.stack([float(cam.fx) * td * p[:, 0] / chi + float(cam.cx),
                     float(cam.fy) * td * p[:, 1] / chi + float(cam.cy)], -1)


def test_project_matches_cv2_fisheye_below_90_degrees(jit_project):
    cam = _camera()
    pts = _rays(math.radians(85), N) * np.random.default_rng(1).uniform(0.5, 20, (N, 1))
    uv, valid = jit_project(cam, jnp.asarray(pts))
    assert bool(jnp.all(valid))
    ref, _ = cv2.fisheye.projectPoints(pts[:, None, :], np.zeros(3), np.zeros(3), np.asarray(cam.intrinsic_matrix),
                                       np.asarray(K))
    np.testing.assert_allclose(np.asarray(uv), ref[:, 0, :], rtol=0, atol=tol.CV2_PROJECT_PX)


def test_unproject_matches_cv2_fisheye_below_73_degrees(jit_project, jit_unproject):
    cam = _camera()
    uv_in, _ = jit_project(cam, jnp.asarray(_rays(math.radians(73), N, seed=2)))
    uv_in = np.asarray(uv_in)
    rays, valid = jit_unproject(cam, jnp.asarray(uv_in))
    assert bool(jnp.all(valid))
    und = cv2.fisheye.undistortPoints(uv_in[:, None, :], np.asarray(cam.intrinsic_matrix), np.asarray(K))[:, 0]
    expected = np.c_[und, np.ones(len(und))]
    expected /= np.linalg.norm(expected, axis=-1, keepdims=True)
    angle = np.arccos(np.clip(np.sum(np.asarray(rays) * expected, -1), -1, 1))
    assert angle.max() < tol.CV2_UNPROJECT_RAD


def test_project_beyond_90_degrees_matches_formula(jit_project):
    cam = _camera()
    theta_max = float(cam.theta_max())
    assert theta_max > math.radians(120), "this lens is monotone well beyond 90 degrees"
    rays = _rays(theta_max, N, seed=3) * 3.0
    uv, valid = jit_project(cam, jnp.asarray(rays))
    assert bool(jnp.all(valid))
    np.testing.assert_allclose(np.asarray(uv), _reference_project(cam, rays), rtol=0, atol=tol.MODEL_PX_F64)


def test_theta_max_is_the_first_stationary_point(jit_project, jit_unproject):
    cam = _camera()
    tm = float(cam.theta_max())
    k = np.asarray(K)
    deriv = np.polynomial.Polynomial([1, 0, 3 * k[0], 0, 5 * k[1], 0, 7 * k[2], 0, 9 * k[3]])
    roots = [r.real for r in deriv.roots() if abs(r.imag) < 1e-12 and 0 < r.real <= np.pi]
    assert tm == pytest.approx(min(roots) - 1e-3, abs=1e-9)
    # Beyond theta_max: projection and unprojection are invalid.
    beyond = np.tile([np.sin(tm + 0.01), 0.0, np.cos(tm + 0.01)], (N, 1))
    assert not np.asarray(jit_project(cam, jnp.asarray(beyond))[1]).any()
    far_pixel = np.tile([float(cam.cx) + float(cam.fx) * 5.0, float(cam.cy)], (N, 1))
    assert not np.asarray(jit_unproject(cam, jnp.asarray(far_pixel))[1]).any()
    # A monotone lens (k = 0, equidistant) is valid up to pi.
    assert float(_camera(k=(0.0, 0.0, 0.0, 0.0)).theta_max()) == pytest.approx(math.pi)


def test_equidistant_unproject_closed_form_up_to_170_degrees(jit_unproject):
    cam = _camera(k=(0.0, 0.0, 0.0, 0.0))
    theta = np.linspace(0.0, math.radians(170), N)
    uv = np.stack([float(cam.cx) + float(cam.fx) * theta * np.cos(0.3), float(cam.cy) + float(cam.fy) * theta * np.sin(0.3)], -1)
    rays, valid = jit_unproject(cam, jnp.asarray(uv))
    assert bool(jnp.all(valid))
    expected = np.stack([np.sin(theta) * np.cos(0.3), np.sin(theta) * np.sin(0.3), np.cos(theta)], -1)
    np.testing.assert_allclose(np.asarray(rays), expected, rtol=0, atol=tol.MODEL_RAY_F64)


def test_roundtrips_eager_jit_vmap(jit_project, jit_unproject):
    cam = _camera()
    rays = jnp.asarray(_rays(float(cam.theta_max()) - 0.01, N, seed=4))
    uv, v1 = jit_project(cam, rays)
    back, v2 = jit_unproject(cam, uv)
    assert bool(jnp.all(v1 & v2))
    np.testing.assert_allclose(np.asarray(back), np.asarray(rays), rtol=0, atol=tol.MODEL_RAY_F64 * 100)
    # project: eager = jit = vmap (unproject's solve is the same code under jit and vmap).
    for out, _ in three_ways(lambda c, r: c.project(r), cam, rays[:8]):
        np.testing.assert_allclose(out, np.asarray(uv)[:8], rtol=0, atol=tol.MODEL_PX_F64)
    # Any leading batch shape: the same rays.
    batched, valid = jit_unproject(cam, uv.reshape(2, N // 2, 2))
    assert batched.shape == (2, N // 2, 3) and bool(jnp.all(valid))
    np.testing.assert_allclose(np.asarray(batched).reshape(-1, 3), np.asarray(back), rtol=0, atol=1e-15)


@pytest.mark.parametrize("dtype,atol", [(jnp.float64, tol.MODEL_PX_F64), (jnp.float32, tol.MODEL_PX_F32)])
def test_pixel_ray_pixel_over_the_image(dtype, atol, jit_project, jit_unproject):
    cam = _camera(dtype=dtype)
    u, v = np.meshgrid(np.linspace(-0.5, 1279.5, 32), np.linspace(-0.5, 965.5, N // 32))  # N pixels, whole image
    grid = jnp.asarray(np.stack([u, v], -1).reshape(-1, 2), dtype)
    rays, valid = jit_unproject(cam, grid)
    assert rays.dtype == dtype
    uv, valid2 = jit_project(cam, rays)
    ok = np.asarray(valid & valid2)
    assert ok.mean() > 0.8
    np.testing.assert_allclose(np.asarray(uv)[ok], np.asarray(grid)[ok], rtol=0, atol=atol)


def test_batch_shapes_and_shape_errors(jit_project):
    cam = _camera()
    uv, valid = jit_project(cam, jnp.ones((2, N // 2, 3)))
    assert uv.shape == (2, N // 2, 2) and valid.shape == (2, N // 2)
    uv, valid = cam.project(jnp.ones(3))
    assert uv.shape == (2,) and valid.shape == ()
    with pytest.raises(ValueError, match="shape"):
        cam.project(jnp.ones((4, 2)))
    with pytest.raises(ValueError, match="shape"):
        cam.unproject(jnp.ones((4, 3)))
    with pytest.raises(ValueError, match="image size"):
        jc.KannalaBrandt(1.0, 1.0, 0.0, 0.0, width=0, height=10)


def test_gradients_finite_at_the_principal_point_and_match_finite_differences():
    cam = _camera()
    g_p = jax.jit(jax.jacfwd(lambda c, p: c.project(p)[0], argnums=1))(cam, jnp.asarray([0.0, 0.0, 2.0]))
    assert np.isfinite(np.asarray(g_p)).all()
    # Rays of [principal point, a pixel at ~110 degrees] as a function of (k, uv): implicit
    # differentiation through the optimistix solve, vs central differences.
    uv = jnp.stack([cam.principal_point, jnp.asarray([1250.0, 900.0])])

    def rays(k, uv):
        return jc.KannalaBrandt(310.0, 305.0, 641.3, 479.8, k, width=1280, height=966).unproject(uv)[0]

    rays_jit = jax.jit(rays)
    d_k, d_uv = jax.jit(jax.jacfwd(rays, argnums=(0, 1)))(jnp.asarray(K), uv)
    assert np.isfinite(np.asarray(d_k)).all() and np.isfinite(np.asarray(d_uv)).all()
    d_uv_pp = np.asarray(d_uv)[0, :2, 0, :]
    np.testing.assert_allclose(d_uv_pp, np.diag([1 / float(cam.fx), 1 / float(cam.fy)]), atol=1e-9)
    numeric_k = central_difference_jacobian(lambda k: np.asarray(rays_jit(jnp.asarray(k), uv)), np.asarray(K), eps=1e-7)
    np.testing.assert_allclose(np.asarray(d_k).reshape(-1, 4), numeric_k, rtol=tol.JAC_FINITE_DIFF_REL, atol=1e-7)
    numeric_uv = central_difference_jacobian(lambda u: np.asarray(rays_jit(jnp.asarray(K), jnp.asarray(u).reshape(2, 2))),
                                             np.asarray(uv).ravel(), eps=1e-4)
    np.testing.assert_allclose(np.asarray(d_uv).reshape(6, 4)[3:], numeric_uv[3:], rtol=1e-6, atol=1e-9)
