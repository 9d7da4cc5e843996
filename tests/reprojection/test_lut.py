"""LUT generation: geometry against independent formulas, supersampling layout, jit/vmap, caching."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish as jf
from jaxfish.reprojection import (
    build_lut,
    centre_sample,
    lut_from_map,
    stack_luts,
    supersample_offsets,
)

from ..tolerances import LUT_PX_F64


def woodscape_project_numpy(cam, p: np.ndarray) -> np.ndarray:
    """The WoodScape projection (CONVENTIONS §1) typed in with NumPy, float64."""
    k = np.asarray(cam.k, np.float64)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    chi = np.hypot(x, y)
    theta = np.arctan2(chi, z)
    rho = k[0] * theta + k[1] * theta**2 + k[2] * theta**3 + k[3] * theta**4
    cx = cam.width / 2 + float(cam.cx_offset) - 0.5
    cy = cam.height / 2 + float(cam.cy_offset) - 0.5
    return np.stack([rho * x / chi + cx, rho * y / chi * float(cam.aspect_ratio) + cy], axis=-1)


def test_supersample_offsets_cover_the_pixel():
    for n in (1, 2, 3, 4):
        o = supersample_offsets(n)
        assert o.shape == (n * n, 2)
        np.testing.assert_allclose(o.mean(axis=0), 0.0, atol=1e-15)
        assert np.all(np.abs(o) < 0.5)
        assert np.allclose(o[centre_sample(n)], 0.0) == (n % 2 == 1)
    with pytest.raises(ValueError, match="positive"):
        supersample_offsets(0)


def test_rectification_lut_matches_the_woodscape_formula(jit_build_lut, small_fisheye):
    """fisheye -> pinhole looking 40 deg right and 20 deg down: every LUT entry is the WoodScape
    projection of the pinhole pixel's rotated ray."""
    pin = jf.Pinhole.from_fov(40, 30, 100.0, dtype=jnp.float64)
    yaw, pitch = math.radians(40), math.radians(-20)
    ry = np.array([[math.cos(yaw), 0, math.sin(yaw)], [0, 1, 0], [-math.sin(yaw), 0, math.cos(yaw)]])
    rx = np.array([[1, 0, 0], [0, math.cos(pitch), -math.sin(pitch)], [0, math.sin(pitch), math.cos(pitch)]])
    r = ry @ rx
    lut = jit_build_lut(small_fisheye, pin, target_to_source=jnp.asarray(r), dtype=jnp.float64)
    assert lut.target_shape == (30, 40) and lut.source_shape == (1, 120, 160) and lut.pad == 0
    f = float(pin.fx)
    uu, vv = np.meshgrid(np.arange(40.0), np.arange(30.0), indexing="xy")
    d = np.stack([(uu - 19.5) / f, (vv - 14.5) / f, np.ones_like(uu)], axis=-1)
    expected = woodscape_project_numpy(small_fisheye, d @ r.T)
    inside = (expected[..., 0] >= -0.5) & (expected[..., 0] <= 159.5) & (expected[..., 1] >= -0.5) & (expected[..., 1] <= 119.5)
    np.testing.assert_array_equal(np.asarray(lut.valid[..., 0]), inside)
    np.testing.assert_allclose(np.asarray(lut.uv[..., 0, :])[inside], expected[inside], atol=LUT_PX_F64)


def test_cube_lut_matches_dominant_axis_geometry(cube_lut, small_rig, small_fisheye, jit_unproject):
    rays, valid = jit_unproject(small_fisheye, small_fisheye.pixel_grid(jnp.float64))
    rays = np.asarray(rays)
    axes = np.asarray(small_rig.face_to_camera.rotation_matrix)[:, :, 2]
    along = rays @ axes.T
    face = np.argmax(along, axis=-1)
    v = np.asarray(valid) & np.asarray(cube_lut.valid[..., 0])
    assert v.mean() > 0.9
    np.testing.assert_array_equal(np.asarray(cube_lut.face[..., 0])[v], face[v])
    # face pixel = pinhole projection in the face frame (f = S/2, centre (S-1)/2)
    rot = np.asarray(small_rig.face_to_camera.rotation_matrix)[face]  # (H, W, 3, 3)
    local = np.einsum("hwkj,hwk->hwj", rot, rays)
    s = small_rig.width
    uv = (s / 2) * local[..., :2] / local[..., 2:3] + (s - 1) / 2
    np.testing.assert_allclose(np.asarray(cube_lut.uv[..., 0, :])[v], uv[v], atol=LUT_PX_F64)
    np.testing.assert_allclose(np.asarray(cube_lut.z_to_range[..., 0])[v], 1.0 / np.max(along, axis=-1)[v], rtol=1e-12)


