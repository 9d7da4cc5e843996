"""Analytic optical flow: closed forms under pure ego motion, the embedded scene's oracle motion,
warping, occlusion, and eager/jit/vmap agreement."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish as jf
from jaxfish import groundtruth as gt
from jaxfish.transforms import Pose
from tests import tolerances as tol

F64 = jnp.float64


_flow = jax.jit(gt.analytic_flow)


def _static_flow(camera, range_m, cam_src, cam_dst, **kw):
    none = Pose(jnp.zeros((0, 3, 3), F64), jnp.zeros((0, 3), F64))
    idx = jnp.full(range_m.shape, -1, jnp.int32)
    return _flow(camera, range_m, idx, none, cam_src, cam_dst, **kw)


def test_pinhole_translation_matches_the_closed_form():
    # Fronto-parallel plane at depth Z; the camera translates by t (its own frame, no rotation):
    # u' = cx + f ((u - cx) Z / f - tx) / (Z - tz), likewise v.
    cam = jf.Pinhole.from_fov(40, 30, 90.0, dtype=F64)
    z, t = 7.0, np.array([0.3, -0.2, 1.1])
    uv = np.asarray(cam.pixel_grid(F64))
    f, cx, cy = float(cam.fx), float(cam.cx), float(cam.cy)
    x, y = (uv[..., 0] - cx) * z / f, (uv[..., 1] - cy) * z / f
    range_m = jnp.asarray(np.sqrt(x * x + y * y + z * z))
    out = _static_flow(cam, range_m, Pose.identity(dtype=F64), Pose(jnp.eye(3, dtype=F64), jnp.asarray(t)))
    u2 = cx + f * (x - t[0]) / (z - t[2])
    v2 = cy + f * (y - t[1]) / (z - t[2])
    want = np.stack([u2, v2], -1) - uv
    inside = (u2 >= -0.5) & (u2 <= 39.5) & (v2 >= -0.5) & (v2 <= 29.5)
    np.testing.assert_array_equal(np.asarray(out.in_image), inside)
    np.testing.assert_allclose(np.asarray(out.flow)[inside], want[inside], atol=tol.FLOW_CLOSED_FORM_PX_F64)


def test_top_view_translation_is_a_uniform_shift():
    # Orthographic top view looking down at the ground from 20 m; the ego moves 0.5 m along the image's
    # -v direction between t-1 and t: every static ground point shifts by +0.5 / mpp pixels in v.
    cam = jf.Orthographic(0.05, width=32, height=24, dtype=F64)
    d = np.array([0.0, -0.5, 0.0])
    out = _static_flow(cam, jnp.full((24, 32), 20.0, F64), Pose.identity(dtype=F64), Pose(jnp.eye(3, dtype=F64), jnp.asarray(d)))
    want = np.broadcast_to(np.array([0.0, 0.5 / 0.05]), (24, 32, 2))
    ok = np.asarray(out.in_image)
    assert ok.sum() == 32 * (24 - 10)
    np.testing.assert_allclose(np.asarray(out.flow)[ok], want[ok], atol=tol.FLOW_CLOSED_FORM_PX_F64)


def test_fisheye_pure_rotation_is_independent_of_depth(jit_project, jit_unproject):
    cam = jf.resize_fisheye(jf.default_rig()["FV"].camera, 48, 36).astype(F64)
    yaw = np.deg2rad(4.0)
    r = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
    dst = Pose(jnp.asarray(r), jnp.zeros(3, F64))
    rng = np.random.default_rng(0)
    a = _static_flow(cam, jnp.asarray(rng.uniform(2, 50, (36, 48))), Pose.identity(dtype=F64), dst)
    b = _static_flow(cam, jnp.full((36, 48), 1000.0, F64), Pose.identity(dtype=F64), dst)
    rays, _ = jit_unproject(cam, cam.pixel_grid(F64))
    uv, _ = jit_project(cam, jnp.einsum("ji,hwj->hwi", jnp.asarray(r), rays))
    want = np.asarray(uv) - np.asarray(cam.pixel_grid(F64))
    ok = np.asarray(a.in_image)
    assert ok.mean() > 0.8
    np.testing.assert_allclose(np.asarray(a.flow)[ok], want[ok], atol=1e-7)
    np.testing.assert_allclose(np.asarray(b.flow)[ok], want[ok], atol=1e-7)


def test_occluded_points_are_not_valid():
    cam = jf.Pinhole.from_fov(16, 12, 90.0, dtype=F64)
    rng = jnp.full((12, 16), 5.0, F64)
    ident = Pose.identity(dtype=F64)
    seen = _static_flow(cam, rng, ident, ident, target_range_m=rng)
    hidden = _static_flow(cam, rng, ident, ident, target_range_m=rng * 0.5)
    assert bool(np.all(np.asarray(seen.valid)))
    assert not bool(np.any(np.asarray(hidden.valid)))
    assert bool(np.all(np.asarray(hidden.in_image)))


def test_actor_points_move_with_their_actor():
    cam = jf.Pinhole.from_fov(16, 12, 90.0, dtype=F64)
    rng = jnp.full((12, 16), 10.0, F64)
    idx = jnp.zeros((12, 16), jnp.int32).at[:, 8:].set(-1)
    ident = Pose.identity(dtype=F64)
    # The actor moves exactly like the camera: its pixels do not move, the static half does.
    move = Pose(jnp.eye(3, dtype=F64)[None], jnp.asarray([[0.4, 0.0, 0.0]]))
    out = _flow(cam, rng, idx, move, ident, Pose(jnp.eye(3, dtype=F64), jnp.asarray([0.4, 0.0, 0.0])))
    f = np.asarray(out.flow)
    np.testing.assert_allclose(f[:, :8], 0.0, atol=1e-9)
    assert np.all(f[:, 8:, 0][np.asarray(out.in_image)[:, 8:]] < -0.3)


def test_jit_vmap_and_loop_agree():
    cam = jf.Pinhole.from_fov(24, 18, 100.0, dtype=F64)
    rng = jnp.asarray(np.random.default_rng(1).uniform(1, 30, (2, 18, 24)))
    idx = (jnp.where(jnp.arange(24)[None, :] < 12, 0, -1) * jnp.ones((18, 1), jnp.int32)).astype(jnp.int32)
    move = Pose(jnp.eye(3, dtype=F64)[None], jnp.asarray([[0.2, 0.1, 0.0]]))
    dst = Pose(jnp.eye(3, dtype=F64), jnp.asarray([0.0, 0.0, 0.3]))
    fn = jax.jit(lambda r: gt.analytic_flow(cam, r, idx, move, Pose.identity(dtype=F64), dst).flow)
    loop = np.stack([np.asarray(fn(rng[i])) for i in range(2)])
    np.testing.assert_allclose(np.asarray(jax.vmap(fn)(rng)), loop, atol=1e-9)
    assert np.all(np.isfinite(loop))
    # Reference: the closed form of a pure z translation for the static right half.
    uv = np.asarray(cam.pixel_grid(F64))
    x = (uv[..., 0] - float(cam.cx)) / float(cam.fx)
    y = (uv[..., 1] - float(cam.cy)) / float(cam.fy)
    z = np.asarray(rng[0]) / np.sqrt(1 + x * x + y * y)
    u2 = float(cam.cx) + float(cam.fx) * x * z / (z - 0.3)
    v2 = float(cam.cy) + float(cam.fy) * y * z / (z - 0.3)
    inside = (u2 >= -0.5) & (u2 <= 23.5) & (v2 >= -0.5) & (v2 <= 17.5)
    inside[:, :12] = False
    assert inside.sum() > 50
    np.testing.assert_allclose(loop[0][..., 0][inside], (u2 - uv[..., 0])[inside], atol=1e-9)


def test_flow_from_the_oracle_geometry_matches_its_motion(sample):
    # Backward flow on the t grid from the oracle's own range and actor ids equals minus its per-pixel
    # motion (the oracle moves points with Scene.move_points, an independent code path).
    o, frame = sample.oracle, sample.frame
    ids = np.asarray(o.actor_id)
    actor_ids = np.asarray(sample.boxes.actor_id)
    lookup = {int(a): i for i, a in enumerate(actor_ids)}
    idx = np.vectorize(lambda a: lookup.get(int(a), -1))(ids).astype(np.int32)
    motion = gt.rigid_motion(sample.boxes.box_to_world, sample.boxes_prev.box_to_world)
    c2w = gt.camera_to_world(sample.vehicle_to_world, sample.calib.camera_to_vehicle)
    c2w_p = gt.camera_to_world(sample.vehicle_to_world_prev, sample.calib.camera_to_vehicle)
    out = _flow(sample.camera, jnp.asarray(o.range_m), jnp.asarray(idx), motion, c2w, c2w_p)
    ok = np.asarray(out.in_image) & np.asarray(o.motion_valid)
    assert ok.mean() > 0.8
    assert frame.ego.displacement_m > 0.5  # the ego moves: this is not a trivial zero flow
    err = np.linalg.norm(np.asarray(out.flow) + np.asarray(o.motion_px), axis=-1)[ok]
    assert err.max() < tol.FLOW_ORACLE_EPE_PX, err.max()
    moving = ok & (idx >= 0) & (np.asarray(sample.truth.displacement_m)[np.clip(idx, 0, None)] > 0.5)
    assert moving.sum() > 10  # moving actors are in view


def test_pipeline_flow_matches_the_oracle(sample):
    bw, o = sample.truth.flow_backward, sample.oracle
    ok = np.asarray(bw.valid) & np.asarray(o.motion_valid)
    err = np.linalg.norm(np.asarray(bw.flow) + np.asarray(o.motion_px), axis=-1)[ok]
    assert ok.mean() > 0.6
    assert np.median(err) < tol.FLOW_PIPELINE_EPE_MEDIAN_PX
    assert np.percentile(err, 90) < tol.FLOW_PIPELINE_EPE_P90_PX


def test_warping_the_current_image_with_forward_flow_gives_the_previous(sample):
    # Forward flow from the exact t-1 render: I_t(p + flow(p)) = I_{t-1}(p) on valid pixels.
    o_p, o = sample.oracle_prev, sample.oracle
    ids = np.asarray(o_p.actor_id)
    lookup = {int(a): i for i, a in enumerate(np.asarray(sample.boxes.actor_id))}
    idx = np.vectorize(lambda a: lookup.get(int(a), -1))(ids).astype(np.int32)
    motion = gt.rigid_motion(sample.boxes_prev.box_to_world, sample.boxes.box_to_world)
    c2w = gt.camera_to_world(sample.vehicle_to_world, sample.calib.camera_to_vehicle)
    c2w_p = gt.camera_to_world(sample.vehicle_to_world_prev, sample.calib.camera_to_vehicle)
    out = _flow(sample.camera, jnp.asarray(o_p.range_m), jnp.asarray(idx), motion, c2w_p, c2w,
                                    target_range_m=jnp.asarray(o.range_m))
    warped = np.asarray(gt.warp_with_flow(jnp.asarray(o.rgb), out.flow))
    ok = np.asarray(out.valid)
    assert ok.mean() > 0.6
    err = np.abs(warped - np.asarray(o_p.rgb)).mean(axis=-1)[ok]
    still = np.abs(np.asarray(o.rgb) - np.asarray(o_p.rgb)).mean(axis=-1)[ok]
    assert err.mean() < tol.FLOW_WARP_RGB_MEAN
    changed = still > 0.05  # pixels whose colour changed between t-1 and t: the flow explains the change
    assert changed.sum() > 50
    assert err[changed].mean() < 0.5 * still[changed].mean()  # the rest: texture aliasing at 128 px


@pytest.mark.parametrize("field", ["flow", "flow_backward"])
def test_pipeline_flow_is_finite_and_zero_where_invalid(sample, field):
    f = getattr(sample.truth, field)
    flow = np.asarray(f.flow)
    assert np.all(np.isfinite(flow))
    assert np.all(flow[~np.asarray(f.in_image)] == 0)
    assert np.all(np.asarray(f.valid) <= np.asarray(f.in_image))
