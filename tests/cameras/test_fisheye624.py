"""Fisheye624 (projectaria's FisheyeRadTanThinPrism) against projectaria's formula and its laws."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish as jf
from tests import tolerances as tol
from tests.cameras import lens_laws

# An Aria-like RGB calibration (single focal length in Aria: fx = fy there). Its polynomial grows
# steeply past its ~110 degree field of view: the thin prism terms fold it near 85 degrees
# (`TOP`: sampled up to 1.2 rad), the radial part never does (theta_max = pi).
ARIA = dict(k=(0.393, -0.419, -0.068, 1.14, -1.18, 0.375), p=(1.1e-4, -4.3e-4), s=(-9.4e-4, 2.1e-5, 4.1e-4, -3.6e-5))
CAMERAS = {
    "aria": jf.Fisheye624(610.0, 610.0, 715.1, 716.4, **ARIA, width=1408, height=1408),
    "separate_focals": jf.Fisheye624(330.0, 331.5, 640.2, 481.7, (0.02, -0.003, 0.001, -1e-4, 1e-5, -1e-6),
                                     (1e-3, -5e-4), (1e-3, -1e-4, 5e-4, 2e-5), width=1280, height=966),
}

TOP = {"aria": 1.2, "separate_focals": math.radians(89.0)}


def _projectaria(cam, p):
    """projectaria_tools FisheyeRadTanThinPrism::project, written out (z > 0)::

        ab = (x, y) / z,  r = |ab|,  th = atan(r),  th_radial = 1 + k0 th² + ... + k5 th¹²
        xr_yr = th_radial * th / r * ab,  r2 = |xr_yr|²
        uv = xr_yr + 2 (xr_yr . p) xr_yr + r2 p + (s0 r2 + s1 r2², s2 r2 + s3 r2²)
        pixel = f * uv + c
    """
    k, pt, s = np.asarray(cam.k), np.asarray(cam.p), np.asarray(cam.s)
    ab = p[:, :2] / p[:, 2:]
    r = np.linalg.norm(ab, axis=-1)
    th = np.arctan(r)
    th_radial = 1 + sum(k[i] * th ** (2 * i + 2) for i in range(6))
    xr = (th_radial * np.where(r < 1e-300, 1.0, th / r))[:, None] * ab
    r2 = np.sum(xr * xr, -1)
    uv = xr + 2 * (xr @ pt)[:, None] * xr + r2[:, None] * pt
    uv = uv + np.stack([s[0] * r2 + s[1] * r2**2, s[2] * r2 + s[3] * r2**2], -1)
    return uv * [float(cam.fx), float(cam.fy)] + [float(cam.cx), float(cam.cy)]


@pytest.mark.parametrize("name", list(CAMERAS))
def test_project_matches_projectaria_in_front_of_the_camera(name, jit_project):
    cam = CAMERAS[name]
    rays = lens_laws.rays_up_to(TOP[name], 1000, seed=2)
    uv, valid = jit_project(cam, jnp.asarray(rays))
    assert bool(jnp.all(valid))
    np.testing.assert_allclose(np.asarray(uv), _projectaria(cam, rays), rtol=1e-13, atol=tol.MODEL_PX_F64)


def test_without_tangential_and_prism_it_is_kannala_brandt(jit_project, jit_unproject):
    k = (0.02, -0.003, 0.001, -1e-4)
    f624 = jf.Fisheye624(330.0, 331.0, 640.2, 481.7, (*k, 0.0, 0.0), width=1280, height=966)
    kb = jf.KannalaBrandt(330.0, 331.0, 640.2, 481.7, k, width=1280, height=966)
    assert float(f624.theta_max()) == pytest.approx(float(kb.theta_max()), abs=1e-12)
    rays = jnp.asarray(lens_laws.rays_up_to(float(kb.theta_max()), 500))
    np.testing.assert_allclose(np.asarray(jit_project(f624, rays)[0]), np.asarray(jit_project(kb, rays)[0]), atol=1e-9)
    grid = lens_laws.image_grid(kb)
    r1, v1 = jit_unproject(f624, grid)
    r2, v2 = jit_unproject(kb, grid)
    np.testing.assert_array_equal(np.asarray(v1), np.asarray(v2))
    np.testing.assert_allclose(np.asarray(r1)[np.asarray(v1)], np.asarray(r2)[np.asarray(v1)], atol=1e-12)


@pytest.mark.parametrize("name", list(CAMERAS))
def test_pixel_ray_pixel_float64_and_float32(name):
    lens_laws.check_pixel_ray_pixel(CAMERAS[name], atol=tol.ROUNDTRIP_PX_F64, min_valid=0.7)
    if name == "separate_focals":  # float32, eager / jit / vmap: one camera (each is a compile of the Newton solve)
        lens_laws.check_pixel_ray_pixel(CAMERAS[name], atol=tol.MODEL_PX_F32, min_valid=0.7, dtype=jnp.float32, three=True)


@pytest.mark.parametrize("name", list(CAMERAS))
def test_rays_to_the_edge_of_the_domain(name, jit_project, jit_unproject):
    top = TOP[name] if name == "aria" else None
    lens_laws.check_ray_pixel_ray_to_the_edge(CAMERAS[name], jit_project, jit_unproject, theta_top=top)


def test_domain_ends_before_the_stationary_point_of_theta_d():
    """theta_d'(θ) = 1 + 3 k0 θ² + ... + 13 k5 θ¹² has its first positive root at θ_s (np.roots):
    the domain ends KB_THETA_MAX_MARGIN_RAD before it."""
    cam = CAMERAS["aria"]
    k = np.asarray(cam.k)
    coeffs = np.zeros(13)
    coeffs[0] = 1.0
    for i in range(6):
        coeffs[2 * i + 2] = (2 * i + 3) * k[i]
    roots = [r.real for r in np.roots(coeffs[::-1]) if abs(r.imag) < 1e-9 and 0 < r.real <= math.pi]
    theta_s = min(roots) if roots else math.pi
    expected = theta_s - jf.cameras.KB_THETA_MAX_MARGIN_RAD if roots else math.pi
    assert float(cam.theta_max()) == pytest.approx(expected, abs=1e-9)


def test_a_tangential_fold_is_invalid():
    """Strong tangential terms fold the image: beyond the fold (even where the Jacobian turns
    positive again) points are invalid, and every valid pixel unprojects to its own ray."""
    cam = jf.Fisheye624(300.0, 300.0, 320.0, 240.0, p=(0.0, 0.15), width=640, height=480)
    theta = np.linspace(-3.1, 3.1, 621)  # along y: yd = yr + 3 p1 yr², folding at yr = -1 / (6 p1)
    rays = np.stack([np.zeros_like(theta), np.sin(theta), np.cos(theta)], -1)
    uv, valid = cam.project(jnp.asarray(rays))
    valid = np.asarray(valid)
    np.testing.assert_array_equal(valid, theta > -1 / 0.9)
    back, bvalid = cam.unproject(uv[valid])
    assert bool(jnp.all(bvalid))
    np.testing.assert_allclose(np.asarray(back), rays[valid], atol=1e-11)


def test_implicit_gradients():
    lens_laws.check_gradients(CAMERAS["aria"], np.array([[715.1, 716.4], [300.0, 200.0], [1100.0, 1200.0], [700.0, 90.0]]))


def test_a_batch_of_cameras():
    a = CAMERAS["separate_focals"]
    lens_laws.check_batch_of_cameras(a, jf.Fisheye624(320.0, 321.0, 641.0, 480.0, (0.01, 0.0, 0.0, 0.0, 0.0, 0.0),
                                                      width=1280, height=966))
