"""FieldOfView (Devernay-Faugeras FOV, COLMAP FOV) against the paper's formulas and its laws."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish as jf
from tests import tolerances as tol
from tests.cameras import lens_laws

CAMERAS = {
    "wide": jf.FieldOfView(300.0, 302.0, 640.2, 481.7, 1.9, width=1280, height=966),
    "narrow": jf.FieldOfView(600.0, 601.0, 320.5, 240.2, 0.4, width=640, height=480),
    "negative_w": jf.FieldOfView(300.0, 302.0, 640.2, 481.7, -1.9, width=1280, height=966),
}


def _paper(cam, p):
    """Devernay & Faugeras (2001), eq. 13-14: r_d = atan(2 r_u tan(ω/2)) / ω on the pinhole plane
    (COLMAP's FOVCameraModel::Distortion without its Taylor branches), theta < 90 degrees."""
    w = float(cam.w)
    x, y = p[:, 0] / p[:, 2], p[:, 1] / p[:, 2]
    ru = np.hypot(x, y)
    rd = np.arctan(2 * ru * np.tan(w / 2)) / w
    return np.stack([float(cam.fx) * rd / ru * x + float(cam.cx), float(cam.fy) * rd / ru * y + float(cam.cy)], -1)


def _paper_inverse(cam, uv):
    """The paper's inverse, eq. 15: r_u = tan(r_d ω) / (2 tan(ω/2)); ray ∝ (x_u, y_u, 1)."""
    w = float(cam.w)
    m = (uv - [float(cam.cx), float(cam.cy)]) / [float(cam.fx), float(cam.fy)]
    rd = np.linalg.norm(m, axis=-1, keepdims=True)
    ru = np.tan(rd * w) / (2 * np.tan(w / 2))
    ray = np.concatenate([m * ru / rd, np.ones_like(rd)], -1)
    return ray / np.linalg.norm(ray, axis=-1, keepdims=True)


@pytest.mark.parametrize("name", list(CAMERAS))
def test_matches_the_paper_in_front_of_the_camera(name, jit_project, jit_unproject):
    cam = CAMERAS[name]
    rays = lens_laws.rays_up_to(math.radians(89.0), 1000, seed=3)
    rays[0] = [1e-9, 0.0, 1.0]  # next to the axis (the formula's 0/0 is the limit there)
    uv, valid = jit_project(cam, jnp.asarray(rays))
    assert bool(jnp.all(valid))
    np.testing.assert_allclose(np.asarray(uv), _paper(cam, rays), rtol=1e-13, atol=tol.MODEL_PX_F64)
    back, bvalid = jit_unproject(cam, uv)
    assert bool(jnp.all(bvalid))
    np.testing.assert_allclose(np.asarray(back)[1:], _paper_inverse(cam, np.asarray(uv)[1:]), atol=tol.MODEL_RAY_F64 * 10)


def test_continues_beyond_90_degrees_monotonically_and_is_even_in_w():
    cam, neg = CAMERAS["wide"], CAMERAS["negative_w"]
    assert float(cam.theta_max()) == pytest.approx(math.pi)
    theta = np.linspace(0.0, math.pi - 1e-3, 4001)
    rd = np.asarray(cam.r_d(jnp.asarray(theta)))
    assert np.all(np.diff(rd) > 0)
    np.testing.assert_allclose(rd, np.asarray(neg.r_d(jnp.asarray(theta))), rtol=1e-15)
    # Past 90 degrees: r_d = (pi - atan(2 tan(ω/2) tan(pi - theta))) / ω.
    behind = theta[theta > math.pi / 2 + 1e-6]
    w = float(cam.w)
    np.testing.assert_allclose(rd[theta > math.pi / 2 + 1e-6],
                               (math.pi - np.arctan(2 * math.tan(w / 2) * np.tan(math.pi - behind))) / w, rtol=1e-12)
    rays = jnp.asarray(np.stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)], -1))
    np.testing.assert_allclose(np.asarray(cam.project(rays)[0]), np.asarray(neg.project(rays)[0]), atol=1e-12)


