"""Every radial model at the edges of its domain: lenses whose domain ends before pi (the Newton
solve must not cycle near the stationary point), points next to the back axis (float64 exactness),
and coordinates whose squares overflow (masked, finite, never a wrong pixel marked valid)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish as jf
from tests import tolerances as tol
from tests.helpers import three_ways

# Lenses whose polynomial has a stationary point below pi and an inflection before it: Newton
# from the fused guess cycled on a band below theta_max (150-167 deg) before the bisection retry.
STATIONARY = {
    "woodscape": lambda dtype: jf.WoodScapeFisheye((340.0, 33.568, 22.838, -12.615), width=1280, height=966, dtype=dtype),
    "kannala_brandt": lambda dtype: jf.KannalaBrandt(330.0, 331.0, 640.2, 483.1, (0.02, -0.003, 0.001, -0.0001),
                                                      width=1280, height=966, dtype=dtype),
    "fisheye624": lambda dtype: jf.Fisheye624(330.0, 331.0, 640.2, 483.1, (0.02, -0.003, 0.001, -0.0001, 0.0, 0.0),
                                              width=1280, height=966, dtype=dtype),
    "opencv": lambda dtype: jf.OpenCVPinhole(500.0, 501.0, 640.2, 483.1, (-0.3, 0.02, 0.0, 0.0), width=1280, height=966,
                                             dtype=dtype),
    "mei": lambda dtype: jf.MeiCamera(500.0, 501.0, 640.2, 483.1, 0.9, (-0.35, 0.02, 0.0, 0.0), width=1280, height=966,
                                      dtype=dtype),
}


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
@pytest.mark.parametrize("model", sorted(STATIONARY))
def test_every_pixel_of_the_domain_unprojects_up_to_a_stationary_point(model, dtype):
    cam = STATIONARY[model](dtype)
    tmax = float(cam.theta_max())
    assert tmax < np.pi - 0.2  # the case under test
    theta = np.linspace(0.0, tmax, 2001)
    p = jnp.asarray(np.stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)], -1), dtype)
    uv, pvalid = cam.project(p)
    assert bool(jnp.all(pvalid))

    def roundtrip(c, x):
        rays, valid = c.unproject(x)
        return c.project(rays)[0], valid

    for back, valid in three_ways(roundtrip, cam, uv):
        assert valid.all(), f"{(~valid).sum()} pixels of the domain have no ray"
        err = np.abs(back - np.asarray(uv)).max()
        assert err < (tol.MODEL_PX_F32 if dtype == jnp.float32 else 1e-6), err  # 1e-6: rho' ~ 0 at theta_max


def _long_double_back_axis_u(cam, x: np.ndarray) -> np.ndarray:
    """u of (x, 0, -1) from the textbook formula in long double (theta = pi - atan(x))."""
    theta = np.longdouble(np.pi) - np.arctan(x.astype(np.longdouble))
    if isinstance(cam, jf.WoodScapeFisheye):
        k = np.asarray(cam.k).astype(np.longdouble)
        rho = theta * (k[0] + theta * (k[1] + theta * (k[2] + theta * k[3])))
        return (rho + np.longdouble(np.asarray(cam.principal_point)[0])).astype(np.float64)
    k = np.asarray(cam.k).astype(np.longdouble)
    t2 = theta * theta
    td = theta * (1 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3]))))
    return (np.longdouble(float(cam.fx)) * td + np.longdouble(float(cam.cx))).astype(np.float64)


@pytest.mark.parametrize("model", ["woodscape", "kannala_brandt"])
def test_projection_next_to_the_back_axis_is_exact_in_float64(model):
    """sin of a rounded theta near pi lost every digit (50 px at 1e-14 rad); theta/chi does not."""
    cam = jf.default_rig()["FV"].camera if model == "woodscape" else \
        jf.KannalaBrandt(330.0, 330.0, 640.0, 483.0, (0.0, 0.0, 0.0, 0.0), width=1280, height=966, dtype=jnp.float64)
    x = 10.0 ** -np.arange(4.0, 15.0)
    p = jnp.asarray(np.stack([x, np.zeros_like(x), -np.ones_like(x)], -1), jnp.float64)
    for uv, valid in three_ways(lambda c, q: c.project(q), cam, p):
        assert valid.all()
        np.testing.assert_allclose(uv[:, 0], _long_double_back_axis_u(cam, x), rtol=0, atol=tol.PROJECT_PX_F64)
    exactly_behind = cam.project(jnp.asarray([0.0, 0.0, -1.0], jnp.float64))
    assert not bool(exactly_behind[1]) and bool(jnp.all(jnp.isfinite(exactly_behind[0])))  # no azimuth


def _models(dtype):
    return {
        "woodscape": jf.default_rig()["FV"].camera.astype(dtype),
        "kannala_brandt": jf.KannalaBrandt(330.0, 331.0, 640.0, 483.0, (0.01, 0.0, 0.0, 0.0), width=1280, height=966, dtype=dtype),
        "ucm": jf.UnifiedCamera(300.0, 300.0, 640.0, 483.0, 0.6, width=1280, height=966, dtype=dtype),
        "eucm": jf.ExtendedUnifiedCamera(300.0, 300.0, 640.0, 483.0, 0.6, 1.1, width=1280, height=966, dtype=dtype),
        "double_sphere": jf.DoubleSphere(300.0, 300.0, 640.0, 483.0, -0.2, 0.6, width=1280, height=966, dtype=dtype),
        "pinhole": jf.Pinhole(500.0, 500.0, 639.5, 482.5, width=1280, height=966, dtype=dtype),
        "mei": jf.MeiCamera(600.0, 600.0, 640.0, 483.0, 1.1, (-0.2, 0.05, 1e-3, 0.0), width=1280, height=966, dtype=dtype),
        "opencv": jf.OpenCVPinhole(500.0, 500.0, 639.5, 482.5, (-0.2, 0.05, 1e-3, 0.0), width=1280, height=966, dtype=dtype),
        "fov": jf.FieldOfView(300.0, 300.0, 640.0, 483.0, 1.5, width=1280, height=966, dtype=dtype),
        "fisheye624": jf.Fisheye624(330.0, 331.0, 640.0, 483.0, (0.01, 0.0, 0.0, 0.0, 0.0, 0.0), (1e-3, 0.0),
                                    width=1280, height=966, dtype=dtype),
    }


@pytest.mark.parametrize("model", sorted(_models(jnp.float32)))
def test_overflowing_coordinates_are_masked_not_wrong(model):
    """float32 squares overflow beyond ~1.8e19: such points and pixels are invalid with finite
    placeholders and finite masked gradients, or exact (they projected to the principal point,
    marked valid)."""
    cam = _models(jnp.float32)[model]
    ok = jnp.asarray([[0.3, 0.2, 1.0]], jnp.float32)
    far = jnp.asarray([[0.3, 0.2, 1.0], [1e20 * 0.3, 1e20 * 0.2, 1e20]], jnp.float32)
    huge_px = jnp.asarray([[700.0, 500.0], [1e22, 1e22]], jnp.float32)
    uv, valid = cam.project(far)
    assert bool(valid[0]) and bool(jnp.all(jnp.isfinite(uv)))
    expected = np.asarray(cam.project(ok)[0][0])
    for i in np.flatnonzero(np.asarray(valid)):  # the pinhole divides without squaring: still exact
        np.testing.assert_allclose(np.asarray(uv[i]), expected, rtol=1e-6)
    rays, valid = cam.unproject(huge_px)
    assert valid.tolist() == [True, False] and bool(jnp.all(jnp.isfinite(rays)))

    def masked(c, x):
        r, v = c.unproject(x)
        return jnp.sum(jnp.where(v[:, None], r, 0.0))

    grads = jax.grad(masked)(cam, huge_px)  # the camera's array leaves
    assert all(bool(jnp.all(jnp.isfinite(g))) for g in jax.tree_util.tree_leaves(grads))


def test_the_fallback_runs_for_a_batch_of_cameras_and_nested_batches():
    """Under vmap the retry's predicate covers the whole batch (`all_of_batch`): one lens that needs
    the bisection gets it, next to one that does not, in one and two levels of vmap, with gradients."""
    stationary = STATIONARY["woodscape"](jnp.float64)
    plain = jf.default_rig()["FV"].camera
    plain = jf.WoodScapeFisheye(plain.k, width=1280, height=966, dtype=jnp.float64)
    cams = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), stationary, plain)
    theta = np.linspace(0.0, float(stationary.theta_max()), 501)
    p = jnp.asarray(np.stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)], -1))
    uv = jax.vmap(lambda c: c.project(p)[0])(cams)
    rays, valid = jax.jit(jax.vmap(lambda c, x: c.unproject(x)))(cams, uv)
    assert bool(jnp.all(valid))
    np.testing.assert_allclose(np.asarray(jax.vmap(lambda c, r: c.project(r)[0])(cams, rays)), np.asarray(uv), atol=1e-6)
    frames = jnp.stack([uv, uv])  # (frames, cameras, points, 2): vmap over frames of vmap over cameras
    nested = jax.vmap(jax.vmap(lambda c, x: c.unproject(x)[1]), in_axes=(None, 0))(cams, frames)
    assert bool(jnp.all(nested))
    grad = jax.grad(lambda c: jnp.sum(jax.vmap(lambda cc, x: cc.unproject(x)[0][:, 2])(c, uv)))(cams)
    assert all(bool(jnp.all(jnp.isfinite(g))) for g in jax.tree_util.tree_leaves(grad))
