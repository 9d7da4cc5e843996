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


_SCAN_STEP = math.pi / 40000


def _radius_profile(xi: float, alpha: float, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normalised image radius and projection denominator along the incidence angle, from the
    construction written out: the unit-sphere point shifted by xi, then UCM(alpha)."""
    x, z = np.sin(theta), np.cos(theta) + xi
    d2 = np.hypot(x, z)
    den = alpha * d2 + (1 - alpha) * z
    return x / np.where(den > 0, den, 1.0), den


def _scan_theta_max(xi: float, alpha: float) -> float:
    """Brute force: the first angle on a fine grid where the denominator is not positive or the
    image radius stops increasing (pi if neither happens before the back axis)."""
    theta = np.arange(0.0, math.pi + _SCAN_STEP / 2, _SCAN_STEP)
    r, den = _radius_profile(xi, alpha, theta)
    bad = (den[1:] <= 0) | (np.diff(r) <= 0)
    return float(theta[np.argmax(bad)]) if bad.any() else math.pi


# Both signs of xi, alpha on both sides of 0.5 and at the ends of [0, 1].
GRID = [(xi, a) for xi in (-0.95, -0.9, -0.5, -0.18, 0.0, 0.3, 0.7, 1.0) for a in (0.0, 0.3, 0.5, 0.59, 0.7, 0.9, 1.0)]


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
    assert tm == pytest.approx(_scan_theta_max(float(cam.xi), float(cam.alpha)), abs=2 * _SCAN_STEP)
    rays = _rays(tm - 1e-3) * 4.0
    uv, valid = jit_project(cam, jnp.asarray(rays))
    assert bool(jnp.all(valid))
    # rtol: alpha <= 0.5 sends the rim to infinity; rays 1e-3 inside it land 5e4 px out.
    np.testing.assert_allclose(np.asarray(uv), _reference(cam, rays), rtol=1e-13, atol=tol.MODEL_PX_F64)
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


def test_the_issue_examples_fold_where_the_construction_says():
    """xi = -0.9, alpha = 0.7 folds at 60.97 degrees (the paper's w2 bound says 62.4); xi = 1,
    alpha = 0 is the stereographic projection, valid to 180 degrees exclusive (w2 says 135)."""
    fold = jc.DoubleSphere(300.0, 300.0, 640.0, 480.0, -0.9, 0.7, width=640, height=480)
    assert math.degrees(float(fold.theta_max())) == pytest.approx(60.9714, abs=1e-4)
    deg = np.array([60.9, 60.97, 60.98, 62.0])
    p = np.stack([np.sin(np.radians(deg)), 0 * deg, np.cos(np.radians(deg))], -1)
    assert np.asarray(fold.project(jnp.asarray(p))[1]).tolist() == [True, True, False, False]
    stereo = jc.DoubleSphere(300.0, 300.0, 640.0, 480.0, 1.0, 0.0, width=640, height=480)
    assert float(stereo.theta_max()) == math.pi
    t = np.radians([100.0, 135.0, 136.0, 179.0, 179.99])
    p = np.stack([np.sin(t), 0 * t, np.cos(t)], -1)
    uv, valid = stereo.project(jnp.asarray(p))
    assert bool(jnp.all(valid))
    # X / (d + Z) = f tan(theta/2); at 179.99 deg d + Z cancels to 1.5e-8 (ulps of 1e-16 / 1.5e-8 relative)
    np.testing.assert_allclose(np.asarray(uv)[:4, 0] - 640.0, 300.0 * np.tan(t[:4] / 2), rtol=1e-12)
    assert not bool(stereo.project(jnp.asarray([0.0, 0.0, -1.0]))[1])


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_theta_max_and_validity_match_a_brute_force_monotonicity_scan(dtype, jit_project):
    theta = np.linspace(0.0, math.pi, 3001)[:-1]
    rays = np.stack([np.sin(theta), 0 * theta, np.cos(theta)], -1)
    for xi, a in GRID:
        cam = jc.DoubleSphere(300.0, 300.0, 640.0, 480.0, xi, a, width=1280, height=960, dtype=dtype)
        scan = _scan_theta_max(xi, a)
        tm = float(cam.theta_max())
        assert tm == pytest.approx(scan, abs=2 * _SCAN_STEP + (1e-5 if dtype == jnp.float32 else 0)), (xi, a)
        _, valid = jit_project(cam, jnp.asarray(rays, dtype))
        clear = np.abs(theta - tm) > (1e-9 if dtype == jnp.float64 else 1e-4)
        np.testing.assert_array_equal(np.asarray(valid)[clear], (theta < tm)[clear], err_msg=str((xi, a)))
        r, den = _radius_profile(xi, a, theta[theta < tm])
        assert (den > 0).all() and (np.diff(r) > 0).all(), (xi, a)


def test_unprojection_is_valid_exactly_on_the_image_of_the_domain(jit_project, jit_unproject):
    """A pixel has a ray exactly when its radius is below the radius of the domain's rim (none
    for lenses valid to pi); each valid ray lies in the domain and projects back to the pixel."""
    for xi, a in GRID:
        cam = jc.DoubleSphere(300.0, 300.0, 640.0, 480.0, xi, a, width=1280, height=960)
        tm = float(cam.theta_max())
        rim = math.inf  # alpha <= 0.5: the denominator vanishes at the rim, which lies at infinity
        if xi == 1.0:  # r -> sqrt(2(1+c)) / (alpha sqrt(2(1+c)) + (1-alpha)(1+c)) -> 1/alpha at the back axis
            rim = 300.0 / a if a > 0 else math.inf
        elif a > 0.5:
            rim = float(_radius_profile(xi, a, np.array([tm]))[0][0]) * 300.0
        radius = np.geomspace(1e-3, 1e5, 400)
        uv = np.stack([640.0 + radius, np.full_like(radius, 480.0)], -1)
        rays, valid = jit_unproject(cam, jnp.asarray(uv))
        valid = np.asarray(valid)
        clear = np.abs(radius - rim) > 1e-6 * rim if math.isfinite(rim) else np.ones_like(valid)
        np.testing.assert_array_equal(valid[clear], (radius < rim)[clear], err_msg=str((xi, a)))
        assert valid.any(), (xi, a)
        angle = np.arccos(np.clip(np.asarray(rays)[valid, 2], -1, 1))
        assert (angle < tm).all()
        back, ok = jit_project(cam, rays)
        assert np.asarray(ok)[valid].all()
        np.testing.assert_allclose(np.asarray(back)[valid], uv[valid], rtol=1e-9, atol=tol.MODEL_PX_F64)


def _masked_project_sum(c, p):
    q, v = c.project(p)
    return jnp.sum(jnp.where(v[:, None], q, 0.0))


def _masked_unproject_sum(c, x):
    r, v = c.unproject(x)
    return jnp.sum(jnp.where(v[:, None], r, 0.0))


_project_loss_grad = jax.jit(jax.grad(_masked_project_sum, argnums=(0, 1)))
_unproject_loss_grad = jax.jit(jax.grad(_masked_unproject_sum, argnums=(0, 1)))


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
@pytest.mark.parametrize("xi, alpha", [(-0.9, 0.7), (0.35, 0.57), (-0.18, 0.59), (0.3, 0.4), (1.0, 0.0), (1.0, 0.8)])
def test_no_nan_in_values_or_gradients_at_the_edge(xi, alpha, dtype):
    """Points just inside and outside theta_max and pixels just inside and outside the rim:
    finite values, and finite gradients of masked sums in the camera and in the inputs."""
    cam = jc.DoubleSphere(300.0, 300.0, 640.0, 480.0, xi, alpha, width=1280, height=960, dtype=dtype)
    tm = float(cam.theta_max())
    eps = 1e-6 if dtype == jnp.float64 else 1e-3
    t = np.array([tm - 10 * eps, tm - eps, tm, tm + eps, tm + 10 * eps, math.pi])
    t = np.minimum(t, math.pi)
    pts = jnp.asarray(np.stack([0.8 * np.sin(t), 0.6 * np.sin(t), np.cos(t)], -1), dtype)
    uv, valid = cam.project(pts)
    assert np.isfinite(np.asarray(uv)).all() and bool(valid[0]) and not bool(valid[-1])
    edge = np.asarray(uv)[np.asarray(valid)][-1] - np.array([640.0, 480.0])
    px = jnp.asarray(np.array([640.0, 480.0]) + edge * np.array([[0.5], [1.0 - eps], [1.0], [1.0 + eps], [2.0]]), dtype)
    rays, rvalid = cam.unproject(px)
    assert np.isfinite(np.asarray(rays)).all() and bool(rvalid[0])

    for grad_of, x in ((_project_loss_grad, pts), (_unproject_loss_grad, px)):
        g_cam, g_x = grad_of(cam, x)
        assert all(bool(jnp.all(jnp.isfinite(g))) for g in jax.tree_util.tree_leaves(g_cam))
        assert bool(jnp.all(jnp.isfinite(g_x)))
