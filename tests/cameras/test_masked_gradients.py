"""Masked points and pixels send no NaN or infinity back: points a hair off the image plane (or
off a unified model's rim), and CARLA lenses' rim pixels, in float32 and float64."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish as jf

W, H = 64, 48

CAMERAS = {
    "pinhole": lambda: jf.Pinhole(20.0, 20.0, 31.5, 23.5, width=W, height=H),
    "opencv": lambda: jf.OpenCVPinhole(20.0, 20.0, 31.5, 23.5, (0.1, 0.01, 0.001, 0.001), width=W, height=H),
    "unified_alpha_0": lambda: jf.UnifiedCamera(20.0, 20.0, 31.5, 23.5, 0.0, width=W, height=H),
    "extended_unified": lambda: jf.ExtendedUnifiedCamera(20.0, 20.0, 31.5, 23.5, 0.0, 1.2, width=W, height=H),
    "mei_xi_0": lambda: jf.MeiCamera(40.0, 40.0, 31.5, 23.5, 0.0, (0.1, 0.01, 0.001, 0.001), width=W, height=H),
    "double_sphere": lambda: jf.DoubleSphere(20.0, 20.0, 31.5, 23.5, 0.0, 0.0, width=W, height=H),
    "cube_rig": lambda: jf.CubeRig(16),
}
TINY = {jnp.float32: 1e-25, jnp.float64: 1e-170}


def _finite_tree(tree) -> bool:
    return all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree_util.tree_leaves(eqx.filter(tree, eqx.is_inexact_array)))


def _masked_pixels(cam, p):
    uv, ok = cam.project(p)
    ok = ok & cam.contains(uv)
    return jnp.sum(jnp.where(ok[..., None], uv, 0.0))


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64], ids=["float32", "float64"])
@pytest.mark.parametrize("name", sorted(CAMERAS))
def test_points_grazing_the_image_plane_have_finite_gradients(name, dtype):
    t = TINY[dtype]
    cam = CAMERAS[name]().astype(dtype)
    edges = [[1.0, 0.0, t], [0.0, 1.0, t], [0.0, t, -1.0], [t, 0.0, -1.0]]
    points = jnp.asarray([[0.1, 0.2, 1.0], *edges], dtype)
    uv, ok = cam.project(points)
    assert bool(ok[0])
    if name != "cube_rig":  # a cube's side faces see the grazing points; a single lens has no image of them
        assert not np.asarray(ok[1:3]).any()
    assert _finite_tree(eqx.filter_grad(_masked_pixels)(cam, points)), "camera gradient"
    grad = np.asarray(jax.grad(_masked_pixels, argnums=1)(cam, points))
    assert np.isfinite(grad).all(), grad


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
