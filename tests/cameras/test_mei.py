"""MeiCamera (unified model + radial-tangential distortion) against cv2.omnidir and its laws."""

from __future__ import annotations

import math

import cv2
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish as jf
from tests import tolerances as tol
from tests.cameras import lens_laws

CAMERAS = {
    # kalibr-like omni-radtan calibrations: xi above and below 1, barrel distortion.
    "xi_above_1": jf.MeiCamera(760.0, 765.0, 640.2, 481.7, 1.35, (-0.28, 0.07, 1.2e-3, -6e-4), width=1280, height=966),
    "xi_below_1": jf.MeiCamera(520.0, 523.0, 640.2, 481.7, 0.7, (-0.12, 0.02, -8e-4, 5e-4), width=1280, height=966),
    "xi_zero": jf.MeiCamera(400.0, 401.0, 320.5, 240.5, 0.0, (-0.2, 0.05, 1e-3, 1e-3), width=640, height=480),
}


def _top(cam) -> float:
    """theta_max, or where the lens never folds (k2 > 0) the angle of r = 20 before distortion (the
    domain there ends where the distorted radius reaches MAX_DISTORTED_RADIUS)."""
    if float(cam.r_max()) < 100:
        return float(cam.theta_max()) - 1e-6
    xi = float(cam.xi)
    return math.acos((xi + math.sqrt(1 + (1 - xi * xi) * 400.0)) / 401.0 - xi)


def _omnidir(cam, rays):
    uv, _ = cv2.omnidir.projectPoints(rays[:, None, :], np.zeros(3), np.zeros(3), np.asarray(cam.intrinsic_matrix),
                                      float(cam.xi), np.asarray(cam.distortion)[None])
    return uv[:, 0]


@pytest.mark.parametrize("name", list(CAMERAS))
def test_project_matches_cv2_omnidir_on_the_whole_domain(name, jit_project):
    cam = CAMERAS[name]
    rays = lens_laws.rays_up_to(_top(cam), 1000) * 3.0
    uv, valid = jit_project(cam, jnp.asarray(rays))
    assert bool(jnp.all(valid))
    np.testing.assert_allclose(np.asarray(uv), _omnidir(cam, rays), rtol=1e-13, atol=tol.MODEL_PX_F64)


def test_without_distortion_it_is_the_unified_camera(jit_project, jit_unproject):
    mei = jf.MeiCamera(700.0, 712.5, 640.2, 481.7, 1.5, width=1280, height=966)
    ucm = jf.UnifiedCamera.from_mei(1.5, 700.0, 712.5, 640.2, 481.7, width=1280, height=966)
    assert float(mei.theta_max()) == pytest.approx(float(ucm.theta_max()), abs=1e-12)
    rays = jnp.asarray(lens_laws.rays_up_to(float(ucm.theta_max()) - 1e-3, 500))
    np.testing.assert_allclose(np.asarray(jit_project(mei, rays)[0]), np.asarray(jit_project(ucm, rays)[0]), atol=1e-9)
    grid = lens_laws.image_grid(mei)
    r1, v1 = jit_unproject(mei, grid)
    r2, v2 = jit_unproject(ucm, grid)
    np.testing.assert_array_equal(np.asarray(v1), np.asarray(v2))
    np.testing.assert_allclose(np.asarray(r1)[np.asarray(v1)], np.asarray(r2)[np.asarray(v1)], atol=1e-12)


@pytest.mark.parametrize("name", list(CAMERAS))
def test_pixel_ray_pixel_float64_and_float32(name):
    lens_laws.check_pixel_ray_pixel(CAMERAS[name], atol=tol.ROUNDTRIP_PX_F64, min_valid=0.5)
    if name == "xi_above_1":  # float32, eager / jit / vmap: one camera (each is a compile of the Newton solve)
        lens_laws.check_pixel_ray_pixel(CAMERAS[name], atol=tol.MODEL_PX_F32, min_valid=0.5, dtype=jnp.float32, three=True)