def test_lut_jit_and_vmap_over_cameras(jit_build_lut, small_rig, cube_lut, small_fisheye):
    """A batch of cameras through vmap equals LUTs built one by one (and stacked)."""
    other = jf.resize_fisheye(jf.default_rig()["MVL"].camera, 160, 120).astype(jnp.float64)
    single = [cube_lut, jit_build_lut(small_rig, other, dtype=jnp.float64)]
    stacked = jax.tree_util.tree_map(lambda *x: jnp.stack(x), small_fisheye, other)
    batched = eqx.filter_jit(eqx.filter_vmap(lambda c: build_lut(small_rig, c, dtype=jnp.float64)))(stacked)
    manual = stack_luts(single)
    assert batched.valid.shape == (2, 120, 160, 1)
    for name in ("valid", "face", "tap_index", "nearest_index", "ring_index"):
        np.testing.assert_array_equal(np.asarray(getattr(manual, name)), np.asarray(getattr(batched, name)), err_msg=name)
    np.testing.assert_allclose(np.asarray(manual.uv), np.asarray(batched.uv), atol=LUT_PX_F64)


def test_panoramic_and_pinhole_to_fisheye(jit_build_lut, small_fisheye):
    """Equirectangular targets and a pinhole source come from the same build_lut."""
    eq = jf.Equirectangular(width=64, height=32, dtype=jnp.float64)
    lut = jit_build_lut(small_fisheye, eq, dtype=jnp.float64)
    v = np.asarray(lut.valid[..., 0])
    assert 0.1 < v.mean() < 0.7  # a ~190 deg lens sees about half the sphere, minus the cropped image
    assert v[16, 32] and not v[16, 0]  # straight ahead seen, straight behind not
    pin = jf.Pinhole.from_fov(64, 48, 90.0, dtype=jnp.float64)
    back = jit_build_lut(pin, small_fisheye, dtype=jnp.float64)  # pinhole -> fisheye
    uv = np.asarray(back.uv[..., 0, :])
    vb = np.asarray(back.valid[..., 0])
    assert vb[60, 80] and not vb[60, 0]
    # the pinhole pixel found for a fisheye pixel projects back onto that fisheye pixel
    d = np.concatenate([(uv[vb] - [31.5, 23.5]) / 32.0, np.ones((vb.sum(), 1))], axis=-1)
    fish = np.stack(np.meshgrid(np.arange(160.0), np.arange(120.0), indexing="xy"), axis=-1)[vb]
    np.testing.assert_allclose(woodscape_project_numpy(small_fisheye, d), fish, atol=1e-6)


def test_lut_from_map_and_errors():
    uv = jnp.asarray([[[[0.0, 0.0]], [[9.4, 3.0]], [[10.0, 0.0]]]])  # (1, 3, 1, 2), last one outside
    lut = lut_from_map(uv, source_width=10, source_height=5)
    np.testing.assert_array_equal(np.asarray(lut.valid[0, :, 0]), [True, True, False])
    assert int(lut.nearest_index[0, 1, 0]) == 3 * 10 + 9
    with pytest.raises(ValueError, match="square"):
        lut_from_map(jnp.zeros((2, 2, 3, 2)), source_width=4, source_height=4)
    with pytest.raises(ValueError, match="3x3"):
        build_lut(jf.Pinhole.from_fov(8, 8), jf.Pinhole.from_fov(8, 8), target_to_source=jnp.eye(4))
