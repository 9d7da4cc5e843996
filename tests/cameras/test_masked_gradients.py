"""Masked points and pixels send no NaN or infinity back: points a hair off the image plane (or
off a unified model's rim), and CARLA lenses' rim pixels, in float32 and float64. Every model is
probed: a point whose pixel or its derivative would overflow is invalid, and a valid point or pixel
has finite derivatives (with respect to the point, the pixel and the camera)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish as jf
from jaxfish.cameras import CARLA_CAMERA_MODELS
from jaxfish.reprojection import CubeRig

W, H = 64, 48

def _finite_tree(tree) -> bool:
    return all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree_util.tree_leaves(eqx.filter(tree, eqx.is_inexact_array)))


def _masked_pixels(cam, p):
    uv, ok = cam.project(p)
    ok = ok & cam.contains(uv)
    return jnp.sum(jnp.where(ok[..., None], uv, 0.0))


def _masked_rays(cam, uv):
    rays, ok = cam.unproject(uv)
    return jnp.sum(jnp.where(ok[..., None], rays, 0.0))


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64], ids=["float32", "float64"])
def test_the_equisolid_rim_pixel_is_invalid_with_a_finite_gradient(dtype):
    cam = jf.CarlaWideAngle("equisolid", fov=360.0, width=W, height=48, dtype=dtype)
    uv = jnp.asarray([[32.0, 0.0], [32.0, 1.0]], dtype)  # the ray straight back (|uv| = 2), and one inside
    rays, ok = cam.unproject(uv)
    assert not bool(ok[0]) and bool(ok[1])
    assert np.isfinite(np.asarray(jax.grad(_masked_rays, argnums=1)(cam, uv))).all()
    _, back = cam.project(jnp.asarray([0.0, 0.0, -1.0], dtype))
    assert not bool(back)  # the domain ends at pi, exclusive, in both directions


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64], ids=["float32", "float64"])
def test_orthographic_rim_pixels_have_finite_gradients(dtype):
    cam = jf.CarlaWideAngle("orthographic", fov=170.0, width=W, height=H, dtype=dtype)
    t = float(cam.theta_max())
    points = jnp.asarray([[np.sin(t), 0.0, np.cos(t)], [np.sin(0.5), 0.0, np.cos(0.5)]], dtype)
    uv, _ = cam.project(points)
    f = float(cam.focal_length())
    rim = jnp.asarray([[W // 2 + f, H // 2]], dtype)  # |uv| = 1: 90 degrees, beyond the domain
    pixels = jnp.concatenate([uv, rim])
    rays, ok = cam.unproject(pixels)
    assert bool(ok[1]) and not bool(ok[2])
    assert np.isfinite(np.asarray(jax.grad(_masked_rays, argnums=1)(cam, pixels))).all()
    assert _finite_tree(eqx.filter_grad(_masked_rays)(cam, pixels))


EVERY_MODEL = {
    "pinhole": lambda: jf.Pinhole(20.0, 20.0, 31.5, 23.5, width=W, height=H),
    "opencv": lambda: jf.OpenCVPinhole(30.0, 30.0, 31.5, 23.5, (-0.2, 0.05, 1e-3, -1e-3, 0.0, 0.01, 0.0, 0.0, 1e-3, 0.0,
                                                             -1e-3, 0.0), width=W, height=H),
    "ucm_alpha_0": lambda: jf.UnifiedCamera(20.0, 20.0, 31.5, 23.5, 0.0, width=W, height=H),
    "ucm": lambda: jf.UnifiedCamera(20.0, 20.0, 31.5, 23.5, 0.6, width=W, height=H),
    "eucm": lambda: jf.ExtendedUnifiedCamera(20.0, 20.0, 31.5, 23.5, 0.6, 1.1, width=W, height=H),
    "eucm_alpha_1": lambda: jf.ExtendedUnifiedCamera(20.0, 20.0, 31.5, 23.5, 1.0, 0.5, width=W, height=H),
    "double_sphere": lambda: jf.DoubleSphere(20.0, 20.0, 31.5, 23.5, -0.2, 0.6, width=W, height=H),
    "double_sphere_0": lambda: jf.DoubleSphere(20.0, 20.0, 31.5, 23.5, 0.0, 0.0, width=W, height=H),
    "mei": lambda: jf.MeiCamera(40.0, 40.0, 31.5, 23.5, 1.2, (-0.2, 0.05, 1e-3, -1e-3), width=W, height=H),
    "mei_xi_0": lambda: jf.MeiCamera(40.0, 40.0, 31.5, 23.5, 0.0, (0.1, 0.01, 0.001, 0.001), width=W, height=H),
    "fov": lambda: jf.FieldOfView(20.0, 20.0, 31.5, 23.5, 1.5, width=W, height=H),
    "fov_pinhole": lambda: jf.FieldOfView(20.0, 20.0, 31.5, 23.5, 0.0, width=W, height=H),
    "fov_near_pinhole": lambda: jf.FieldOfView(20.0, 20.0, 31.5, 23.5, 1e-20, width=W, height=H),
    "kannala_brandt": lambda: jf.KannalaBrandt(20.0, 20.0, 31.5, 23.5, (0.02, -0.003, 0.001, -0.0001), width=W, height=H),
    "woodscape": lambda: jf.WoodScapeFisheye((30.0, 1.0, 0.5, -0.1), width=W, height=H),
    "fisheye624": lambda: jf.Fisheye624(20.0, 20.0, 31.5, 23.5, (0.02, -0.003, 0.001, -1e-4, 0.0, 0.0), (1e-3, -1e-3),
                                        (1e-3, 0.0, -1e-3, 0.0), width=W, height=H),
    "ftheta": lambda: jf.FTheta(31.5, 23.5, np.asarray((1.9e-2, 1.0e-5, -2.0e-7, 1.0e-9)), max_angle=np.radians(100.0),
                                c=1.0007, d=0.0004, e=-0.0003, width=W, height=H),
    "ocamcalib": lambda: jf.OCamCalib(np.asarray((-3.3797e1, 0.0, 1.1107e-2, -7.3917e-5, 7.3525e-7)), xc=23.5, yc=31.5,
                                      c=1.0004, d=0.0021, e=-0.0013, width=W, height=H),
    "equirectangular": lambda: jf.Equirectangular(width=W, height=H),
    "cylindrical": lambda: jf.Cylindrical(width=W, height=H),
    "orthographic": lambda: jf.Orthographic(0.1, width=W, height=H),
    "cube_rig": lambda: CubeRig(16),
    **{f"carla_{m}": (lambda m=m: jf.CarlaWideAngle(m, {"perspective": 90.0, "orthographic": 170.0,
                                                        "kannala-brandt": 180.0}.get(m, 360.0), width=W, height=H))
       for m in CARLA_CAMERA_MODELS},
}
# Heights above (or below) the image plane, and distances from the back axis, down to where the
# squares underflow; per dtype.
GRAZING = {jnp.float32: (1e-8, 1e-13, 1e-16, 1e-20, 1e-25, 1e-30),
           jnp.float64: (1e-17, 1e-100, 1e-156, 1e-170, 1e-200, 1e-300)}


def _grazing_points(dtype) -> np.ndarray:
    rows = [[0.1, 0.2, 1.0]]
    for t in GRAZING[dtype]:
        rows += [[1.0, 0.0, t], [0.0, 1.0, t], [1.0, 1.0, t], [1.0, 0.0, -t], [t, 0.0, -1.0], [0.0, t, -1.0],
                 [t, t, -1.0], [t, 0.0, 1.0], [0.0, 0.0, t], [3e5, -2e5, t * 1e5]]
    rows += [[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]
    return np.asarray(rows)


def _pixel_losses(cam, p):
    """Pixels masked by validity alone, and by validity and the image bounds."""
    uv, ok = cam.project(p)
    seen = ok & cam.contains(uv)
    return jnp.sum(jnp.where(ok[..., None], uv, 0.0)) + jnp.sum(jnp.where(seen[..., None], uv, 0.0))


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64], ids=["float32", "float64"])
@pytest.mark.parametrize("name", sorted(EVERY_MODEL))
def test_every_model_sends_finite_gradients_from_grazing_points(name, dtype):
    cam = EVERY_MODEL[name]().astype(dtype)
    points = jnp.asarray(_grazing_points(dtype), dtype)
    uv, ok = cam.project(points)
    assert bool(ok[0]) and np.isfinite(np.asarray(uv)).all()
    cam_grad, point_grad = eqx.filter_grad(lambda args: _pixel_losses(*args))((cam, points))
    assert _finite_tree(cam_grad), "camera gradient"
    bad = ~np.isfinite(np.asarray(point_grad)).all(-1)
    assert not bad.any(), np.asarray(points)[bad]


@pytest.mark.parametrize("name", sorted(EVERY_MODEL))
def test_every_model_sends_finite_gradients_from_valid_and_masked_pixels(name):
    """In float32, where derivatives overflow first."""
    dtype = jnp.float32
    cam = EVERY_MODEL[name]().astype(dtype)
    u, v = np.meshgrid(np.linspace(-40.0, 104.0, 37), np.linspace(-40.0, 88.0, 33))
    extra = [[31.5, 23.5], [32.0, 24.0], [1e20, 3.0], [1e6, -1e6]]
    pixels = jnp.asarray(np.concatenate([np.stack([u.ravel(), v.ravel()], -1), extra]), dtype)
    rays, ok = cam.unproject(pixels)
    assert np.isfinite(np.asarray(rays)).all() and bool(ok.any())
    cam_grad, pixel_grad = eqx.filter_grad(lambda args: _masked_rays(*args))((cam, pixels))
    assert _finite_tree(cam_grad), "camera gradient"
    bad = ~np.isfinite(np.asarray(pixel_grad)).all(-1)
    assert not bad.any(), np.asarray(pixels)[bad]


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64], ids=["float32", "float64"])
def test_a_near_pinhole_fov_lens_has_no_image_of_grazing_points(dtype):
    """ω = 0 (or below ~eps) is the pinhole: a point within eps of the image plane is invalid,
    as for `Pinhole`, and one clear of it keeps its pixel."""
    eps = float(jnp.finfo(dtype).eps)
    points = jnp.asarray([[1.0, 0.0, eps / 2], [1.0, 0.0, 1e-13 if dtype == jnp.float32 else 1e-156],
                          [1.0, 0.0, 4 * eps], [0.1, 0.2, 1.0]], dtype)
    for w in (0.0, 1e-20):
        cam = jf.FieldOfView(20.0, 20.0, 31.5, 23.5, w, width=W, height=H, dtype=dtype)
        pin = jf.Pinhole(20.0, 20.0, 31.5, 23.5, width=W, height=H, dtype=dtype)
        uv, ok = cam.project(points)
        ref, ref_ok = pin.project(points)
        assert np.asarray(ok).tolist() == [False, False, True, True] == np.asarray(ref_ok).tolist()
        if w == 0.0:
            np.testing.assert_allclose(np.asarray(uv)[2:], np.asarray(ref)[2:], rtol=1e-6 if dtype == jnp.float32 else 1e-12)
        assert np.isfinite(np.asarray(jax.grad(_masked_pixels, argnums=1)(cam, points))).all()
        assert _finite_tree(eqx.filter_grad(_masked_pixels)(cam, points))


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64], ids=["float32", "float64"])
@pytest.mark.parametrize("model,fov", [("orthographic", 170.0), ("orthographic", 180.0), ("equisolid", 360.0)])
def test_a_valid_point_near_the_carla_rim_has_a_pixel_with_a_ray(model, fov, dtype):
    """Up to ``theta_max``, a point `project` marks valid lands on a pixel that `unproject` gives a
    ray (the rim ``|uv| = 1`` or ``2`` is excluded from both), eager, jitted and vmapped, and the ray
    has a finite gradient."""
    cam = jf.CarlaWideAngle(model, fov, width=W, height=H, dtype=dtype)
    top = float(cam.theta_max())
    theta = np.concatenate([top - np.logspace(-10, -2, 400), [top]])
    points = jnp.asarray(np.stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)], -1), dtype)
    for project, unproject in ((cam.project, cam.unproject), (jax.jit(jax.vmap(cam.project)), jax.vmap(cam.unproject))):
        uv, ok = project(points)
        _, back = unproject(uv)
        assert bool(ok.any()) and not np.asarray(ok & ~back).any(), np.asarray(theta)[np.asarray(ok & ~back)]
    uv, ok = cam.project(points)
    assert np.isfinite(np.asarray(jax.grad(_masked_rays, argnums=1)(cam, uv))).all()
