"""Fisheye images and depth from cube faces: range along the fisheye ray (sky 1000), z-depth."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from jaxfish import groundtruth as gt


def test_range_matches_the_oracle_and_sky_is_1000(sample):
    img, o = sample.truth.images, sample.oracle
    v = np.asarray(img.valid) & np.asarray(o.valid)
    r, ro = np.asarray(img.range_m), np.asarray(o.range_m)
    hit = v & (ro < 1000) & (r < 1000)
    rel = np.abs(r - ro)[hit] / ro[hit]
    assert np.median(rel) < 1e-3
    sky = v & (np.asarray(o.semantic) == 13)
    assert sky.sum() > 50
    assert np.mean(r[sky] == 1000.0) > 0.97
    assert np.all(r[np.asarray(img.valid)] > 0)


def test_z_depth_option(sample):
    img = sample.truth.images
    z = np.asarray(gt.range_to_z_depth(sample.camera, img.range_m))
    o = sample.oracle
    v = np.asarray(img.valid) & (np.asarray(o.range_m) < 1000) & (np.asarray(img.range_m) < 1000)
    zo = np.asarray(o.depth_m)
    rel = np.abs(z - zo)[v] / np.maximum(np.abs(zo[v]), 1.0)
    assert np.median(rel) < 1e-3
    assert np.all(z[np.asarray(img.range_m) >= 1000] == 1000)
    zr = np.asarray(gt.range_to_z_depth(sample.camera, img.range_m, rays=gt.pixel_rays(sample.camera, dtype=img.range_m.dtype)))
    np.testing.assert_allclose(zr, z, rtol=1e-6, atol=1e-6)  # precomputed rays: the same depths


def test_semantics_agree_with_the_oracle(sample):
    t = np.asarray(sample.truth.images.tag)
    o = np.asarray(sample.oracle.semantic)
    v = np.asarray(sample.truth.images.valid)
    assert np.mean(t[v] == o[v]) > 0.97
    assert sample.truth.images.rgb.dtype == jnp.uint8


def test_view_ground_truth_on_a_pinhole_view(sample):
    # The front cube face as a directly captured pinhole view: its instances match the renderer's ids.
    import types

    from jaxfish.reprojection import CubeRig

    rig = CubeRig(sample.face_size, dtype=jnp.float32)
    mount = sample.calib.camera_to_vehicle @ rig.face_pose("front")
    view = lambda f: types.SimpleNamespace(rgb=f.rgb[0], depth_m=f.depth_m[0], semantic=f.semantic[0])  # noqa: E731
    t = gt.view_ground_truth(rig.face, mount, view(sample.faces_prev), view(sample.faces), sample.boxes_prev, sample.boxes,
                             sample.vehicle_to_world_prev, sample.vehicle_to_world)
    want = sample.faces.actor_id[0]
    got = np.asarray(t.instances.actor_id)
    sel = want > 0
    assert sel.sum() > 100
    assert np.mean(got[sel] == want[sel]) > 0.98
    assert np.all(np.isfinite(np.asarray(t.flow.flow))) and np.asarray(t.flow.valid).mean() > 0.3  # 0.8 m forward: the near ground leaves a 90-degree view
    sky = np.asarray(sample.faces.semantic[0]) == 13
    assert np.all(np.asarray(t.images.range_m)[sky] == 1000.0)


def test_view_labels_at_t_minus_1_need_their_images():
    with pytest.raises(ValueError, match="labels_prev needs images_prev"):
        gt.view_ground_truth(None, None, None, None, None, None, None, None, labels_prev=(None, None))
