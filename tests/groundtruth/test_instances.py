"""Instance and motion segmentation: culling is exact against brute force, every instance pixel lies
in its box, CARLA's box bugs, moving vs parked actors, colours stable across frames."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxfish import groundtruth as gt
from tests import tolerances as tol


def _random_boxes(rng, n):
    yaw = rng.uniform(-180, 180, n)
    loc = np.stack([rng.uniform(0, 40, n), rng.uniform(-10, 10, n), np.zeros(n)], -1)
    cls = rng.choice([4, 10, 21], n)
    ext = np.stack([rng.uniform(0.3, 2.5, n), rng.uniform(0.3, 1.2, n), rng.uniform(0.5, 1.5, n)], -1)
    return gt.boxes_from_carla(np.arange(1, n + 1) + 100, cls, loc, np.stack([np.zeros(n), yaw, np.zeros(n)], -1),
                               np.stack([np.zeros(n), np.zeros(n), ext[:, 2]], -1), ext, fix_extents=False, dtype=jnp.float32)


def _brute_force(pts, cls, boxes, margin):
    """All pixels x all boxes in NumPy float64 (the reference the culled kernel must equal)."""
    r = np.asarray(boxes.box_to_world.rotation_matrix, np.float64)
    c = np.asarray(boxes.box_to_world.translation, np.float64)
    h = np.asarray(boxes.half_extent, np.float64)
    bc = np.asarray(boxes.class_id)
    local = np.einsum("bji,nbj->nbi", r, pts.reshape(-1, 1, 3) - c[None])
    inside = np.all(np.abs(local) <= h + margin, axis=-1)
    grp = lambda k: np.where(k == 4, 1, np.where(np.isin(k, [10, 21, 24]), 2, 0))  # noqa: E731
    inside &= (grp(cls.reshape(-1))[:, None] == grp(bc)[None]) & (grp(cls.reshape(-1))[:, None] > 0)
    depth = np.max(np.abs(local) / h, axis=-1)
    best = np.argmin(np.where(inside, depth, np.inf), axis=-1)
    return np.where(inside.any(-1), best, -1).reshape(cls.shape)


def test_culled_assignment_equals_brute_force():
    rng = np.random.default_rng(0)
    boxes = _random_boxes(rng, 40)
    corners = np.asarray(boxes.corners())
    # Points: half inside random boxes, half anywhere; classes random among instance and other classes.
    h, w = 40, 56
    n = h * w
    which = np.sort(rng.integers(0, 40, n))  # neighbouring pixels see the same boxes, as in images
    t = rng.uniform(-1.1, 1.1, (n, 3)) * np.where(rng.random(n) < 0.3, 2.0, 1.0)[:, None]
    r = np.asarray(boxes.box_to_world.rotation_matrix)[which]
    pts = np.einsum("nij,nj->ni", r, t * np.asarray(boxes.half_extent)[which]) + np.asarray(boxes.box_to_world.translation)[which]
    far = rng.uniform(corners.min((0, 1)), corners.max((0, 1)), (n, 3))
    pts = np.where(rng.random(n)[:, None] < 0.95, pts, far).reshape(h, w, 3).astype(np.float32)
    own = np.asarray(boxes.class_id)[which]
    cls = np.where(rng.random(n) < 0.8, own, rng.choice([4, 10, 21, 7, 0], n)).reshape(h, w)
    out = gt.instance_segmentation(jnp.asarray(pts), jnp.asarray(cls), boxes, margin_m=0.0, fallback_m=0.0, tile=8)
    want = _brute_force(pts.astype(np.float64), cls, boxes, 0.0)
    got = np.asarray(out.box_index)
    agree = got == want
    # float32 kernel vs float64 reference: only points within rounding of a face may differ.
    assert agree.mean() > 0.999, agree.mean()
    assert (want >= 0).sum() > 800
    # Testing every tile in place (capacity 0) gives the same labels as the busy-tile gather.
    dense = gt.instance_segmentation(jnp.asarray(pts), jnp.asarray(cls), boxes, margin_m=0.0, fallback_m=0.0, tile=8, capacity=0)
    np.testing.assert_array_equal(np.asarray(dense.box_index), got)


def test_fallback_and_unassigned_pixels():
    boxes = gt.boxes_from_carla([7], [10], [[0.0, 0.0, 0.0]], [[0.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]], [[2.0, 1.0, 1.0]],
                                fix_extents=False)
    pts = jnp.asarray([[[0.0, 0.0, 1.0], [2.2, 0.0, 1.0], [3.0, 0.0, 1.0], [0.0, 0.0, 1.0]]], jnp.float32)
    cls = jnp.asarray([[10, 10, 10, 7]])
    out = gt.instance_segmentation(pts, cls, boxes, margin_m=0.0, fallback_m=0.3)
    np.testing.assert_array_equal(np.asarray(out.actor_id), [[7, 7, 0, 0]])
    np.testing.assert_array_equal(np.asarray(out.fallback), [[False, True, False, False]])
    np.testing.assert_array_equal(np.asarray(out.unassigned), [[False, False, True, False]])


def test_carla_box_bugs_are_fixed():
    h = gt.fix_carla_extents(np.array([[0.9, 0.0, 0.7], [0.0, 0.0, 0.0], [0.25, 0.25, 0.9], [2.0, 0.9, 0.8]]), np.array([21, 21, 4, 10]))
    fb = np.asarray(gt.TWO_WHEELER_FALLBACK_HALF_EXTENT)
    np.testing.assert_allclose(h[0], [0.9, fb[1], 0.7])
    np.testing.assert_allclose(h[1], fb)
    np.testing.assert_allclose(h[2], np.array([0.25, 0.25, 0.9]) + np.asarray(gt.PEDESTRIAN_PADDING_M))
    np.testing.assert_allclose(h[3], [2.0, 0.9, 0.8])


def test_every_instance_pixel_lies_in_its_box(sample):
    inst = sample.truth.instances
    bi = np.asarray(inst.box_index)
    c2w = gt.camera_to_world(sample.vehicle_to_world, sample.calib.camera_to_vehicle)
    pts, _ = gt.pixel_points(sample.camera, sample.truth.images.range_m)
    world = np.asarray(c2w.apply(pts), np.float64)
    sel = (bi >= 0) & ~np.asarray(inst.fallback)
    assert sel.sum() > 100
    inside = np.asarray(sample.boxes.contains(jnp.asarray(world[sel], jnp.float32), jnp.asarray(bi[sel]), margin_m=gt.BOX_MARGIN_M + 1e-4))
    assert inside.all()


def test_culling_keeps_few_candidates_per_tile(sample):
    c2w = gt.camera_to_world(sample.vehicle_to_world, sample.calib.camera_to_vehicle)
    pts, _ = gt.pixel_points(sample.camera, sample.truth.images.range_m)
    base = gt.carla_to_synwoodscape(sample.truth.images.tag)
    k = gt.max_box_candidates(c2w.apply(pts), base, sample.boxes)
    assert 1 <= k <= sample.boxes.num_boxes // 3


def test_instances_agree_with_the_oracle(sample):
    got = np.asarray(sample.truth.instances.actor_id)
    want = np.asarray(sample.oracle.actor_id)
    ego_id = sample.frame.ego.id
    valid = np.asarray(sample.truth.images.valid)
    sel = valid & (want > 0)
    assert (sel & (want != ego_id)).sum() > 40  # other actors are in view, not only the ego body
    assert np.mean(got[sel] == want[sel]) > tol.INSTANCE_ORACLE_AGREEMENT, np.mean(got[sel] == want[sel])
    assert np.mean(got[valid] == want[valid]) > tol.INSTANCE_ORACLE_AGREEMENT


def test_semantics_split_two_wheelers_and_ego(sample):
    sem = np.asarray(sample.truth.semantic)
    ids = np.asarray(sample.oracle.actor_id)
    by_id = {a.id: a.category for a in sample.frame.actors}
    cat = np.vectorize(lambda i: by_id.get(int(i), ""))(ids)
    tw = (cat == "two_wheeler") & (np.asarray(sample.truth.instances.actor_id) == ids)
    car = (cat == "four_wheeler") & (np.asarray(sample.truth.instances.actor_id) == ids)
    if tw.any():
        assert np.all(sem[tw] == 21)
    assert car.any() and np.all(sem[car] == 10)
    assert set(np.unique(sem)) <= set(range(25))


def test_moving_actors_are_in_the_motion_mask_and_parked_ones_are_not(sample):
    t = sample.truth
    disp = np.asarray(t.displacement_m)
    bi = np.asarray(t.instances.box_index)
    mask = np.asarray(t.motion)
    cls = np.asarray(sample.boxes.class_id)
    visible = [b for b in range(disp.shape[0]) if (bi == b).sum() > 3]
    moving = [b for b in visible if disp[b] > 0.5 and cls[b] != 24]
    parked = [b for b in visible if disp[b] < 1e-6]
    assert moving and parked
    for b in moving:
        assert mask[bi == b].all()
    for b in parked:
        assert not mask[bi == b].any()
    assert not mask[bi < 0].any()
    # Any threshold on request.
    strict = gt.motion_segmentation(jnp.asarray(bi), jnp.asarray(disp), jnp.asarray(cls), threshold_m=float(disp.max()) + 1.0)
    assert not np.asarray(strict).any()


def test_displacements_match_the_actor_transforms(sample):
    for i, a in enumerate(sample.frame.actors):
        if a.category != "ego":
            # Upright actors: the box centre moves like the origin plus the yaw change of its offset.
            assert abs(float(sample.truth.displacement_m[i]) - a.displacement_m) < 0.05 + 0.01 * a.displacement_m


def test_instance_colours_are_stable_and_distinct():
    ids = jnp.arange(100, 400, dtype=jnp.int32)
    a = np.asarray(gt.instance_colors(ids))
    b = np.asarray(gt.instance_colors(ids[::-1]))[::-1]  # another frame, another order
    np.testing.assert_array_equal(a, b)
    assert len({tuple(c) for c in a}) == len(a)
    assert a.min() >= 48
    np.testing.assert_array_equal(np.asarray(gt.instance_colors(jnp.asarray([0]))), [[0, 0, 0]])


def test_colours_stable_across_two_frames(sample):
    from jaxfish.scene import generate_street
    nxt = generate_street(0, frame=4)
    shared = sorted({a.id for a in sample.frame.actors} & {a.id for a in nxt.actors})
    assert len(shared) > 5
    c = np.asarray(gt.instance_colors(jnp.asarray(shared)))
    np.testing.assert_array_equal(c, np.asarray(gt.instance_colors(jnp.asarray(shared))))
