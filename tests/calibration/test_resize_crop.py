"""Exact resize and crop of WoodScape intrinsics (`resize_fisheye`, `crop_fisheye`, `Calibration.resize/crop`)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish as jf
from tests import tolerances as tol

N = 512


def _points(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(N, 3))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return d * rng.uniform(0.5, 30.0, (N, 1))


def _camera() -> jf.WoodScapeFisheye:
    return jf.WoodScapeFisheye([335.0, -28.0, 45.0, -6.5], width=1280, height=966, cx_offset=3.9, cy_offset=-3.1,
                               aspect_ratio=1.002)


@pytest.mark.parametrize("size", [(640, 483), (1920, 1449), (333, 777)])
def test_resized_camera_projects_to_the_resized_pixel(size, jit_project, jit_unproject):
    cam = _camera()
    w, h = size
    small = jf.resize_fisheye(cam, w, h)
    assert small.image_size == (w, h)
    theta_max = jax.jit(lambda c: c.theta_max())
    assert float(theta_max(small)) == pytest.approx(float(theta_max(cam)), abs=1e-12)
    sx, sy = w / cam.width, h / cam.height
    pts = jnp.asarray(_points())
    uv, valid = jit_project(cam, pts)
    uv2, valid2 = jit_project(small, pts)
    assert np.array_equal(np.asarray(valid), np.asarray(valid2))
    expected = (np.asarray(uv) + 0.5) * [sx, sy] - 0.5  # pixel edges map to pixel edges
    np.testing.assert_allclose(np.asarray(uv2), expected, rtol=0, atol=tol.PROJECT_PX_F64 * 10)
    if size != (640, 483):
        return
    # The inverse: a resized pixel has the ray of the corresponding original pixel.
    grid = np.asarray(cam.pixel_grid(jnp.float64))[::60, ::60].reshape(-1, 2)
    grid = np.concatenate([grid, np.zeros((N - len(grid), 2))])
    rays, ok = jit_unproject(cam, jnp.asarray(grid))
    rays2, ok2 = jit_unproject(small, jnp.asarray((grid + 0.5) * [sx, sy] - 0.5))
    assert np.array_equal(np.asarray(ok), np.asarray(ok2))
    np.testing.assert_allclose(np.asarray(rays2), np.asarray(rays), rtol=0, atol=1e-11)


def test_real_calibration_resize_and_crop_roundtrip(real_calibration_path, jit_project):
    calib = jf.load_calibration(real_calibration_path)
    half = calib.resize(calib.camera.width // 2, calib.camera.height // 3)
    assert half.name == calib.name
    np.testing.assert_array_equal(np.asarray(half.camera_to_vehicle.translation),
                                  np.asarray(calib.camera_to_vehicle.translation))
    back = half.resize(calib.camera.width, calib.camera.height)
    pts = jnp.asarray(_points(1))
    np.testing.assert_allclose(np.asarray(jit_project(back.camera, pts)[0]), np.asarray(jit_project(calib.camera, pts)[0]),
                               rtol=0, atol=tol.PROJECT_PX_F64 * 10)
    crop = calib.crop(100, 50, 800, 600)
    np.testing.assert_allclose(np.asarray(jit_project(crop.camera, pts)[0]),
                               np.asarray(jit_project(calib.camera, pts)[0]) - [100, 50], rtol=0,
                               atol=tol.PROJECT_PX_F64 * 10)


@pytest.mark.parametrize("box", [(0, 0, 1280, 966), (200, 100, 640, 480), (-100, -50, 1500, 1100), (1000, 900, 64, 32)])
def test_crop_shifts_pixels(box, jit_project):
    cam = _camera()
    x0, y0, w, h = box
    crop = jf.crop_fisheye(cam, x0, y0, w, h)
    assert crop.image_size == (w, h)
    pts = jnp.asarray(_points(2))
    uv, valid = jit_project(cam, pts)
    uv2, valid2 = jit_project(crop, pts)
    np.testing.assert_allclose(np.asarray(uv2), np.asarray(uv) - [x0, y0], rtol=0, atol=tol.PROJECT_PX_F64 * 10)
    assert np.array_equal(np.asarray(valid), np.asarray(valid2))
    np.testing.assert_allclose(np.asarray(crop.principal_point), np.asarray(cam.principal_point) - [x0, y0], atol=1e-12)
    np.testing.assert_array_equal(np.asarray(crop.k), np.asarray(cam.k))


def test_crop_then_resize_composes(jit_project):
    cam = _camera()
    out = jf.resize_fisheye(jf.crop_fisheye(cam, 320, 241, 640, 483), 256, 128)
    pts = jnp.asarray(_points(3))
    uv = np.asarray(jit_project(cam, pts)[0])
    expected = (uv - [320, 241] + 0.5) * [256 / 640, 128 / 483] - 0.5
    np.testing.assert_allclose(np.asarray(jit_project(out, pts)[0]), expected, rtol=0, atol=tol.PROJECT_PX_F64 * 10)


def test_non_uniform_resize_is_not_a_scaled_k():
    """OmniDet-style scaling (k by one factor, the aspect ratio unchanged) is wrong for non-uniform
    resizes; the exact rule keeps k * sx for u and moves sy / sx into the aspect ratio."""
    cam = _camera()
    out = jf.resize_fisheye(cam, 640, 241)
    sx, sy = 640 / 1280, 241 / 966
    np.testing.assert_allclose(np.asarray(out.k), np.asarray(cam.k) * sx, rtol=1e-15)
    assert float(out.aspect_ratio) == pytest.approx(float(cam.aspect_ratio) * sy / sx, rel=1e-15)


@pytest.mark.parametrize("bad", [(0, 10), (10, -1)])
def test_bad_sizes_raise(bad):
    with pytest.raises(ValueError, match="positive"):
        jf.resize_fisheye(_camera(), *bad)
    with pytest.raises(ValueError, match="positive"):
        jf.crop_fisheye(_camera(), 0, 0, *bad)
