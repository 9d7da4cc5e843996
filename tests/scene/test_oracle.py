"""Oracle mode: direct fisheye rendering, its motion, and the cube -> fisheye pipeline's error."""

from __future__ import annotations

import numpy as np
import pytest

from jaxfish.scene import CARLA_SEMANTIC_TAGS, oracle_errors, render_fisheye
from tests.tolerances import (
    ORACLE_DEPTH_REL_MEDIAN,
    ORACLE_LABEL_AGREEMENT,
    ORACLE_RGB_PSNR_DB,
    SCENE_PLANAR_DEPTH_REL,
    SCENE_ROAD_Z_M,
)


@pytest.fixture(scope="module")
def oracle_fv(street, small_rig):
    return render_fisheye(street, small_rig["FV"])


def test_oracle_road_pixels_lie_on_the_ground(oracle_fv):
    road = np.isin(np.asarray(oracle_fv.semantic), (CARLA_SEMANTIC_TAGS["road"], CARLA_SEMANTIC_TAGS["roadline"]))
    assert road.sum() > 1000
    np.testing.assert_allclose(np.asarray(oracle_fv.point_world)[road][:, 2], 0.0, atol=SCENE_ROAD_Z_M)


def test_oracle_range_and_depth_agree_with_the_lens(oracle_fv, small_rig):
    cam = small_rig["FV"].camera
    rays, valid = cam.unproject(cam.pixel_grid())
    hit = np.asarray(oracle_fv.hit) & np.asarray(valid)
    np.testing.assert_allclose(np.asarray(oracle_fv.depth_m)[hit],
                               (np.asarray(oracle_fv.range_m) * np.asarray(rays[..., 2]))[hit], rtol=SCENE_PLANAR_DEPTH_REL, atol=1e-4)
    assert not np.any(np.asarray(oracle_fv.valid) & ~np.asarray(valid))


def test_oracle_motion_of_static_ground_matches_ego_motion(oracle_fv, street, small_rig):
    # a ground point at t was at the same world place at t-1; seen from the camera at t-1 it moves
    # by the ego displacement: its motion must be towards the image bottom for a front camera
    road = (np.asarray(oracle_fv.object_index) < 0) & np.asarray(oracle_fv.hit) & np.asarray(oracle_fv.motion_valid)
    mv = np.asarray(oracle_fv.motion_px)[road]
    assert road.sum() > 1000 and np.median(mv[:, 1]) > 0.0
    assert np.all(np.isfinite(np.asarray(oracle_fv.motion_px)))


@pytest.mark.parametrize("camera", ["FV", "MVL"])
def test_cube_to_fisheye_error_against_the_oracle(street, small_rig, camera):
    e = oracle_errors(street, small_rig[camera], 64)
    assert e.pixels > 0.9 * 160 * 121
    assert e.depth_rel_median < ORACLE_DEPTH_REL_MEDIAN
    assert e.label_agreement > ORACLE_LABEL_AGREEMENT
    assert e.instance_agreement > ORACLE_LABEL_AGREEMENT
    assert e.rgb_psnr_db > ORACLE_RGB_PSNR_DB
