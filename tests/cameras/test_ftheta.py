"""FTheta against the f-theta formulas written out here (NCore / Omniverse: angle = backward
polynomial of the pixel radius; the exact forward map by np.roots), and its own laws."""

from __future__ import annotations

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish.cameras as jc
from jaxfish.refit import convert_camera, intrinsics_from_dict, intrinsics_to_dict
from tests import tolerances as tol
from tests.helpers import central_difference_jacobian, three_ways

W, H = 1920, 1280
CX, CY = 958.7, 641.3
BW = (1.9e-3, 1.0e-7, -2.0e-10, 1.0e-13)  # radians per pixel^i (bw1 .. bw4)
AFFINE = dict(c=1.0007, d=0.0004, e=-0.0003)
MAX_ANGLE = math.radians(100.0)
N = 256


def _camera(dtype=jnp.float64, bw=BW, max_angle=MAX_ANGLE) -> jc.FTheta:
    return jc.FTheta(CX, CY, np.asarray(bw), max_angle=max_angle, **AFFINE, width=W, height=H,
                     dtype=dtype).with_fitted_inverse()


def ref_unproject(u, v, bw=BW, c=AFFINE["c"], d=AFFINE["d"], e=AFFINE["e"]):
    """Pixel -> ray: sensor offset through [[c, d], [e, 1]]⁻¹, theta = bw(r)."""
    x, y = np.linalg.solve(np.array([[c, d], [e, 1.0]]), [u - CX, v - CY])
    r = math.hypot(x, y)
    theta = sum(b * r ** (i + 1) for i, b in enumerate(bw))
    return np.array([math.sin(theta) * x / r, math.sin(theta) * y / r, math.cos(theta)])


def ref_project(p, bw=BW, c=AFFINE["c"], d=AFFINE["d"], e=AFFINE["e"]):
    """Point -> pixel: the smallest positive real root of bw(r) = theta (np.roots)."""
    chi = math.hypot(p[0], p[1])
    theta = math.atan2(chi, p[2])
    coeffs = [*reversed(bw), -theta]  # bw_n r^n + ... + bw_1 r - theta
    roots = [z.real for z in np.roots(coeffs) if abs(z.imag) < 1e-9 and z.real > 0]
    r = min(roots)
    x, y = r * p[0] / chi, r * p[1] / chi
    return np.array([c * x + d * y + CX, e * x + y + CY])


def _pixels(n, seed=0):
    rng = np.random.default_rng(seed)
    return np.stack([rng.uniform(-0.5, W - 0.5, n), rng.uniform(-0.5, H - 0.5, n)], -1)


def test_unproject_and_project_match_the_formulas(jit_project, jit_unproject):
    cam = _camera()
    uv = _pixels(N)
    rays, valid = jit_unproject(cam, jnp.asarray(uv))
    ok = np.asarray(valid)
    assert ok.mean() > 0.8  # the corners lie beyond 100 degrees
    ref = np.stack([ref_unproject(u, v) for u, v in uv[ok]])
    np.testing.assert_allclose(np.asarray(rays)[ok], ref, rtol=0, atol=tol.MODEL_RAY_F64)
    pts = ref * np.random.default_rng(1).uniform(0.5, 20.0, (len(ref), 1))
    got, pvalid = jit_project(cam, jnp.asarray(np.pad(pts, ((0, N - len(pts)), (0, 0)), constant_values=1.0)))
    assert bool(jnp.all(pvalid))
    expected = np.stack([ref_project(p) for p in pts])
    np.testing.assert_allclose(np.asarray(got)[: len(pts)], expected, rtol=0, atol=tol.MODEL_PX_F64)
    np.testing.assert_allclose(expected, uv[ok], rtol=0, atol=tol.MODEL_PX_F64)


