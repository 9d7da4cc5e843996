"""3D boxes (corner order, frames) and 2D boxes from masks and from box surfaces."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxfish import groundtruth as gt


def test_corners_follow_carla_vertex_order(sample):
    corners = np.asarray(sample.boxes.corners(), np.float64)
    for i, a in enumerate(sample.frame.actors):
        want = a.bbox_corners("t")  # the scene's own corners (CARLA get_world_vertices order)
        ext = np.asarray(gt.fix_carla_extents(np.asarray([a.bbox_extent]), np.asarray([int(sample.boxes.class_id[i])])))[0]
        if np.allclose(ext, a.bbox_extent):
            np.testing.assert_allclose(corners[i], want, atol=1e-3)
    np.testing.assert_array_equal(gt.CORNER_SIGNS[0], [-1, -1, -1])
    np.testing.assert_array_equal(gt.CORNER_SIGNS[5], [1, -1, 1])


def test_vehicle_frame_boxes(sample):
    world = np.asarray(sample.boxes.corners(), np.float64)
    veh = np.asarray(gt.boxes_in_frame(sample.boxes, sample.vehicle_to_world.inverse()), np.float64)
    back = np.asarray(sample.vehicle_to_world.apply(jnp.asarray(veh, jnp.float32)), np.float64)
    np.testing.assert_allclose(back, world, atol=1e-3)
    # The ego's own box, in its ISO vehicle frame, is centred near the origin's x range and symmetric in y.
    ego = veh[0]
    assert abs(ego[:, 1].mean()) < 1e-3


def test_mask_boxes_are_tight():
    bi = -np.ones((10, 12), np.int32)
    bi[2:5, 3:9] = 0
    bi[7, 11] = 2
    b = gt.boxes_from_instances(jnp.asarray(bi), 3)
    np.testing.assert_array_equal(np.asarray(b.xyxy), [[3, 2, 8, 4], [0, 0, 0, 0], [11, 7, 11, 7]])
    np.testing.assert_array_equal(np.asarray(b.present), [True, False, True])
    np.testing.assert_array_equal(np.asarray(b.pixels), [18, 0, 1])


def test_surface_boxes_enclose_the_visible_boxes(sample):
    vis, full = sample.truth.boxes_2d, sample.truth.boxes_2d_full
    # Not the ego: its body is seen from inside its box's extent, and pixels within the fallback
    # distance of a box may lie just outside its projection.
    not_ego = np.asarray(sample.boxes.class_id) != 24
    pv, pf = np.asarray(vis.present) & not_ego, np.asarray(full.present)
    assert pv.sum() >= 3
    assert np.all(pf[pv])
    v, f = np.asarray(vis.xyxy)[pv], np.asarray(full.xyxy)[pv]
    # The full extent (occluded parts included) contains the visible extent, up to a pixel of resampling.
    assert np.all(f[:, :2] <= v[:, :2] + 1) and np.all(f[:, 2:] >= v[:, 2:] - 1)


def test_surface_points_lie_on_the_box_surface(sample):
    pts = gt.box_surface_points(sample.boxes, 5)
    assert pts.shape == (sample.boxes.num_boxes, 6 * 25, 3)
    idx = jnp.broadcast_to(jnp.arange(sample.boxes.num_boxes)[:, None], pts.shape[:2])
    assert bool(jnp.all(sample.boxes.contains(pts, idx, margin_m=1e-3)))
    assert not bool(jnp.any(sample.boxes.contains(pts, idx, margin_m=-1e-3)))
