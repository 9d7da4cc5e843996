"""Multi-camera fusion against the analytic scene: ground-pattern cells land exactly where the
documented BEV convention puts them, boxes get their known heights, eager / jit / vmap agree."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxfish import bev
from tests.bev.conftest import BEV_MPP, BOXES, cell_centres, ground_class, pattern_is_uniform
from tests.tolerances import BEV_EAGER_JIT_CELL_FRACTION, BEV_FUSED_HEIGHT_M


@pytest.fixture(scope="module")
def jit_fuse():
    return jax.jit(lambda c, p, r, s, b, bp, ry: bev.fuse_cameras(c, p, r, s, b, bp, rays=ry))


@pytest.fixture(scope="module")
def fused(rig, jit_fuse):
    return jit_fuse(rig.cameras, rig.poses, rig.range_m, rig.semantic, rig.bev_camera, rig.bev_pose, rig.rays)


def _inside_box(x, y, margin):
    inside = np.full(np.shape(x), -1)
    for i, (x0, x1, y0, y1, _, _) in enumerate(BOXES):
        inside = np.where((x > x0 + margin) & (x < x1 - margin) & (y > y0 + margin) & (y < y1 - margin), i, inside)
    return inside


def _near_box(x, y, margin):
    near = np.zeros(np.shape(x), bool)
    for x0, x1, y0, y1, _, _ in BOXES:
        near |= (x > x0 - margin) & (x < x1 + margin) & (y > y0 - margin) & (y < y1 + margin)
    return near


def test_ground_pattern_lands_on_its_exact_cells(rig, jit_fuse):
    f = jit_fuse(rig.cameras, rig.poses, rig.range_ground, rig.semantic_ground, rig.bev_camera, rig.bev_pose, rig.rays)
    x, y = cell_centres()
    sem, obs = np.asarray(f.semantic), np.asarray(f.observed)
    interior = pattern_is_uniform(x, y, BEV_MPP / 2 + 1e-4) & obs
    assert interior.sum() > 0.3 * x.size  # the rig sees most of the 16 m x 16 m grid around the car
    np.testing.assert_array_equal(sem[interior], ground_class(x, y)[interior])
    # a swapped or mirrored axis, or a wrong scale, would disagree on about half of them
    assert np.mean(ground_class(-x, y)[interior] == sem[interior]) < 0.75
    assert np.mean(ground_class(x * 1.1, y * 1.1)[interior] == sem[interior]) < 0.75
    np.testing.assert_array_equal(np.asarray(f.height_m)[obs], 0.0)
    assert not np.asarray(f.occupancy).any()
    assert np.all(sem[~obs] == bev.UNOBSERVED)


def test_boxes_have_their_known_heights(rig, fused):
    x, y = cell_centres()
    h, sem, obs = np.asarray(fused.height_m), np.asarray(fused.semantic), np.asarray(fused.observed)
    inside = _inside_box(x, y, BEV_MPP)
    checked = 0
    for i, (*_, height, cls) in enumerate(BOXES[:-1]):
        cells = (inside == i) & obs
        assert cells.sum() >= 20, f"box {i} barely seen"
        np.testing.assert_allclose(h[cells], height, atol=BEV_FUSED_HEIGHT_M)
        assert np.all(sem[cells] == cls)
        assert np.all(np.asarray(fused.occupancy)[cells] == (height > bev.OCCUPANCY_MIN_HEIGHT_M))
        checked += cells.sum()
    # the tall box: cameras below its top see its near faces, whose top edge is the highest point
    tall = obs & (_inside_box(x, y, -BEV_MPP) == len(BOXES) - 1)
    assert tall.sum() >= 5 and np.max(h[tall]) <= BOXES[-1][4] + BEV_FUSED_HEIGHT_M
    assert np.max(h[tall]) > BOXES[-1][4] - 0.05 and np.all(sem[tall][h[tall] > 0.2] == BOXES[-1][5])
    ground = obs & ~_near_box(x, y, BEV_MPP)
    np.testing.assert_allclose(h[ground], 0.0, atol=BEV_FUSED_HEIGHT_M)
    assert not np.asarray(fused.occupancy)[ground].any() and checked > 100


def test_eager_jit_and_vmap_agree(rig, fused):
    eager = bev.fuse_cameras([c.camera for c in rig.calibs.values()], [c.camera_to_vehicle for c in rig.calibs.values()],
                             rig.range_m, rig.semantic, rig.bev_camera, rig.bev_pose, rays=rig.rays)

    def agree(a, b):  # float32 rounding (eager vs fused multiply-adds) may move a boundary point to the next cell
        differ = (np.asarray(a.semantic) != np.asarray(b.semantic)) | (np.asarray(a.height_m) != np.asarray(b.height_m))
        assert differ.mean() <= BEV_EAGER_JIT_CELL_FRACTION
        np.testing.assert_array_equal(np.asarray(a.observed)[~differ], np.asarray(b.observed)[~differ])

    agree(eager, fused)
    batch = jax.jit(jax.vmap(lambda r, s: bev.fuse_cameras(rig.cameras, rig.poses, r, s, rig.bev_camera, rig.bev_pose,
                                                            rays=rig.rays)))(
        jnp.stack([rig.range_m, rig.range_ground]), jnp.stack([rig.semantic, rig.semantic_ground]))
    agree(jax.tree.map(lambda a: a[0], batch), fused)
    assert batch.semantic.shape == (2, 160, 160) and not np.asarray(batch.occupancy[1]).any()
    assert fused.height_m.dtype == jnp.float32


def test_bad_inputs_raise_clear_errors(rig):
    args = (rig.cameras, rig.poses)
    with pytest.raises(ValueError, match=r"range_m must be \(N=4"):
        bev.fuse_cameras(*args, rig.range_m[:3], rig.semantic[:3], rig.bev_camera, rig.bev_pose, rays=rig.rays)
    with pytest.raises(ValueError, match="semantic must be integer"):
        bev.fuse_cameras(*args, rig.range_m, rig.range_m, rig.bev_camera, rig.bev_pose, rays=rig.rays)
    with pytest.raises(ValueError, match="do not match the cameras' images"):
        bev.fuse_cameras(*args, rig.range_m[:, :10], rig.semantic[:, :10], rig.bev_camera, rig.bev_pose, rays=rig.rays)
    with pytest.raises(ValueError, match="valid must be"):
        bev.fuse_cameras(*args, rig.range_m, rig.semantic, rig.bev_camera, rig.bev_pose, rays=rig.rays,
                         valid=np.ones((4, 2, 2), bool))
    with pytest.raises(ValueError, match="share one model and image size"):
        bev.stack_cameras([rig.calibs["FV"].camera, rig.calibs["RV"].resize(64, 48).camera])


def test_bev_pose_must_look_down_and_single_poses_stack(rig):
    from jaxfish.transforms import Pose

    sideways = Pose(np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]), np.array([1.3, 0.0, 50.0]))
    up = Pose(np.asarray(rig.bev_pose.rotation_matrix, np.float64) * [1.0, -1.0, -1.0], np.asarray(rig.bev_pose.translation))
    for pose in (sideways, up):
        with pytest.raises(ValueError, match="look straight down"):
            bev.fuse_cameras(rig.cameras, rig.poses, rig.range_m, rig.semantic, rig.bev_camera, pose, rays=rig.rays)
        with pytest.raises(ValueError, match="look straight down"):
            bev.ipm_semantics(rig.cameras, rig.poses, rig.semantic, rig.bev_camera, pose)
        for f in (bev.bev_ground_points, bev.bev_pixel_to_vehicle):
            with pytest.raises(ValueError, match="look straight down"):
                f(rig.bev_camera, pose)
    # One unbatched pose is a batch of one camera (not a misleading "range_m must be (N=3, ...)").
    one = bev.stack_poses(rig.calibs["FV"].camera_to_vehicle)
    assert one.rotation_matrix.shape == (1, 3, 3) and one.translation.shape == (1, 3)
    np.testing.assert_allclose(one.rotation_matrix[0], rig.calibs["FV"].camera_to_vehicle.rotation_matrix, atol=1e-7)
    with pytest.raises(ValueError, match=r"range_m must be \(N=1"):
        bev.fuse_cameras(rig.calibs["FV"].camera, rig.calibs["FV"].camera_to_vehicle, rig.range_m, rig.semantic,
                         rig.bev_camera, rig.bev_pose)