@pytest.mark.parametrize("dtype,atol", [(jnp.float64, tol.ROUNDTRIP_PX_F64), (jnp.float32, tol.MODEL_PX_F32)])
def test_pixel_ray_pixel_over_the_image(dtype, atol, jit_project, jit_unproject):
    cam = _camera(dtype)
    u, v = np.meshgrid(np.linspace(-0.5, W - 0.5, 16), np.linspace(-0.5, H - 0.5, N // 16))
    grid = jnp.asarray(np.stack([u, v], -1).reshape(-1, 2), dtype)
    rays, ok = jit_unproject(cam, grid)
    assert rays.dtype == dtype
    back, ok2 = jit_project(cam, rays * 3)
    okv = np.asarray(ok & ok2)
    assert okv.mean() > 0.8 and (np.asarray(ok) == okv).all()
    np.testing.assert_allclose(np.asarray(back)[okv], np.asarray(grid)[okv], rtol=0, atol=atol)


def test_the_forward_polynomial_is_only_a_start():
    exact = _camera()
    crude = jc.FTheta(CX, CY, np.asarray(BW), [400.0], max_angle=MAX_ANGLE, **AFFINE, width=W, height=H)
    none = jc.FTheta(CX, CY, np.asarray(BW), max_angle=MAX_ANGLE, **AFFINE, width=W, height=H)
    pts = jnp.asarray(np.array([[0.3, -0.2, 1.0], [1.0, 0.5, 0.1], [0.0, 0.0, 1.0]]))
    for cam in (crude, none):
        np.testing.assert_allclose(np.asarray(cam.project(pts)[0]), np.asarray(exact.project(pts)[0]),
                                   rtol=0, atol=tol.MODEL_PX_F64)


def test_domain_edges_max_angle_and_stationary_point(jit_project, jit_unproject):
    cam = _camera()
    tm = float(cam.theta_max())
    assert tm == pytest.approx(MAX_ANGLE)
    near = np.array([tm - 1e-7, tm - 1e-12, tm + 1e-9, tm + 1e-6])
    pts = np.tile(np.stack([np.sin(near), np.zeros(4), np.cos(near)], -1), (N // 4, 1))
    uv, valid = jit_project(cam, jnp.asarray(pts))
    assert np.asarray(valid)[:4].tolist() == [True, True, False, False]
    rays, ok = jit_unproject(cam, uv)
    okv = np.asarray(ok & valid)
    assert okv[:2].all()
    np.testing.assert_allclose(np.asarray(rays)[okv], pts[okv], rtol=0, atol=1e-9)
    # A backward polynomial that turns back inside the diagonal: the domain ends there.
    bw = (2.0e-3, 0.0, -2.0e-10)
    folding = _camera(bw=bw, max_angle=math.pi)
    r = np.linspace(0, math.hypot(W, H), 400001)
    theta = np.polynomial.polynomial.polyval(r, (0.0, *bw))
    first = r[int(np.argmax(np.diff(theta) <= 0))]
    assert float(folding.rho_max()) == pytest.approx(first - 1e-3 * math.hypot(W, H) / math.pi, abs=0.02)
    tmax = float(folding.theta_max())
    assert tmax == pytest.approx(np.polynomial.polynomial.polyval(float(folding.rho_max()), (0.0, *bw)))
    beyond = np.tile([[math.sin(tmax + 1e-4), 0.0, math.cos(tmax + 1e-4)]], (N, 1))
    _, bad = jit_project(folding, jnp.asarray(beyond))
    assert not np.asarray(bad).any()


def test_special_inputs_are_invalid_not_nan(jit_project, jit_unproject):
    cam = _camera()
    pts = np.zeros((N, 3))
    pts[1] = [0, 0, -1.0]
    pts[2] = [np.inf, 0, 1]
    pts[3] = [0, 0, 1.0]
    uv, valid = jit_project(cam, jnp.asarray(pts))
    assert np.asarray(valid)[:4].tolist() == [False, False, False, True]
    np.testing.assert_allclose(np.asarray(uv)[3], [CX, CY], atol=1e-12)
    assert np.isfinite(np.asarray(uv)).all()
    rays, ok = jit_unproject(cam, jnp.asarray(np.full((N, 2), np.nan)))
    assert not np.asarray(ok).any() and np.isfinite(np.asarray(rays)).all()
    no_lens = jc.FTheta(CX, CY, np.asarray([-1e-3]), width=W, height=H)
    assert not bool(no_lens.unproject(jnp.asarray([CX + 10.0, CY]))[1])


def test_gradients_finite_and_match_finite_differences():
    cam = _camera()
    for fn in (lambda c: c.project(jnp.asarray([0.0, 0.0, 2.0]))[0],
               lambda c: c.unproject(jnp.asarray([CX, CY]))[0]):
        g = jax.jacfwd(fn)(cam)
        assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree_util.tree_leaves(g))

    def f(x):  # (bw1 * 1e3, bw2 * 1e7, cx, c, X, Y, Z) -> pixel
        bw = jnp.asarray(BW).at[0].set(x[0] * 1e-3).at[1].set(x[1] * 1e-7)
        c = jc.FTheta(x[2], CY, bw, max_angle=MAX_ANGLE, c=x[3], d=AFFINE["d"], e=AFFINE["e"], width=W, height=H)
        return c.project(x[4:])[0]

    x0 = np.array([BW[0] * 1e3, BW[1] * 1e7, CX, AFFINE["c"], 0.7, -0.4, 0.5])
    fwd = np.asarray(jax.jacfwd(f)(jnp.asarray(x0)))
    rev = np.asarray(jax.jacrev(f)(jnp.asarray(x0)))
    np.testing.assert_allclose(fwd, rev, rtol=0, atol=tol.JAC_FWD_REV * np.abs(fwd).max())
    num = central_difference_jacobian(lambda x: f(jnp.asarray(x)), x0, eps=1e-6)
    np.testing.assert_allclose(fwd, num, rtol=tol.JAC_FINITE_DIFF_REL, atol=1e-6 * np.abs(fwd).max())


def test_eager_jit_vmap_agree():
    cam = _camera()
    pts = jnp.asarray(np.array([[0.3, -0.2, 1.0], [1.0, 0.5, 0.2]]))
    outs = three_ways(lambda c, p: c.project(p), cam, pts)
    for uv, _ in outs[1:]:
        np.testing.assert_allclose(uv, outs[0][0], rtol=0, atol=tol.MODEL_PX_F64)


def test_calibration_json_round_trip():
    cam = _camera()
    d = json.loads(json.dumps(intrinsics_to_dict(cam)))
    assert d["model"] == "ftheta" and d["bw1"] == BW[0] and d["max_angle"] == MAX_ANGLE
    back = intrinsics_from_dict(d)
    for a, b in zip(jax.tree_util.tree_leaves(cam), jax.tree_util.tree_leaves(back), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    for key, value in (("bw1", -1e-3), ("max_angle", 4.0)):
        with pytest.raises(ValueError, match=rf"calib.json: field 'intrinsic\.{key}'"):
            intrinsics_from_dict(dict(d, **{key: value}), source="calib.json")


def test_convert_a_fisheye_to_ftheta():
    source = jc.KannalaBrandt(500.0, 501.0, 959.2, 640.6, (0.02, -0.004, 0.0005, -0.00003), width=W, height=H)
    result = convert_camera(source, "ftheta", fov="image", n_theta=48, n_phi=8)
    assert bool(result.converged) and int(result.num_target_invalid) == 0
    assert float(result.max_px) < 0.5 and float(result.rms_px) < 0.1
    assert np.abs(np.asarray(result.camera.fw)).max() > 0  # the forward polynomial is refilled
