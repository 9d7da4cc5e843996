"""The dense (gather) top view against the analytic scene: it covers every cell a camera sees, it
is exact on flat ground, its depth-consistency test rejects occluded cells, box tops keep their
known heights, eager / jit / vmap agree and bad range values leave no NaN."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxfish import bev
from tests.bev.conftest import BEV_MPP, BOXES, cell_centres, ground_class, pattern_is_uniform, render
from tests.tolerances import BEV_EAGER_JIT_CELL_FRACTION, BEV_FUSED_HEIGHT_M


@pytest.fixture(scope="module")
def jit_dense():
    return jax.jit(lambda c, p, r, s, b, bp, ry, **kw: bev.fuse_cameras_dense(c, p, r, s, b, bp, rays=ry, **kw))


@pytest.fixture(scope="module")
def dense(rig, jit_dense):
    return jit_dense(rig.cameras, rig.poses, rig.range_m, rig.semantic, rig.bev_camera, rig.bev_pose, rig.rays)


@pytest.fixture(scope="module")
def dense_ground(rig, jit_dense):
    return jit_dense(rig.cameras, rig.poses, rig.range_ground, rig.semantic_ground, rig.bev_camera, rig.bev_pose,
                     rig.rays)


def _footprint(calibs, x, y):
    """Ground distance between a cell centre and the ground point of its nearest pixel in the
    camera the fusion reads on flat ground (the nearest camera that sees the cell): half a pixel
    diagonal (0.71 px, i.e. 0.71 / k1 rad, times 2 for the polynomial's slope at large angles)
    stretched by the grazing angle, plus half a cell."""
    g = np.stack([x, y, np.zeros_like(x)], -1)
    best = np.full(np.shape(x), np.inf)
    out = np.full(np.shape(x), np.inf)
    for calib in calibs.values():
        r = np.asarray(calib.camera_to_vehicle.rotation_matrix, np.float64)
        t = np.asarray(calib.camera_to_vehicle.translation, np.float64)
        uv, ok = calib.camera.project(jnp.asarray((g - t) @ r, jnp.float32))
        seen = np.asarray(ok & calib.camera.contains(uv))
        dist = np.linalg.norm(g - t, axis=-1)
        pick = seen & (dist < best)
        best = np.where(pick, dist, best)
        out = np.where(pick, 2.0 * 0.71 / float(calib.camera.k[0]) * dist * dist / t[2], out)
    return out + BEV_MPP / 2


def test_dense_view_covers_what_the_splat_misses(rig, dense_ground, dense):
    splat = bev.fuse_cameras(rig.cameras, rig.poses, rig.range_ground, rig.semantic_ground, rig.bev_camera,
                             rig.bev_pose, rays=rig.rays)
    s_obs, d_obs = np.asarray(splat.observed), np.asarray(dense_ground.observed)
    # the four fisheyes see the whole ground around the car: every cell, where the splat's points
    # thin out with distance and leave holes
    assert d_obs.all() and s_obs.mean() < 0.8
    assert np.all(d_obs[s_obs])
    # with boxes: only their shadows (ground no camera sees) stay unobserved
    boxed = np.asarray(bev.fuse_cameras(rig.cameras, rig.poses, rig.range_m, rig.semantic, rig.bev_camera,
                                        rig.bev_pose, rays=rig.rays).observed)
    assert np.asarray(dense.observed).mean() > 0.9 and boxed.mean() < 0.75
    assert np.all(np.asarray(dense.semantic)[~np.asarray(dense.observed)] == bev.UNOBSERVED)


def test_dense_view_is_exact_on_flat_ground(rig, dense_ground):
    x, y = cell_centres()
    sem, obs = np.asarray(dense_ground.semantic), np.asarray(dense_ground.observed)
    truth = ground_class(x, y)
    margin = _footprint(rig.calibs, x, y)
    sure = np.zeros(x.shape, bool)
    # one class over the cell's sampling footprint (samples <= 0.3 m apart cannot step over a 0.7 m square)
    for r in np.unique(np.ceil(margin[margin < 0.3] * 100)):
        cells = np.ceil(margin * 100) == r
        sure[cells] = pattern_is_uniform(x[cells], y[cells], r / 100 + 1e-4)
    assert sure.mean() > 0.08  # near the cameras (320 x 240 fisheyes: a pixel spans > 0.35 m beyond ~5 m)
    np.testing.assert_array_equal(sem[sure & obs], truth[sure & obs])
    assert np.mean(sem[obs] == truth[obs]) > 0.9  # the rest: cells within a fisheye pixel of a class boundary
    # where a fisheye point landed in the cell, the splat's exact class stays
    splat = bev.fuse_cameras(rig.cameras, rig.poses, rig.range_ground, rig.semantic_ground, rig.bev_camera,
                             rig.bev_pose, rays=rig.rays)
    s_obs = np.asarray(splat.observed)
    np.testing.assert_array_equal(sem[s_obs], np.asarray(splat.semantic)[s_obs])
    np.testing.assert_array_equal(np.asarray(dense_ground.height_m), 0.0)
    assert not np.asarray(dense_ground.occupancy).any()


WALL = (6.0, 6.3, -2.0, 2.0, 1.2, 22)  # a wall across FV's view: the ground behind it is hidden from FV


def test_depth_consistency_rejects_occluded_cells(rig, jit_dense):
    fv = rig.calibs["FV"]
    r = np.asarray(fv.camera_to_vehicle.rotation_matrix, np.float64)
    t = np.asarray(fv.camera_to_vehicle.translation, np.float64)
    ray, ok = (np.asarray(a[0], np.float64) for a in rig.rays)
    rng, cls = render(ray @ r.T, t, (WALL,))
    rng = np.where(ok > 0, rng, 0.0).astype(np.float32)[None]
    sem = np.where(ok > 0, cls, -1).astype(np.int32)[None]
    rays1 = tuple(a[:1] for a in rig.rays)
    args = ([fv.camera], [fv.camera_to_vehicle], rng, sem, rig.bev_camera, rig.bev_pose, rays1)
    out = jit_dense(*args)
    lab, obs = np.asarray(out.semantic), np.asarray(out.observed)
    # the cells whose ground point FV sees behind the wall, more than 0.5 m (and 3 cells) behind it,
    # and more than a pixel (with the cell) inside the wall's silhouette
    x, y = cell_centres()
    g = np.stack([x, y, np.zeros_like(x)], -1)
    e = 2.0 * 0.71 / float(fv.camera.k[0]) * np.linalg.norm(g - t, axis=-1) + BEV_MPP
    hidden = x > WALL[1] + 3 * BEV_MPP
    for dx in (-1.0, 0.0, 1.0):
        for dy in (-1.0, 0.0, 1.0):
            p = g + np.stack([dx * e, dy * e, np.zeros_like(x)], -1)
            dist = np.linalg.norm(p - t, axis=-1)
            hit_range, _ = render((p - t) / dist[..., None], t, (WALL,))
            hidden &= hit_range < dist - 0.5
    assert hidden.sum() > 100
    # neither the ground label of the hidden cell nor the wall's label seen in front of it
    assert np.all(lab[hidden] == bev.UNOBSERVED) and not obs[hidden].any()
    # the same cells in front of the wall stay observed with their ground class
    front = (x < WALL[0] - 3 * BEV_MPP) & (np.abs(y) < 1.0) & (x > t[0] + 1.0) & obs
    assert front.sum() > 50 and np.mean(lab[front] == ground_class(x, y)[front]) > 0.95
    # without a depth test (a tolerance larger than the scene) they take the wall's label: what the test removes
    loose = np.asarray(bev.fuse_cameras_dense(*args[:-1], rays=rays1, range_tolerance=1e3).semantic)
    assert np.mean(loose[hidden] == WALL[5]) > 0.9


def _inside_box(x, y, margin):
    inside = np.full(np.shape(x), -1)
    for i, (x0, x1, y0, y1, _, _) in enumerate(BOXES):
        inside = np.where((x > x0 + margin) & (x < x1 - margin) & (y > y0 + margin) & (y < y1 - margin), i, inside)
    return inside


def test_box_tops_keep_their_known_heights_and_classes(rig, dense):
    x, y = cell_centres()
    h, sem, obs = np.asarray(dense.height_m), np.asarray(dense.semantic), np.asarray(dense.observed)
    inside = _inside_box(x, y, BEV_MPP)
    for i, (*_, height, cls) in enumerate(BOXES[:-1]):  # tops lower than every camera: seen
        cells = inside == i
        assert np.mean(obs[cells]) > 0.9, f"box {i}: top not filled"
        np.testing.assert_allclose(h[cells & obs], height, atol=BEV_FUSED_HEIGHT_M)
        assert np.all(sem[cells & obs] == cls)
        assert np.all(np.asarray(dense.occupancy)[cells & obs] == (height > bev.OCCUPANCY_MIN_HEIGHT_M))
    assert np.all(np.isfinite(h)) and np.all(h[~obs] == 0.0)


def test_eager_jit_vmap_agree_and_bad_ranges_leave_no_nan(rig, dense):
    eager = bev.fuse_cameras_dense([c.camera for c in rig.calibs.values()],
                                   [c.camera_to_vehicle for c in rig.calibs.values()], rig.range_m, rig.semantic,
                                   rig.bev_camera, rig.bev_pose, rays=rig.rays)

    def agree(a, b):
        differ = (np.asarray(a.semantic) != np.asarray(b.semantic)) | (np.asarray(a.height_m) != np.asarray(b.height_m))
        assert differ.mean() <= BEV_EAGER_JIT_CELL_FRACTION
        np.testing.assert_array_equal(np.asarray(a.observed)[~differ], np.asarray(b.observed)[~differ])

    agree(eager, dense)
    batch = jax.jit(jax.vmap(lambda r, s: bev.fuse_cameras_dense(rig.cameras, rig.poses, r, s, rig.bev_camera,
                                                                 rig.bev_pose, rays=rig.rays)))(
        jnp.stack([rig.range_m, rig.range_ground]), jnp.stack([rig.semantic, rig.semantic_ground]))
    agree(jax.tree.map(lambda a: a[0], batch), dense)
    assert batch.semantic.shape == (2, 160, 160) and batch.height_m.dtype == jnp.float32
    # NaN, infinite and negative ranges are no observation: finite output, the rest unchanged
    rng = np.array(rig.range_m)
    rng[:, ::7, ::5] = np.nan
    rng[:, 3::11, ::3] = np.inf
    rng[:, 5::13, 1::4] = -2.0
    bad = bev.fuse_cameras_dense(rig.cameras, rig.poses, rng, rig.semantic, rig.bev_camera, rig.bev_pose, rays=rig.rays)
    assert np.all(np.isfinite(np.asarray(bad.height_m)))
    assert np.asarray(bad.observed).mean() > 0.8


def test_bad_arguments_raise_clear_errors(rig):
    args = (rig.cameras, rig.poses, rig.range_m, rig.semantic, rig.bev_camera, rig.bev_pose)
    with pytest.raises(ValueError, match="fill_radius must be >= 0"):
        bev.fuse_cameras_dense(*args, rays=rig.rays, fill_radius=-1)
    with pytest.raises(ValueError, match="range_tolerance must be >= 0"):
        bev.fuse_cameras_dense(*args, rays=rig.rays, range_tolerance=float("nan"))
    with pytest.raises(ValueError, match=r"range_m must be \(N=4"):
        bev.fuse_cameras_dense(rig.cameras, rig.poses, rig.range_m[:3], rig.semantic[:3], rig.bev_camera,
                               rig.bev_pose, rays=rig.rays)


def test_dense_view_covers_far_more_of_the_small_capture(tmp_path_factory):
    from jaxfish.dataset import CaptureSource, rig_constants_of
    from jaxfish.pipeline import GroundTruthOptions, bev_truth, camera_maps
    from tests.bev.small_capture import shared_bev_capture

    source = CaptureSource(shared_bev_capture(tmp_path_factory))
    frame = source.read(0, sensors=False)
    constants = rig_constants_of(source)
    maps = camera_maps(frame, constants)
    truth = bev_truth(frame, constants, GroundTruthOptions())
    args = (bev.stack_cameras(list(maps.cameras)), bev.stack_poses(list(maps.cameras_to_vehicle)), maps.range_m,
            maps.semantic, truth.camera, truth.camera_to_vehicle)
    splat = bev.fuse_cameras(*args, valid=maps.valid)
    # its ranges are resampled from 16-pixel cube faces: the plane test allows for that step, as jaxfish bev does
    dense = bev.fuse_cameras_dense(*args, valid=maps.valid, height_tolerance_rad=0.6 * maps.range_resolution_rad)
    s_cov, d_cov = float(np.mean(np.asarray(splat.observed))), float(np.mean(np.asarray(dense.observed)))
    assert d_cov > 2 * s_cov and d_cov > 0.5
    t = np.asarray(truth.view.truth.semantic)
    scores = bev.bev_scores(np.asarray(dense.semantic), t, num_classes=25)
    assert float(scores.coverage) == pytest.approx(d_cov)
    assert float(scores.miou_all) <= float(scores.miou_observed)
