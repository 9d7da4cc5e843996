"""The BEV grid against the documented convention, height maps, occupancy, IoU against a NumPy loop,
and uniform top-view flow under pure ego translation."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxfish import bev
from jaxfish import groundtruth as gt
from tests.bev.conftest import BEV_MPP, BEV_SIZE, BEV_X0, cell_centres
from tests.tolerances import BEV_FLOW_UNIFORM_PX, BEV_GRID_M

F32 = jnp.float32


def test_pixels_map_to_the_documented_ground_points(rig):
    x, y = cell_centres()
    g = np.asarray(jax.jit(bev.bev_ground_points)(rig.bev_camera, rig.bev_pose))
    np.testing.assert_allclose(g[..., 0], x, atol=BEV_GRID_M)
    np.testing.assert_allclose(g[..., 1], y, atol=BEV_GRID_M)
    np.testing.assert_array_equal(g[..., 2], 0.0)
    a = np.asarray(jax.jit(bev.bev_pixel_to_vehicle)(rig.bev_camera, rig.bev_pose))
    c = (BEV_SIZE - 1) / 2
    np.testing.assert_allclose(a, [[0, -BEV_MPP, BEV_X0 + BEV_MPP * c], [-BEV_MPP, 0, BEV_MPP * c]], atol=BEV_GRID_M)
    uv = np.asarray(jax.jit(bev.vehicle_to_bev_pixels)(rig.bev_camera, rig.bev_pose, g + np.array([0.0, 0.0, 1.7])))
    v, u = np.mgrid[0:BEV_SIZE, 0:BEV_SIZE]
    np.testing.assert_allclose(uv, np.stack([u, v], -1), atol=BEV_GRID_M / BEV_MPP)


def test_height_map_and_occupancy_of_boxes_of_known_height(rig):
    # Depth of the top view (distance below the camera at 50 m): blocks of 0.1, 0.5 and 1.6 m.
    depth = np.full((BEV_SIZE, BEV_SIZE), 50.0, np.float32)
    depth[10:20, 10:30] -= 0.1
    depth[40:60, 40:50] -= 0.5
    depth[100:120, 70:75] -= 1.6
    depth[0, 0] = 1000.0  # sky
    h = np.asarray(jax.jit(bev.height_map)(rig.bev_camera, rig.bev_pose, depth))
    expect = np.zeros_like(depth)
    expect[10:20, 10:30], expect[40:60, 40:50], expect[100:120, 70:75] = 0.1, 0.5, 1.6
    np.testing.assert_allclose(h, expect, atol=BEV_GRID_M)
    occ = np.asarray(jax.jit(bev.occupancy_map)(h))
    np.testing.assert_array_equal(occ, expect > bev.OCCUPANCY_MIN_HEIGHT_M)  # 0.1 m (a speed bump) is free
    obs = np.ones_like(occ)
    obs[45, 45] = False
    assert not np.asarray(jax.jit(bev.occupancy_map)(h, observed=obs))[45, 45]
    rgb = np.asarray(jax.jit(bev.colorize_height)(h))
    assert rgb.dtype == np.uint8 and rgb.shape == (BEV_SIZE, BEV_SIZE, 3)
    assert np.all(rgb[0, 0] == [68, 1, 84]) and np.all(rgb[110, 72] != rgb[0, 0])
    with pytest.raises(ValueError, match="does not match the BEV image"):
        bev.height_map(rig.bev_camera, rig.bev_pose, depth[:10])


def _iou_reference(pred, truth, c):
    out = {}
    for k in range(c):
        inter = np.sum((pred == k) & (truth == k) & (truth >= 0))
        union = np.sum(((pred == k) | (truth == k)) & (truth >= 0))
        if union:
            out[k] = inter / union
    return out


def test_semantic_iou_against_a_loop():
    rng = np.random.default_rng(0)
    truth = rng.integers(-1, 6, (2, 40, 30))
    pred = np.where(rng.random(truth.shape) < 0.7, truth, rng.integers(-1, 7, truth.shape))
    s = jax.jit(lambda p, t: bev.semantic_iou(p, t, num_classes=8))(pred, truth)
    ref = _iou_reference(pred, truth, 8)
    assert sorted(ref) == list(np.nonzero(np.asarray(s.present))[0])  # class 7 is in neither
    for k, v in ref.items():
        assert float(s.iou[k]) == pytest.approx(v, rel=1e-6)
    assert float(s.mean_iou) == pytest.approx(np.mean(list(ref.values())), rel=1e-6)
    perfect = jax.jit(bev.semantic_iou)(truth, truth)
    assert float(perfect.mean_iou) == 1.0
    with pytest.raises(ValueError, match="differ in shape"):
        bev.semantic_iou(pred[0], truth)


def test_top_view_flow_is_uniform_under_pure_ego_translation(rig):
    cam, c2v = rig.bev_camera, rig.bev_pose
    depth = np.full((BEV_SIZE, BEV_SIZE), 50.0, np.float32)
    depth[30:60, 50:90] = 48.5  # a static raised block: orthographic flow ignores height
    view = type("View", (), {"rgb": np.zeros((BEV_SIZE, BEV_SIZE, 3), np.uint8), "depth_m": depth,
                             "semantic": np.full((BEV_SIZE, BEV_SIZE), 7, np.uint8)})
    boxes = gt.boxes_from_actors([], "t")
    yaw = 30.0
    fwd, left = 0.8, -0.3  # ego motion in its own frame between t-1 and t (metres)
    loc0 = np.array([10.0, 5.0, 0.0], np.float32)
    c, s = np.cos(np.radians(yaw)), np.sin(np.radians(yaw))
    # CARLA world (left-handed, y right): forward = (c, s), ISO left = -CARLA right = (s, -c)
    loc1 = loc0 + np.array([fwd * c + left * s, fwd * s - left * c, 0.0], np.float32)
    rot = np.array([0.0, yaw, 0.0], np.float32)
    v2w0, v2w1 = gt.vehicle_to_world_from_carla(loc0, rot), gt.vehicle_to_world_from_carla(loc1, rot)
    truth = gt.view_ground_truth(cam, c2v, view, view, boxes, boxes, v2w0, v2w1)
    flow, valid = np.asarray(truth.flow.flow), np.asarray(truth.flow.valid)
    assert valid.mean() > 0.9
    # static points move by -motion in the vehicle frame: v grows by fwd/m, u by left/m
    np.testing.assert_allclose(flow[valid], np.broadcast_to([left / BEV_MPP, fwd / BEV_MPP], flow[valid].shape),
                               atol=BEV_FLOW_UNIFORM_PX)

