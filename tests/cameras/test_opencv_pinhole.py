"""OpenCVPinhole (radial-tangential + rational + thin prism) against cv2.projectPoints and its laws."""

from __future__ import annotations

import math

import cv2
import jax.numpy as jnp
import numpy as np
import pytest
from numpy.polynomial import polynomial as P

import jaxfish as jf
from tests import tolerances as tol
from tests.cameras import lens_laws

# OpenCV's order: k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4.
FULL = (-0.31, 0.11, 1.1e-3, -6e-4, -0.02, 0.04, 0.01, -0.003, 1.5e-3, -2e-4, 8e-4, 1e-4)
CAMERAS = {
    "full": jf.OpenCVPinhole(610.0, 612.0, 640.3, 360.8, FULL, width=1280, height=720),
    "radtan": jf.OpenCVPinhole(458.654, 457.296, 367.215, 248.375, (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05),
                               width=752, height=480),  # EuRoC cam0 (kalibr pinhole-radtan)
    "rational_wide": jf.OpenCVPinhole(300.0, 300.0, 320.0, 240.0, (0.9, 0.2, 0.0, 0.0, 0.01, 1.4, 0.5, 0.05),
                                      width=640, height=480),
}


MIN_VALID = {"full": 0.6, "radtan": 1.0, "rational_wide": 0.99}
"""Fraction of the image with rays: the strong barrel of "full" reaches its radial maximum inside the image."""


def _top(cam) -> float:
    """The sampled incidence angles: up to theta_max (minus 0.01 rad where tangential and prism terms
    fold the image just before the radial part does), or to r = 20 where the radial part never folds
    (k2 > 0: the domain then ends where the distorted radius reaches MAX_DISTORTED_RADIUS)."""
    if float(cam.r_max()) > 100:
        return math.atan(20.0)
    return float(cam.theta_max()) - 0.01


def _cv2_project(cam, rays):
    uv, _ = cv2.projectPoints(rays[:, None, :], np.zeros(3), np.zeros(3), np.asarray(cam.intrinsic_matrix),
                              np.asarray(cam.distortion))
    return uv[:, 0]


def _radial_limit(d) -> float:
    """atan of the first radius where r N(r²)/D(r²) stops increasing or D reaches 0 (np.roots)."""
    k1, k2, _, _, k3, k4, k5, k6 = d[:8]
    n, den = [1.0, k1, k2, k3], [1.0, k4, k5, k6]
    s_n = P.polymulx(P.polyder(n))  # s N'(s)
    s_d = P.polymulx(P.polyder(den))
    g = P.polysub(P.polymul(P.polyadd(n, 2 * s_n), den), 2 * P.polymul(n, s_d))
    roots = [r.real for poly in (g, den) for r in P.polyroots(P.polytrim(poly)) if abs(r.imag) < 1e-12 and r.real > 0]
    return math.atan(math.sqrt(min(roots))) if roots else math.pi / 2


@pytest.mark.parametrize("name", list(CAMERAS))
def test_project_matches_cv2_project_points_rational_and_thin_prism(name, jit_project):
    cam = CAMERAS[name]
    rays = lens_laws.rays_up_to(_top(cam), 1000) * 4.0
    uv, valid = jit_project(cam, jnp.asarray(rays))
    assert bool(jnp.all(valid))
    np.testing.assert_allclose(np.asarray(uv), _cv2_project(cam, rays), rtol=1e-13, atol=tol.MODEL_PX_F64)


@pytest.mark.parametrize("name", list(CAMERAS))
def test_domain_ends_before_the_radial_fold(name):
    cam = CAMERAS[name]
    limit = min(_radial_limit(np.asarray(cam.distortion)), math.pi / 2)
    assert float(cam.theta_max()) == pytest.approx(limit - jf.cameras.RADTAN_MARGIN_RAD, abs=1e-9)
    assert float(cam.r_max()) == pytest.approx(math.tan(limit - jf.cameras.RADTAN_MARGIN_RAD), rel=1e-9)


def test_unprojection_agrees_with_cv2_undistort_points():
    """cv2 iterates its own undistortion (a fixed-point scheme, here 500 steps): they agree where
    it converges, on the image of the EuRoC calibration."""
    cam = CAMERAS["radtan"]
    grid = np.asarray(lens_laws.image_grid(cam))
    rays, valid = cam.unproject(jnp.asarray(grid))
    assert bool(jnp.all(valid))
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 500, 1e-15)
    xy = cv2.undistortPoints(grid[:, None, :], np.asarray(cam.intrinsic_matrix), np.asarray(cam.distortion),
                             criteria=crit)[:, 0]
    ours = np.asarray(rays)[:, :2] / np.asarray(rays)[:, 2:]
    np.testing.assert_allclose(ours, xy, atol=1e-9)


