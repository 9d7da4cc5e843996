"""The second ground-truth stage gives the same labels, flow and boxes whatever size statics it
runs with, as long as they reach the plan's counts: padding the candidate count and the tile
capacities changes nothing, which is what lets `ground_truth_from_images` reuse a program compiled
for larger sizes."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from jaxfish.groundtruth import _fisheye as fe


@pytest.fixture(scope="module")
def small_rig_inputs(sample):
    """The second stage's arguments and the plan's own size statics, for the suite's small sample."""
    s = sample
    rays = fe._jit_rays(s.camera)
    fp, fc = s.faces_prev, s.faces
    img_p, img = fe.fisheye_images_pair(s.lut, fp.rgb, fp.depth_m, fp.semantic, fc.rgb, fc.depth_m, fc.semantic)
    c2w_p = fe.camera_to_world(s.vehicle_to_world_prev, s.calib.camera_to_vehicle)
    c2w = fe.camera_to_world(s.vehicle_to_world, s.calib.camera_to_vehicle)
    reach = max(fe.BOX_MARGIN_M, fe.FALLBACK_DISTANCE_M)
    k, busy, many, cands, points = fe._jit_plan(s.camera, rays, img_p, img, c2w_p, c2w, s.boxes_prev, s.boxes, "0.9.10", reach)
    statics = fe.rest_statics("0.9.10", fe.MOTION_THRESHOLD_M, True, fe.BOX_MARGIN_M, fe.FALLBACK_DISTANCE_M, None, 12,
                              int(k), int(busy), int(many))
    return (s.camera, rays, img_p, img, c2w_p, c2w, s.boxes_prev, s.boxes, cands, points), statics


def test_size_variants_choose_dominating_within_factor():
    variants = fe._SizeVariants()
    args = (np.zeros((4, 5), np.float32), np.zeros(3, np.int32))
    base = ("0.9.10", 0.5, False, 0.2, 1.0)
    first = variants.choose(args, base + (4, 128, 64) + (12,))
    assert first[5:8] == (4, 128, 64)
    # Dominated within one power of two: the compiled variant is reused.
    assert variants.choose(args, base + (2, 64, 64) + (12,))[5:8] == (4, 128, 64)
    # More than one power of two smaller in one size: its own variant.
    assert variants.choose(args, base + (1, 64, 64) + (12,))[5:8] == (1, 64, 64)
    # Larger: never a smaller program.
    assert variants.choose(args, base + (8, 128, 64) + (12,))[5:8] == (8, 128, 64)
    # Another signature (shapes or other statics) shares nothing.
    other = (np.zeros((4, 6), np.float32), np.zeros(3, np.int32))
    assert variants.choose(other, base + (2, 64, 64) + (12,))[5:8] == (2, 64, 64)
    assert variants.choose(args, ("0.9.10", 0.5, True, 0.2, 1.0) + (2, 64, 64) + (12,))[5:8] == (2, 64, 64)


def test_padded_sizes_give_identical_truth(small_rig_inputs):
    """`ground_truth_from_plan` with the plan's own sizes and with every size doubled: bit-identical."""
    args, statics = small_rig_inputs
    exact = fe._jit_from_plan(*args, *statics)
    padded = statics[:5] + tuple(2 * v for v in statics[5:8]) + statics[8:]
    wide = fe._jit_from_plan(*args, *padded)
    for a, b in zip(jax.tree_util.tree_leaves(exact), jax.tree_util.tree_leaves(wide), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
