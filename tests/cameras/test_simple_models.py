"""Pinhole, Orthographic, Equirectangular and Cylindrical: oracles, round trips, validity."""

from __future__ import annotations

import math

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish as jf
from tests.helpers import three_ways


def _dirs(n, seed=0, forward_only=False):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    if forward_only:
        d[:, 2] = np.abs(d[:, 2]) + 0.5
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def test_pinhole_from_fov_is_carla_convention():
    cam = jf.Pinhole.from_fov(800, 600, 90.0)
    assert float(cam.fx) == pytest.approx(400.0) and float(cam.fy) == pytest.approx(400.0)
    np.testing.assert_allclose([float(cam.cx), float(cam.cy)], [399.5, 299.5])
    # The optical axis hits the image centre; the 90-degree fov spans the image edge to edge.
    uv, valid = cam.project(jnp.asarray([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [-1.0, 0.0, 1.0]]))
    np.testing.assert_allclose(np.asarray(uv), [[399.5, 299.5], [799.5, 299.5], [-0.5, 299.5]], atol=1e-12)
    with pytest.raises(ValueError, match="fov_deg"):
        jf.Pinhole.from_fov(10, 10, 180.0)


def test_pinhole_matches_cv2_and_roundtrips():
    cam = jf.Pinhole(500.0, 480.0, 321.5, 239.25, width=640, height=480)
    pts = _dirs(200, forward_only=True) * 4.0
    expected, _ = cv2.projectPoints(pts[:, None, :], np.zeros(3), np.zeros(3), np.asarray(cam.intrinsic_matrix), None)
    uv, valid = cam.project(jnp.asarray(pts))
    assert bool(jnp.all(valid))
    np.testing.assert_allclose(np.asarray(uv), expected[:, 0, :], atol=1e-9)
    rays, rvalid = cam.unproject(uv)
    np.testing.assert_allclose(np.asarray(rays), pts / 4.0, atol=1e-12)
    _, behind = cam.project(jnp.asarray([[0.0, 0.0, -1.0], [1.0, 1.0, 0.0]]))
    assert not bool(jnp.any(behind))


def test_orthographic_roundtrip_and_origins():
    cam = jf.Orthographic(0.05, width=200, height=100)
    pts = jnp.asarray([[1.0, -0.5, 3.0], [0.0, 0.0, 10.0], [-4.975, -2.475, 1.0]])
    uv, valid = cam.project(pts)
    np.testing.assert_allclose(np.asarray(uv), [[119.5, 39.5], [99.5, 49.5], [0.0, 0.0]], atol=1e-9)
    assert bool(jnp.all(valid)) and not bool(cam.is_central)
    origins = cam.ray_origins(uv)
    rays, _ = cam.unproject(uv)
    # origin + t * ray reaches the point.
    np.testing.assert_allclose(np.asarray(origins + rays * pts[:, 2:3]), np.asarray(pts), atol=1e-12)
    assert not bool(cam.project(jnp.asarray([0.0, 0.0, -1.0]))[1])


def test_equirectangular_full_sphere():
    cam = jf.Equirectangular(width=360, height=180)
    d = jnp.asarray(_dirs(500, seed=2))
    uv, valid = cam.project(d)
    assert bool(jnp.all(valid)) and bool(jnp.all(cam.contains(uv)))
    rays, rvalid = cam.unproject(uv)
    assert bool(jnp.all(rvalid))
    np.testing.assert_allclose(np.asarray(rays), np.asarray(d), atol=1e-12)
    # Optical axis at the centre; +x (right) to the right of it; +y (down) below it.
    uv, _ = cam.project(jnp.asarray([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]))
    np.testing.assert_allclose(np.asarray(uv), [[179.5, 89.5], [269.5, 89.5], [179.5, 179.5]], atol=1e-9)
    g = jax.jacrev(lambda p: cam.project(p)[0])(jnp.asarray([0.0, 1.0, 0.0]))
    assert bool(jnp.all(jnp.isfinite(g))), "finite gradient at the pole"


def test_equirectangular_partial_range_validity():
    cam = jf.Equirectangular(width=100, height=50, lon_range=(-math.pi / 2, math.pi / 2), lat_range=(-0.5, 0.5))
    _, valid = cam.project(jnp.asarray([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.2]]))
    np.testing.assert_array_equal(np.asarray(valid), [True, False, False])
    with pytest.raises(ValueError, match="lon_range"):
        jf.Equirectangular(width=10, height=10, lon_range=(1.0, 0.0))


def test_cylindrical_roundtrip_keeps_verticals():
    cam = jf.Cylindrical(width=400, height=200)
    d = jnp.asarray(_dirs(300, seed=3, forward_only=True))
    uv, valid = cam.project(d)
    assert bool(jnp.all(valid))
    rays, _ = cam.unproject(uv)
    np.testing.assert_allclose(np.asarray(rays), np.asarray(d), atol=1e-12)
    # A vertical line (same longitude) maps to one image column.
    col = jnp.asarray([[1.0, y, 2.0] for y in (-1.0, 0.0, 0.7)])
    uv, _ = cam.project(col)
    np.testing.assert_allclose(np.asarray(uv[:, 0]), float(uv[0, 0]), atol=1e-12)


@pytest.mark.parametrize(
    "cam",
    [
        jf.Pinhole.from_fov(64, 48, 70.0),
        jf.Orthographic(0.1, width=64, height=48),
        jf.Equirectangular(width=64, height=32),
        jf.Cylindrical(width=64, height=32),
    ],
    ids=["pinhole", "orthographic", "equirectangular", "cylindrical"],
)
def test_eager_jit_vmap_and_float32(cam):
    pts = jnp.asarray(_dirs(8, seed=4, forward_only=True) * 3.0)
    eager, jitted, batched = three_ways(lambda p: cam.project(p), pts)
    np.testing.assert_allclose(eager[0], jitted[0], atol=1e-12)
    np.testing.assert_allclose(eager[0], batched[0], atol=1e-12)
    uv32, _ = cam.project(pts.astype(jnp.float32))
    assert uv32.dtype == jnp.float32
    for shape in ((), (1,), (3, 1, 2)):
        uv, valid = cam.unproject(jnp.full(shape + (2,), 10.0))
        assert uv.shape == shape + (3,) and valid.shape == shape
