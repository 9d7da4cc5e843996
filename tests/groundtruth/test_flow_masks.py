"""Flow validity and occlusion masks (`FlowField.valid`, `FlowField.occluded`) against the embedded
scene's exact oracle: every t-1 pixel's surface point moved to t with its object and ray cast at t
from the camera towards it (seen when nothing nearer is hit)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxfish import groundtruth as gt
from jaxfish.scene import cast_rays
from jaxfish.transforms import Pose

from .. import tolerances as tol


def _oracle_masks(sample) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(seen at t-1 and inside at t, of those seen at t, of those hidden at t) on the t-1 grid."""
    scene, cam, calib, o = sample.frame.scene, sample.camera, sample.calib, sample.oracle_prev
    mount = Pose(calib.camera_to_vehicle.rotation_matrix, calib.camera_to_vehicle.translation, dtype=jnp.float32)
    pose_t = scene.camera_to_world(mount, 1.0)
    p_t = scene.move_points(o.object_index, o.point_world, 0.0, 1.0)  # the t-1 point where it is at t
    uv, ok = cam.project(pose_t.inverse().apply(p_t))
    uv = np.asarray(uv)
    inside = (np.asarray(o.valid) & np.asarray(ok) & (uv[..., 0] >= -0.5) & (uv[..., 0] <= cam.width - 0.5)
              & (uv[..., 1] >= -0.5) & (uv[..., 1] <= cam.height - 0.5))
    origin = jnp.broadcast_to(pose_t.translation, p_t.shape)
    dist = jnp.linalg.norm(p_t - origin, axis=-1)
    hit = cast_rays(scene, origin, (p_t - origin) / dist[..., None], time=1.0)
    dist, rng, any_hit = np.asarray(dist), np.asarray(hit.range_m), np.asarray(hit.hit)
    # Seen: the ray towards the moved point hits nothing nearer (sky points: the ray hits nothing).
    seen = np.where(np.asarray(o.hit), any_hit & (rng >= dist * (1 - tol.FLOW_MASK_ORACLE_REL)), ~any_hit)
    return inside, inside & seen, inside & ~seen


def test_masks_are_the_flow_fields_validity_and_its_occluded_complement(sample):
    for field in (sample.truth.flow, sample.truth.flow_backward):
        valid, occ, inside = (np.asarray(x) for x in (field.valid, field.occluded, field.in_image))
        assert not np.any(valid & occ)
        assert np.array_equal(valid | occ, inside)
        assert np.array_equal(occ, inside & ~valid)


def test_flow_masks_match_the_exact_oracle(sample):
    inside, seen, hidden = _oracle_masks(sample)
    f = sample.truth.flow  # forward flow on the t-1 grid
    valid, occ = np.asarray(f.valid), np.asarray(f.occluded)
    assert hidden.sum() >= 20, hidden.sum()  # the scene has occlusions to find
    assert seen.mean() > 0.5
    assert np.mean(valid == seen) >= tol.FLOW_MASK_ORACLE_AGREEMENT, np.mean(valid == seen)
    assert np.mean(occ == hidden) >= tol.FLOW_MASK_ORACLE_AGREEMENT, np.mean(occ == hidden)
    # Most of the oracle's hidden pixels are found, and most pixels flagged occluded are hidden.
    both = (occ & hidden).sum()
    assert both / hidden.sum() >= tol.FLOW_OCCLUSION_ORACLE_RECALL, (both, hidden.sum())
    assert both / max(occ.sum(), 1) >= tol.FLOW_OCCLUSION_ORACLE_PRECISION, (both, occ.sum())


def test_without_a_target_range_nothing_is_occluded(sample):
    c2w = gt.camera_to_world(sample.vehicle_to_world, sample.calib.camera_to_vehicle)
    rng = jnp.full((sample.camera.height, sample.camera.width), 10.0, jnp.float32)
    idx = jnp.full(rng.shape, -1, jnp.int32)
    none = Pose(jnp.zeros((0, 3, 3), jnp.float32), jnp.zeros((0, 3), jnp.float32))
    f = gt.analytic_flow(sample.camera, rng, idx, none, c2w, c2w)
    assert not np.any(np.asarray(f.occluded))
    assert np.array_equal(np.asarray(f.valid), np.asarray(f.in_image))
