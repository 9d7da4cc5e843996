"""Resampling kernels: cv2.remap as oracle, analytic cubes (incl. seams), depth, supersampling."""

from __future__ import annotations

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish as jf
from jaxfish.reprojection import CubeRig, Lut, lut_from_map, pad_faces, resample_bilinear, supersample_offsets

from ..helpers import three_ways
from ..tolerances import (
    ANALYTIC_CUBE,
    CV2_REMAP_F32,
    DEPTH_PLANE_REL_F32,
    DEPTH_SPHERE_REL_F32,
)
from .conftest import face_rays, smooth_function

SRC_W, SRC_H = 37, 29


@pytest.fixture(scope="module")
def remap_case():
    """A random image and a random map on the 1/32-pixel grid (cv2's interpolation grid, so its
    fixed-point weights are exact), reaching half a pixel beyond every border."""
    rng = np.random.default_rng(1)
    img = rng.random((SRC_H, SRC_W, 3), dtype=np.float32)
    u = np.round(rng.uniform(-0.5, SRC_W - 0.5, (23, 31)) * 32) / 32
    v = np.round(rng.uniform(-0.5, SRC_H - 0.5, (23, 31)) * 32) / 32
    u[0, :8] = np.linspace(-0.5, 0, 8)  # borders on purpose
    v[1, :8] = np.linspace(SRC_H - 1, SRC_H - 0.5, 8)
    return img, u.astype(np.float32), v.astype(np.float32)