@pytest.mark.parametrize("name", list(CAMERAS))
def test_rays_to_the_edge_of_the_domain(name, jit_project, jit_unproject):
    """Up to theta_max; where the radial part never folds (k2 > 0) the domain ends where the distorted
    radius reaches MAX_DISTORTED_RADIUS, so the rays stop at r = 20 (before distortion) there (`_top`)."""
    lens_laws.check_ray_pixel_ray_to_the_edge(CAMERAS[name], jit_project, jit_unproject, theta_top=_top(CAMERAS[name]))


def test_domain_ends_where_the_radial_distortion_folds(jit_project, jit_unproject):
    """r (1 + k1 r² + k2 r⁴) has its maximum at 3 k1 r² + 5 k2 r⁴ + 1 = 0 (np.roots); the domain ends
    1e-3 rad (in atan r) before, and theta_max is the incidence angle of that radius."""
    xi, k1, k2 = 0.9, -0.35, 0.02
    cam = jf.MeiCamera(500.0, 500.0, 640.0, 480.0, xi, (k1, k2, 0.0, 0.0), width=1280, height=966)
    s = min(r.real for r in np.roots([5 * k2, 3 * k1, 1.0]) if abs(r.imag) < 1e-12 and r.real > 0)
    r_max = math.tan(math.atan(math.sqrt(s)) - jf.cameras.RADTAN_MARGIN_RAD)
    assert float(cam.r_max()) == pytest.approx(r_max, rel=1e-9)
    lam = (xi + math.sqrt(1 + (1 - xi * xi) * r_max**2)) / (1 + r_max**2)
    assert float(cam.theta_max()) == pytest.approx(math.acos(lam - xi), abs=1e-9)
    lens_laws.check_ray_pixel_ray_to_the_edge(cam, jit_project, jit_unproject)


def test_the_unified_fold_bounds_the_domain_for_xi_above_1():
    cam = CAMERAS["xi_above_1"]
    xi = float(cam.xi)
    assert float(cam.theta_max()) <= math.acos(-1 / xi) + 1e-12
    fold = math.acos(-1 / xi)
    beyond = jnp.asarray([[math.sin(fold + 1e-3), 0.0, math.cos(fold + 1e-3)], [0.0, 0.0, -1.0], [0.0, 0.0, 0.0]])
    assert not bool(jnp.any(cam.project(beyond)[1]))
    nothing = jf.MeiCamera(500.0, 500.0, 640.0, 480.0, -1.0, width=1280, height=966)
    assert not bool(jnp.any(nothing.project(jnp.asarray(lens_laws.rays_up_to(math.pi, 50)))[1]))


def test_a_tangential_fold_is_invalid():
    """Strong tangential terms fold the image (the Jacobian determinant changes sign) before the
    radial part does: points beyond the fold are invalid, pixels unproject to the unfolded side."""
    cam = jf.MeiCamera(500.0, 500.0, 640.0, 480.0, 1.0, (0.0, 0.0, 0.2, 0.0), width=1280, height=966)
    theta = np.linspace(-3.0, 3.0, 601)  # along y: yd = y + 3 p1 y², folding at y = -1 / (6 p1)
    rays = np.stack([np.zeros_like(theta), np.sin(theta), np.cos(theta)], -1)
    uv, valid = cam.project(jnp.asarray(rays))
    valid = np.asarray(valid)
    assert valid.any() and not valid.all()
    back, bvalid = cam.unproject(uv[valid])
    assert bool(jnp.all(bvalid))
    np.testing.assert_allclose(np.asarray(back), rays[valid] / np.linalg.norm(rays[valid], axis=-1, keepdims=True),
                               atol=1e-10)


def test_implicit_gradients():
    cam = CAMERAS["xi_above_1"]
    lens_laws.check_gradients(cam, np.array([[640.2, 481.7], [100.0, 200.0], [1100.0, 900.0], [700.0, 30.0]]))


def test_a_batch_of_cameras():
    lens_laws.check_batch_of_cameras(CAMERAS["xi_above_1"], CAMERAS["xi_below_1"])