@pytest.mark.parametrize("name", list(CAMERAS))
def test_pixel_ray_pixel_float64_and_float32(name):
    lens_laws.check_pixel_ray_pixel(CAMERAS[name], atol=tol.ROUNDTRIP_PX_F64, min_valid=MIN_VALID[name])
    if name == "radtan":  # float32, eager / jit / vmap: one camera (each is a compile of the Newton solve)
        lens_laws.check_pixel_ray_pixel(CAMERAS[name], atol=tol.MODEL_PX_F32, min_valid=MIN_VALID[name], dtype=jnp.float32, three=True)


@pytest.mark.parametrize("name", list(CAMERAS))
def test_rays_to_the_edge_of_the_domain(name, jit_project, jit_unproject):
    cam = CAMERAS[name]
    top = _top(cam) if name != "rational_wide" else None  # no tangential terms: the radial edge itself
    lens_laws.check_ray_pixel_ray_to_the_edge(cam, jit_project, jit_unproject, theta_top=top)


def test_without_distortion_it_is_the_pinhole(jit_project, jit_unproject):
    cam = jf.OpenCVPinhole(500.0, 480.0, 321.5, 239.25, width=640, height=480)
    pin = jf.Pinhole(500.0, 480.0, 321.5, 239.25, width=640, height=480)
    rays = jnp.asarray(lens_laws.rays_up_to(1.5, 300))
    np.testing.assert_allclose(np.asarray(jit_project(cam, rays)[0]), np.asarray(jit_project(pin, rays)[0]), atol=1e-9)
    grid = lens_laws.image_grid(cam)
    np.testing.assert_allclose(np.asarray(jit_unproject(cam, grid)[0]), np.asarray(jit_unproject(pin, grid)[0]),
                               atol=1e-14)
    assert float(cam.theta_max()) == pytest.approx(math.pi / 2 - jf.cameras.RADTAN_MARGIN_RAD)
    assert not bool(jnp.any(cam.project(jnp.asarray([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]))[1]))


def test_shorter_distortion_vectors_are_padded_and_others_refused():
    five = jf.OpenCVPinhole(500.0, 500.0, 320.0, 240.0, (-0.2, 0.05, 1e-3, 2e-3, 0.01), width=640, height=480)
    np.testing.assert_array_equal(np.asarray(five.distortion), [-0.2, 0.05, 1e-3, 2e-3, 0.01] + [0.0] * 7)
    with pytest.raises(ValueError, match="distortion must have shape"):
        jf.OpenCVPinhole(500.0, 500.0, 320.0, 240.0, (0.1, 0.2, 0.3), width=640, height=480)


def test_a_thin_prism_fold_is_invalid():
    """A thin prism term folds the image before the radial part: beyond the fold, points are invalid
    (even where the Jacobian turns positive again), and every valid pixel unprojects to its ray."""
    cam = jf.OpenCVPinhole(300.0, 300.0, 320.0, 240.0, (0.0, 0.0, 0.0, 0.0, 0.0, 0, 0, 0, 0.0, 0.0, -0.3, 0.0),
                           width=640, height=480)
    y = np.linspace(-8.0, 8.0, 801)  # yd = y - 0.3 y²: folds at y = 1/0.6
    rays = np.stack([np.zeros_like(y), y, np.ones_like(y)], -1)
    uv, valid = cam.project(jnp.asarray(rays))
    valid = np.asarray(valid)
    np.testing.assert_array_equal(valid, y < 1 / 0.6)
    back, bvalid = cam.unproject(uv[valid])
    assert bool(jnp.all(bvalid))
    np.testing.assert_allclose(np.asarray(back), rays[valid] / np.linalg.norm(rays[valid], axis=-1, keepdims=True),
                               atol=1e-12)


def test_implicit_gradients():
    lens_laws.check_gradients(CAMERAS["full"], np.array([[640.3, 360.8], [300.0, 150.0], [1000.0, 600.0], [900.0, 120.0]]))


def test_a_batch_of_cameras():
    a = CAMERAS["full"]
    lens_laws.check_batch_of_cameras(a, jf.OpenCVPinhole(600.0, 601.0, 639.0, 359.0, FULL[:4] + (0.0,) * 8,
                                                         width=1280, height=720))