def test_bilinear_matches_cv2_remap(remap_case, jit_kernels):
    img, u, v = remap_case
    lut = lut_from_map(jnp.asarray(np.stack([u, v], -1)[:, :, None, :]), source_width=SRC_W, source_height=SRC_H)
    expected = cv2.remap(img, u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    eager, jitted, vmapped = three_ways(lambda x, l: resample_bilinear(x, l)[0], jnp.asarray(img)[None], lut)
    for got in (eager, jitted, vmapped):
        assert got.dtype == np.float32
        np.testing.assert_allclose(got, expected, atol=CV2_REMAP_F32)
    out, valid = jit_kernels["bilinear"](jnp.asarray(img)[None], lut)
    assert np.all(np.asarray(valid))


def test_nearest_matches_cv2_exactly(remap_case, jit_kernels):
    _, u, v = remap_case
    u = u + np.float32(1 / 64)  # away from the .5 ties, where rounding conventions differ
    v = v - np.float32(1 / 64)
    u, v = np.clip(u, -0.49, SRC_W - 0.51), np.clip(v, -0.49, SRC_H - 0.51)
    labels = np.random.default_rng(2).integers(0, 65535, (SRC_H, SRC_W), dtype=np.uint16)
    lut = lut_from_map(jnp.asarray(np.stack([u, v], -1)[:, :, None, :]), source_width=SRC_W, source_height=SRC_H)
    got, _ = jit_kernels["nearest"](jnp.asarray(labels)[None], lut)
    expected = cv2.remap(labels, u, v, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
    assert got.dtype == jnp.uint16
    np.testing.assert_array_equal(np.asarray(got), expected)


def test_integer_images_are_rounded_not_truncated(jit_kernels):
    img = np.array([[[0], [255]], [[10], [20]]], np.uint8)
    lut = lut_from_map(jnp.asarray([[[[0.5, 0.0]], [[0.999, 0.0]]]]), source_width=2, source_height=2)
    got, _ = jit_kernels["bilinear"](jnp.asarray(img)[None], lut)
    np.testing.assert_array_equal(np.asarray(got)[0, :, 0], [128, 255])


def _analytic_faces(rig):
    return smooth_function(face_rays(rig))


def test_analytic_cube_is_seam_free(cube_lut, small_rig, small_fisheye, jit_kernels, jit_unproject):
    faces = _analytic_faces(small_rig)
    out, valid = jit_kernels["bilinear"](jnp.asarray(faces), cube_lut)
    rays, rv = jit_unproject(small_fisheye, small_fisheye.pixel_grid(jnp.float64))
    expected = smooth_function(np.asarray(rays))
    v = np.asarray(valid) & np.asarray(rv)
    err = np.max(np.abs(np.asarray(out) - expected), axis=-1)
    uv = np.asarray(cube_lut.uv[..., 0, :])
    s = small_rig.width
    seam = v & np.any((uv < 0.5) | (uv > s - 1.5), axis=-1)  # taps reach into the padding ring
    assert seam.sum() > 100 and (v & ~seam).sum() > 1000
    assert err[v & ~seam].max() < ANALYTIC_CUBE
    assert err[seam].max() < ANALYTIC_CUBE  # worst at the cube corners, where three faces meet
    # Clamping taps at the face border instead of padding (ring switched off) is much worse there.
    clamped = eqx.tree_at(lambda l: l.ring_valid, cube_lut, jnp.zeros_like(cube_lut.ring_valid))
    out_c, _ = jit_kernels["bilinear"](jnp.asarray(faces), clamped)
    err_c = np.max(np.abs(np.asarray(out_c) - expected), axis=-1)
    assert np.percentile(err_c[seam], 99) > 10 * np.percentile(err[seam], 99)


def test_pad_ring_holds_the_neighbouring_faces(cube_lut, small_rig):
    faces = _analytic_faces(small_rig)
    padded = np.asarray(jax.jit(pad_faces)(jnp.asarray(faces), cube_lut))
    s = small_rig.width
    assert padded.shape == (5, s + 2, s + 2, 3)
    np.testing.assert_array_equal(padded[:, 1:-1, 1:-1], faces)
    # every ring pixel of the front face (all four neighbours exist) is the function of its own ray
    u = np.arange(-1, s + 1, dtype=np.float64)
    ring_uv = np.concatenate([np.stack([u, np.full_like(u, -1.0)], -1), np.stack([u, np.full_like(u, s)], -1),
                              np.stack([np.full_like(u, -1.0), u], -1), np.stack([np.full_like(u, s), u], -1)])
    rays, _ = small_rig.unproject_faces(jnp.zeros(len(ring_uv), jnp.int32), jnp.asarray(ring_uv))
    expected = smooth_function(np.asarray(rays))
    got = padded[0, ring_uv[:, 1].astype(int) + 1, ring_uv[:, 0].astype(int) + 1]
    corner = np.all((ring_uv < 0) | (ring_uv > s - 1), axis=-1)  # three faces meet: clamped there
    np.testing.assert_allclose(got[~corner], expected[~corner], atol=ANALYTIC_CUBE)
    np.testing.assert_allclose(got[corner], expected[corner], atol=0.02)


def test_label_cube_follows_the_dominant_axis_rule(cube_lut, small_rig, small_fisheye, jit_kernels, jit_unproject):
    s = small_rig.width
    labels = np.broadcast_to(np.arange(5, dtype=np.uint8)[:, None, None], (5, s, s))
    got, valid = jit_kernels["nearest"](jnp.asarray(labels), cube_lut)
    rays, _ = jit_unproject(small_fisheye, small_fisheye.pixel_grid(jnp.float64))
    along = np.asarray(rays) @ np.asarray(small_rig.face_to_camera.rotation_matrix)[:, :, 2].T
    top2 = np.sort(along, axis=-1)[..., -2:]
    away = np.asarray(valid) & (top2[..., 1] - top2[..., 0] > 1e-6)
    np.testing.assert_array_equal(np.asarray(got)[away], np.argmax(along, axis=-1)[away])
    assert set(np.unique(np.asarray(got)[np.asarray(valid)])) <= set(range(5))


@pytest.fixture(scope="module")
def rig256():
    """Five 256-px faces: fine enough that a plane up to 60 deg from its normal keeps the four
    depth taps within 5 % (64-px faces would fall back to nearest there)."""
    return CubeRig(256, dtype=jnp.float64)


@pytest.fixture(scope="module")
def depth_setup(jit_build_lut, rig256, small_fisheye, jit_unproject):
    lut32 = jit_build_lut(rig256, small_fisheye)  # the float32 production path
    rays, rv = jit_unproject(small_fisheye, small_fisheye.pixel_grid(jnp.float64))
    return lut32, face_rays(rig256), np.asarray(rays), np.asarray(rv)


def _plane_depth(rays_f, axes, n, d0):
    with np.errstate(divide="ignore"):
        t = d0 / np.einsum("fhwk,k->fhw", rays_f, n)
    t = np.where(t > 0, t, np.inf)
    return np.minimum(t * np.einsum("fhwk,fk->fhw", rays_f, axes), 1000.0).astype(np.float32)


@pytest.mark.parametrize("normal", [(0.0, 0.0, 1.0), (0.3, 0.5, 0.8), (-0.6, 0.1, 0.2)])
def test_depth_of_a_plane_is_the_exact_range(depth_setup, rig256, jit_kernels, normal):
    lut, rays_f, rays, rv = depth_setup
    axes = np.asarray(rig256.face_to_camera.rotation_matrix)[:, :, 2]
    n = np.asarray(normal) / np.linalg.norm(normal)
    d0 = 2.5
    got, valid = jit_kernels["depth"](jnp.asarray(_plane_depth(rays_f, axes, n, d0)), lut)
    got = np.asarray(got)
    with np.errstate(divide="ignore"):
        t = d0 / (rays @ n)
    near = np.asarray(valid) & rv & (t > 0) & (t < 2 * d0)  # within 60 deg of the plane normal
    assert near.sum() > 500
    np.testing.assert_allclose(got[near], t[near], rtol=DEPTH_PLANE_REL_F32)
    sky = np.asarray(valid) & ((t < 0) | (t > 1e4))
    assert np.mean(got[sky] == 1000.0) > 0.95  # sky stays exactly 1000 (but at the horizon line)


def test_depth_sphere_steps_and_far(depth_setup, rig256, jit_kernels):
    """Range of a sphere around the camera; a step between two spheres yields no flying points."""
    lut, rays_f, rays, rv = depth_setup
    axes = np.asarray(rig256.face_to_camera.rotation_matrix)[:, :, 2]
    cosine = np.einsum("fhwk,fk->fhw", rays_f, axes)
    got, valid = jit_kernels["depth"](jnp.asarray((5.0 * cosine).astype(np.float32)), lut)
    np.testing.assert_allclose(np.asarray(got)[np.asarray(valid)], 5.0, rtol=DEPTH_SPHERE_REL_F32)
    radius = np.where(rays_f[..., 0] > 0.2, 2.0, 10.0)  # a step: 2 m to the right, 10 m elsewhere
    radius = np.where(rays_f[..., 1] < -0.5, 2000.0, radius)  # and "sky" above
    z = np.minimum(radius * cosine, 1000.0).astype(np.float32)
    got, valid = jit_kernels["depth"](jnp.asarray(z), lut)
    g = np.asarray(got)[np.asarray(valid)]
    # at the step the nearest tap is used: its range is off by < 1 % (half a face pixel), never in between
    ok = np.isclose(g, 2.0, rtol=0.01) | np.isclose(g, 10.0, rtol=0.01) | (g == 1000.0)
    assert ok.all(), np.unique(g[~ok])
    assert (g == 1000.0).sum() > 100 and np.isclose(g, 2.0, rtol=1e-3).sum() > 100


def test_batched_frames_and_cameras(cube_lut, small_rig, jit_kernels):
    """Leading frame axes are kept; vmap over a camera axis of stacked LUTs."""
    rng = np.random.default_rng(3)
    s = small_rig.width
    frames = jnp.asarray(rng.random((2, 5, s, s, 2), dtype=np.float32))
    batched, _ = jit_kernels["bilinear"](frames, cube_lut)
    for i in range(2):
        one, _ = jit_kernels["bilinear"](frames[i], cube_lut)
        np.testing.assert_array_equal(np.asarray(batched[i]), np.asarray(one))
    luts = jax.tree_util.tree_map(lambda x: jnp.stack([x, x]), cube_lut)
    per_cam, valid = jax.jit(jax.vmap(lambda f, l: jit_kernels["bilinear"](f, l)))(frames, luts)
    np.testing.assert_array_equal(np.asarray(per_cam), np.asarray(batched))
    assert valid.shape == (2, 120, 160)
    labels = jnp.asarray(rng.integers(0, 9, (3, 5, s, s), dtype=np.int32))
    lab, _ = jit_kernels["nearest"](labels, cube_lut)
    assert lab.shape == (3, 120, 160) and lab.dtype == jnp.int32
    many = jnp.asarray(rng.integers(0, 9, (10, 5, s, s), dtype=np.uint8))  # > 8 frames: a lax.map loop
    looped, _ = jit_kernels["nearest"](many, cube_lut)
    np.testing.assert_array_equal(np.asarray(looped[9]), np.asarray(jit_kernels["nearest"](many[9], cube_lut)[0]))
    with pytest.raises(ValueError, match="does not match"):
        jit_kernels["bilinear"](frames[..., :40, :, :], cube_lut)


def _sub_lut(lut: Lut, n: int) -> Lut:
    """The n x n samples contained in a 9 x 9 LUT (n = 1 or 3: offsets (3j + 1 + 0.5) / 9 - 0.5 ...)."""
    step = 9 // n
    keep = np.asarray([(step * iy + step // 2) * 9 + step * ix + step // 2 for iy in range(n) for ix in range(n)])
    np.testing.assert_allclose(supersample_offsets(9)[keep], supersample_offsets(n), atol=1e-12)
    fields = {k: getattr(lut, k) for k in ("face", "uv", "valid", "z_to_range", "tap_index", "tap_frac", "nearest_index")}
    fields = {k: v[:, :, keep] for k, v in fields.items()}
    return Lut(**fields, ring_index=lut.ring_index, ring_frac=lut.ring_frac, ring_valid=lut.ring_valid,
               num_faces=lut.num_faces, source_width=lut.source_width, source_height=lut.source_height,
               pad=lut.pad, supersample=n)


@pytest.fixture(scope="module")
def supersampled(jit_build_lut, rig256):
    """A 9 x 9-supersampled LUT to an 80 x 60 fisheye and its 3 x 3 and 1 x 1 sub-LUTs."""
    cam = jf.resize_fisheye(jf.default_rig()["FV"].camera, 80, 60).astype(jnp.float64)
    lut9 = jit_build_lut(rig256, cam, supersample=9)
    return {9: lut9, 3: _sub_lut(lut9, 3), 1: _sub_lut(lut9, 1)}


def test_supersampled_labels_majority_and_centre(supersampled, rig256, jit_kernels):
    s = rig256.width
    labels = jnp.asarray(np.broadcast_to(np.arange(5, dtype=np.uint8)[:, None, None], (5, s, s)))
    lut3, lut1 = supersampled[3], supersampled[1]
    centre, _ = jit_kernels["nearest"](labels, lut3, reduce="centre")
    single, _ = jit_kernels["nearest"](labels, lut1)
    np.testing.assert_array_equal(np.asarray(centre), np.asarray(single))
    # majority vote on a fine label checkerboard (2 x 2-pixel cells, 3 labels): independent count
    yy, xx = np.mgrid[0:s, 0:s]
    board = np.broadcast_to(((xx // 2 + yy // 2) % 3).astype(np.uint8), (5, s, s))
    major, valid = jit_kernels["nearest"](jnp.asarray(board), lut3)
    samples = board.reshape(-1)[np.asarray(lut3.nearest_index)]
    counts = np.stack([((samples == k) & np.asarray(lut3.valid)).sum(-1) for k in range(3)], -1)
    srt = np.sort(counts, -1)
    clear = np.asarray(valid) & (srt[..., -1] > srt[..., -2])
    assert clear.mean() > 0.5
    np.testing.assert_array_equal(np.asarray(major)[clear], np.argmax(counts, axis=-1)[clear])


def test_supersampling_reduces_aliasing(supersampled, rig256, jit_kernels, tmp_path):
    """Stripes of ~2 fisheye pixels period: 3 x 3 supersampling comes much closer than one sample
    per pixel to the box-filtered reference (9 x 9). Writes the figure (1 | 3 | 9 samples)."""
    rays = face_rays(rig256)
    pattern = 0.5 + 0.5 * np.sin(110.0 * np.arctan2(rays[..., 0], rays[..., 2]))
    faces = jnp.asarray(pattern.astype(np.float32)[..., None])
    outs = {}
    for n in (1, 3, 9):
        out, valid = jit_kernels["bilinear"](faces, supersampled[n])
        outs[n] = np.asarray(out)[..., 0]
    v = np.asarray(valid)
    err = {n: float(np.sqrt(np.mean((outs[n] - outs[9])[v] ** 2))) for n in (1, 3)}
    assert err[3] < 0.5 * err[1], err
    figure = np.concatenate([outs[n] for n in (1, 3, 9)], axis=1)
    path = tmp_path / "supersampling.png"
    assert cv2.imwrite(str(path), np.clip(figure * 255, 0, 255).astype(np.uint8))
    assert path.stat().st_size > 1000


def _bilinear_from_padded_faces(faces, lut):
    """Reference: bilinear taps read from `pad_faces` output (the padded layout `Lut.tap_index` addresses)."""
    x = jnp.asarray(faces)
    c, sw = x.shape[-1], lut.source_width + 2
    flat = pad_faces(x, lut).reshape((-1, c))
    idx, fr = lut.tap_index, lut.tap_frac.astype(jnp.float64)
    g = lambda i: flat[i].astype(jnp.float64)  # noqa: E731
    t00, t01, t10, t11 = g(idx), g(idx + 1), g(idx + sw), g(idx + sw + 1)
    top = t00 + (t01 - t00) * fr[..., 0:1]
    val = (top + (t10 + (t11 - t10) * fr[..., 0:1] - top) * fr[..., 1:2])[:, :, 0]
    return jnp.where(lut.pixel_valid[..., None], val, 0.0)


@pytest.mark.parametrize("face_size", [64, 12])
def test_bilinear_border_pixels_equal_the_padded_faces(face_size, jit_build_lut, small_fisheye, jit_kernels):
    """The unpadded fast path (border pixels recomputed from the ring) equals reading padded faces;
    12-px faces overflow the border capacity and take the padded path; a hand-built LUT without the
    border list computes it per call."""
    lut = jit_build_lut(CubeRig(face_size, dtype=jnp.float64), small_fisheye, dtype=jnp.float64)
    n_border = int(jnp.sum(lut.border_pixel < lut.pixel_valid.size))
    assert bool(lut.border_fits) == (face_size == 64) and n_border > 0
    faces = np.random.default_rng(3).uniform(0, 1, (5, face_size, face_size, 2))
    ref = np.asarray(jax.jit(_bilinear_from_padded_faces)(faces, lut))
    got, _ = jit_kernels["bilinear"](faces, lut)
    np.testing.assert_allclose(np.asarray(got), ref, rtol=0, atol=1e-12)
    bare = eqx.tree_at(lambda t: (t.border_pixel, t.border_fits), lut, (None, None), is_leaf=lambda v: v is None)
    got_bare, _ = jit_kernels["bilinear"](faces, bare)
    np.testing.assert_array_equal(np.asarray(got_bare), np.asarray(got))


def test_empty_channels_and_frames_give_empty_results(cube_lut, small_rig):
    from jaxfish.reprojection import resample_depth, resample_nearest

    from .conftest import FACE_SIZE, FISHEYE_H, FISHEYE_W

    s, f = FACE_SIZE, len(small_rig.faces)
    out, valid = resample_bilinear(np.zeros((f, s, s, 0), np.uint8), cube_lut)
    assert out.shape == (FISHEYE_H, FISHEYE_W, 0) and out.dtype == np.uint8 and valid.shape == (FISHEYE_H, FISHEYE_W)
    out, _ = resample_bilinear(np.zeros((0, f, s, s, 3), np.float32), cube_lut)
    assert out.shape == (0, FISHEYE_H, FISHEYE_W, 3)
    out, _ = resample_nearest(np.zeros((f, s, s, 0), np.int32), cube_lut)
    assert out.shape == (FISHEYE_H, FISHEYE_W, 0)
    out, _ = resample_nearest(np.zeros((0, f, s, s), np.uint8), cube_lut)
    assert out.shape == (0, FISHEYE_H, FISHEYE_W)
    out, valid = resample_depth(np.zeros((0, f, s, s), np.float32), cube_lut)
    assert out.shape == (0, FISHEYE_H, FISHEYE_W) and valid.shape == (FISHEYE_H, FISHEYE_W)
    assert pad_faces(np.zeros((f, s, s, 0), np.uint8), cube_lut).shape == (f, s + 2, s + 2, 0)