@pytest.mark.parametrize("name", ["wide", "narrow"])
def test_pixel_ray_pixel_float64_and_float32(name):
    share = 0.5 if name == "wide" else 1.0  # the wide lens's image circle (r_d < pi / ω) lies inside the image
    lens_laws.check_pixel_ray_pixel(CAMERAS[name], atol=tol.ROUNDTRIP_PX_F64, min_valid=share)
    if name == "narrow":  # float32, eager / jit / vmap: one camera (each is a compile of the Newton solve)
        lens_laws.check_pixel_ray_pixel(CAMERAS[name], atol=tol.MODEL_PX_F32, min_valid=share, dtype=jnp.float32, three=True)


@pytest.mark.parametrize("name", list(CAMERAS))
def test_rays_to_the_edge_of_the_domain(name, jit_project, jit_unproject):
    lens_laws.check_ray_pixel_ray_to_the_edge(CAMERAS[name], jit_project, jit_unproject, theta_top=math.pi - 1e-6)
    cam = CAMERAS[name]
    _, behind = cam.project(jnp.asarray([[0.0, 0.0, -1.0], [0.0, 0.0, 0.0]]))
    assert not bool(jnp.any(behind))
    rim = np.pi / abs(float(cam.w)) * float(cam.fx)  # r_d reaches pi / ω at theta = pi: pixels beyond have no ray
    _, valid = cam.unproject(jnp.asarray([[float(cam.cx) + rim * 0.999, float(cam.cy)], [float(cam.cx) + rim * 1.001, float(cam.cy)]]))
    assert np.asarray(valid).tolist() == [True, False]


def test_w_zero_is_the_pinhole_with_finite_gradients():
    fov = jf.FieldOfView(500.0, 480.0, 321.5, 239.25, 0.0, width=640, height=480)
    pin = jf.Pinhole(500.0, 480.0, 321.5, 239.25, width=640, height=480)
    rays = jnp.asarray(lens_laws.rays_up_to(1.5, 200))
    np.testing.assert_allclose(np.asarray(fov.project(rays)[0]), np.asarray(pin.project(rays)[0]), atol=1e-9)
    assert float(fov.theta_max()) == pytest.approx(math.pi / 2)
    assert not bool(fov.project(jnp.asarray([1.0, 0.0, -0.1]))[1])
    # d/dω at 0 is 0 (the model is even in ω); second order matches the paper's expansion
    # r_d = r_u (1 + ω² (1/12 - r_u²/3)) + O(ω⁴).
    g = jax.grad(lambda w: fov.__class__(500.0, 480.0, 321.5, 239.25, w, width=640, height=480)
                 .project(rays)[0].sum())(jnp.asarray(0.0))
    assert float(g) == 0.0
    ru = np.linalg.norm(np.asarray(rays)[:, :2] / np.asarray(rays)[:, 2:], axis=-1)
    h = 1e-3
    small = jf.FieldOfView(1.0, 1.0, 0.0, 0.0, h, width=640, height=480)
    rd = np.linalg.norm(np.asarray(small.project(rays)[0]), axis=-1)
    np.testing.assert_allclose(rd, ru * (1 + h * h * (1 / 12 - ru * ru / 3)), rtol=1e-9 * (1 + ru.max() ** 4))


def test_omega_at_or_beyond_pi_sees_nothing():
    cam = jf.FieldOfView(300.0, 300.0, 320.0, 240.0, math.pi, width=640, height=480)
    assert not bool(jnp.any(cam.project(jnp.asarray(lens_laws.rays_up_to(1.0, 20)))[1]))
    assert not bool(jnp.any(cam.unproject(jnp.asarray([[320.0, 240.0], [330.0, 250.0]]))[1]))


def test_implicit_gradients():
    lens_laws.check_gradients(CAMERAS["wide"], np.array([[640.2, 481.7], [400.0, 300.0], [900.0, 700.0], [700.0, 100.0]]))


def test_a_batch_of_cameras():
    lens_laws.check_batch_of_cameras(CAMERAS["wide"], jf.FieldOfView(280.0, 281.0, 641.0, 480.0, 0.0, width=1280,
                                                                     height=966))
