"""Every camera model on hostile inputs: non-finite, huge and tiny points and pixels, degenerate
parameters. Invalid means masked: values stay finite, non-finite inputs are invalid, and no NaN
reaches the gradients with respect to the inputs or the camera parameters (one bad point must not
poison a calibration's gradient). Huge and tiny points project exactly like their direction."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish as jf
from jaxfish.refit import Correspondences, reprojection_residuals
from jaxfish.reprojection import CubeRig
from tests import tolerances as tol
from tests.helpers import three_ways

W, H = 64, 48
MODELS = {
    "woodscape": lambda: jf.WoodScapeFisheye((30.0, 1.0, 0.5, -0.1), width=W, height=H),
    "pinhole": lambda: jf.Pinhole.from_fov(W, H, 90.0),
    "kannala_brandt": lambda: jf.KannalaBrandt(20.0, 20.0, 31.5, 23.5, (0.02, -0.003, 0.001, -0.0001), width=W, height=H),
    "ucm": lambda: jf.UnifiedCamera(20.0, 20.0, 31.5, 23.5, 0.6, width=W, height=H),
    "eucm": lambda: jf.ExtendedUnifiedCamera(20.0, 20.0, 31.5, 23.5, 0.6, 1.1, width=W, height=H),
    "double_sphere": lambda: jf.DoubleSphere(20.0, 20.0, 31.5, 23.5, -0.2, 0.6, width=W, height=H),
    "mei": lambda: jf.MeiCamera(40.0, 40.0, 31.5, 23.5, 1.2, (-0.2, 0.05, 1e-3, -1e-3), width=W, height=H),
    "opencv": lambda: jf.OpenCVPinhole(30.0, 30.0, 31.5, 23.5, (-0.2, 0.05, 1e-3, -1e-3, 0.0, 0.01, 0.0, 0.0, 1e-3, 0.0,
                                                             -1e-3, 0.0), width=W, height=H),
    "fov": lambda: jf.FieldOfView(20.0, 20.0, 31.5, 23.5, 1.5, width=W, height=H),
    "fisheye624": lambda: jf.Fisheye624(20.0, 20.0, 31.5, 23.5, (0.02, -0.003, 0.001, -1e-4, 0.0, 0.0), (1e-3, -1e-3),
                                        (1e-3, 0.0, -1e-3, 0.0), width=W, height=H),
    "equirectangular": lambda: jf.Equirectangular(width=W, height=H),
    "cylindrical": lambda: jf.Cylindrical(width=W, height=H),
    "orthographic": lambda: jf.Orthographic(0.1, width=W, height=H),
    "cube": lambda: CubeRig(16),
}
CENTRAL = sorted(set(MODELS) - {"orthographic"})

# Rows: two ordinary points, then NaN, +inf, -inf rows (invalid), then huge and tiny copies of the
# ordinary directions (float32 squares overflow / underflow; same pixel as the direction).
DIRECTIONS = np.array([[0.1, 0.2, 1.0], [0.3, -0.2, 0.8]])
HOSTILE = np.concatenate([DIRECTIONS, [[np.nan, 0.0, 1.0], [np.inf, 0.0, 1.0], [0.0, -np.inf, 1.0]],
                          DIRECTIONS * 2.0**80, DIRECTIONS * 2.0**-80])  # ~1e24, ~1e-24: exact copies
NONFINITE = slice(2, 5)
BAD_PIXELS = np.array([[20.0, 30.0], [np.nan, 3.0], [np.inf, 3.0], [3.0, -np.inf], [1e20, 3.0], [3.0, -1e30]])


def _masked_sum(values, valid):
    return jnp.sum(jnp.where(valid[..., None], values, 0.0))


def _finite_tree(tree) -> bool:
    return all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree_util.tree_leaves(eqx.filter(tree, eqx.is_inexact_array)))


@pytest.mark.parametrize("model", sorted(MODELS))
def test_hostile_points_are_masked_finite_and_the_same_eager_jitted_vmapped(model):
    cam = jax.tree_util.tree_map(lambda x: x.astype(jnp.float32) if eqx.is_inexact_array(x) else x, MODELS[model]())
    pts = jnp.asarray(HOSTILE, jnp.float32)
    eager, jitted, batched = three_ways(lambda c, p: c.project(p), cam, pts)
    for uv, valid in (eager, jitted, batched):
        assert np.isfinite(uv).all(), uv
        assert not valid[NONFINITE].any()
        np.testing.assert_allclose(uv, eager[0], rtol=tol.EAGER_JIT_REL_F32, atol=tol.EAGER_JIT_PX_F32)
        np.testing.assert_array_equal(valid, eager[1])
    if model in CENTRAL:  # huge and tiny points: exactly the pixel and validity of their direction
        n = len(DIRECTIONS)
        for block in (slice(5, 5 + n), slice(5 + n, 5 + 2 * n)):
            np.testing.assert_array_equal(eager[0][block], eager[0][:n])
            np.testing.assert_array_equal(eager[1][block], eager[1][:n])
        assert eager[1][:n].all()


@pytest.mark.parametrize("model", sorted(MODELS))
def test_no_nan_reaches_the_gradients_from_masked_hostile_points(model):
    cam = jax.tree_util.tree_map(lambda x: x.astype(jnp.float32) if eqx.is_inexact_array(x) else x, MODELS[model]())
    pts = jnp.asarray(HOSTILE, jnp.float32)
    loss = lambda c, p: _masked_sum(*c.project(p))  # noqa: E731
    assert _finite_tree(eqx.filter_grad(loss)(cam, pts)), "camera gradient"
    grad_p = np.asarray(jax.grad(loss, argnums=1)(cam, pts))
    keep = np.ones(len(HOSTILE), bool)
    keep[NONFINITE] = False
    assert np.isfinite(grad_p[keep]).all(), grad_p


@pytest.mark.parametrize("model", sorted(MODELS))
def test_hostile_pixels_are_masked_finite_with_finite_gradients(model):
    cam = jax.tree_util.tree_map(lambda x: x.astype(jnp.float32) if eqx.is_inexact_array(x) else x, MODELS[model]())
    uv = jnp.asarray(BAD_PIXELS, jnp.float32)
    rays, valid = jax.jit(lambda c, x: c.unproject(x))(cam, uv)
    assert np.isfinite(np.asarray(rays)).all(), rays
    assert not np.asarray(valid)[1:4].any()
    loss = lambda c, x: _masked_sum(*c.unproject(x))  # noqa: E731
    assert _finite_tree(eqx.filter_grad(loss)(cam, uv)), "camera gradient"
    grad_uv = np.asarray(jax.grad(loss, argnums=1)(cam, uv))
    assert np.isfinite(grad_uv[[0, 4, 5]]).all(), grad_uv


@pytest.mark.parametrize("make", [
    lambda: jf.ExtendedUnifiedCamera(20.0, 20.0, 31.5, 23.5, 1.0, 1.0, width=W, height=H),
    lambda: jf.DoubleSphere(20.0, 20.0, 31.5, 23.5, 1.0, 1.0, width=W, height=H),
    lambda: jf.DoubleSphere(20.0, 20.0, 31.5, 23.5, -1.0, 0.5, width=W, height=H),
    lambda: jf.MeiCamera(20.0, 20.0, 31.5, 23.5, -1.0, width=W, height=H),
    lambda: jf.FieldOfView(20.0, 20.0, 31.5, 23.5, 0.0, width=W, height=H),
    lambda: jf.FieldOfView(20.0, 20.0, 31.5, 23.5, 3.5, width=W, height=H),
    lambda: jf.OpenCVPinhole(20.0, 20.0, 31.5, 23.5, (0.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0), width=W, height=H),
], ids=["eucm_alpha_1", "double_sphere_alpha_1", "double_sphere_xi_-1", "mei_xi_-1", "fov_w_0", "fov_w_beyond_pi",
        "opencv_rational_pole"])
def test_degenerate_documented_parameters_keep_values_and_gradients_finite(make):
    cam = make()
    uv = jnp.asarray([[31.5, 23.5], [51.5, 23.5], [231.5, 23.5], [1031.5, 23.5]])  # centre to far outside the rim
    loss = lambda c, x: _masked_sum(*c.unproject(x))  # noqa: E731
    rays, _ = cam.unproject(uv)
    assert np.isfinite(np.asarray(rays)).all()
    assert _finite_tree(eqx.filter_grad(loss)(cam, uv))
    assert np.isfinite(np.asarray(jax.grad(loss, argnums=1)(cam, uv))).all()
    assert np.isfinite(float(cam.theta_max()))


def test_woodscape_without_a_positive_k1_has_no_valid_ray():
    cam = jf.WoodScapeFisheye((0.0, 10.0, 0.0, 0.0), width=W, height=H)  # rho does not increase at 0
    assert not bool(cam.project(jnp.asarray([0.0, 0.0, 1.0]))[1])
    assert not bool(cam.unproject(jnp.asarray([40.0, 23.5]))[1])
    loss = lambda c, x: _masked_sum(*c.unproject(x))  # noqa: E731
    assert _finite_tree(eqx.filter_grad(loss)(cam, jnp.asarray([[40.0, 23.5], [31.5, 23.5]])))


def test_refit_residuals_have_a_finite_gradient_at_weight_zero():
    cam = MODELS["pinhole"]()
    corr = Correspondences(jnp.asarray([[0.1, 0.2, 1.0], [0.2, 0.1, 1.0]]), jnp.asarray([[40.0, 30.0], [20.0, 10.0]]),
                           weight=jnp.asarray([1.0, 0.0]))
    grad = jax.grad(lambda w: jnp.sum(reprojection_residuals(cam, Correspondences(corr.points, corr.pixels, weight=w))
                                      ** 2))(corr.weight)
    assert np.isfinite(np.asarray(grad)).all()
    r = np.asarray(reprojection_residuals(cam, corr))
    assert np.abs(r[0]).sum() > 0 and (r[1] == 0).all()  # weight 0: no residual


@pytest.mark.parametrize("name", list(MODELS))
@pytest.mark.parametrize("shape", [(0,), (3, 0)])
def test_empty_arrays_give_empty_results(name, shape):
    cam = MODELS[name]()
    rays, valid = cam.unproject(np.zeros(shape + (2,)))
    assert rays.shape == shape + (3,) and valid.shape == shape
    uv, valid = cam.project(np.zeros(shape + (3,)))
    assert uv.shape == shape + (2,) and valid.shape == shape


def test_image_sizes_above_the_bound_are_refused():
    big = jf.cameras.MAX_IMAGE_SIDE + 1
    makers = [lambda w: jf.WoodScapeFisheye((30.0, 1.0, 0.5, -0.1), width=w, height=H),
              lambda w: jf.Pinhole(20.0, 20.0, 31.5, 23.5, width=w, height=H),
              lambda w: jf.KannalaBrandt(20.0, 20.0, 31.5, 23.5, (0.02, -0.003, 0.001, -0.0001), width=w, height=H),
              lambda w: jf.UnifiedCamera(20.0, 20.0, 31.5, 23.5, 0.6, width=w, height=H),
              lambda w: jf.DoubleSphere(20.0, 20.0, 31.5, 23.5, -0.2, 0.6, width=w, height=H),
              lambda w: jf.MeiCamera(20.0, 20.0, 31.5, 23.5, 1.0, width=w, height=H),
              lambda w: jf.OpenCVPinhole(20.0, 20.0, 31.5, 23.5, width=w, height=H),
              lambda w: jf.FieldOfView(20.0, 20.0, 31.5, 23.5, 1.0, width=w, height=H),
              lambda w: jf.Fisheye624(20.0, 20.0, 31.5, 23.5, width=w, height=H),
              lambda w: jf.Equirectangular(width=w, height=H), lambda w: jf.Orthographic(0.1, width=w, height=H)]
    for make in makers:
        assert make(jf.cameras.MAX_IMAGE_SIDE).width == 65536
        with pytest.raises(ValueError, match=rf"{big}x{H} exceeds 65536 pixels per side"):
            make(big)
        with pytest.raises(ValueError, match="exceeds 65536"):
            make(10**12)
