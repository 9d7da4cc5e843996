"""`rig_ground_truth`: every camera (and sample) of a batch equals `fisheye_ground_truth` of that
camera, in loop and vmap mode, stacked or not; shapes and errors."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish as jf
from jaxfish import groundtruth as gt
from jaxfish.reprojection import CubeRig, build_lut, cube_face_size, stack_luts
from jaxfish.scene import generate_street
from jaxfish.transforms import Pose

from ..tolerances import RIG_FLOW_PX_F32, RIG_RANGE_REL_F32
from .conftest import HEIGHT, SEED, WIDTH, _faces, actor_dict

F32 = jnp.float32
CAMERAS = ("FV", "MVL")
FRAMES = (3, 4)


@dataclasses.dataclass(frozen=True)
class Batch:
    luts: list
    cams: list
    c2v: Pose
    faces_prev: object  # (N, C, F, S, S, ...) fields
    faces: object
    boxes_prev: list
    boxes: list
    v2w_prev: list
    v2w: list
    reference: list  # [n][c] fisheye_ground_truth


def _stack_faces(per):  # per[n][c] Faces -> fields (N, C, ...)
    return type(per[0][0])(*(np.stack([np.stack([getattr(f, k) for f in row]) for row in per])
                             for k in ("rgb", "depth_m", "semantic", "actor_id")))


@pytest.fixture(scope="module")
def batch() -> Batch:
    rig = jf.default_rig(width=WIDTH, height=HEIGHT, dtype=F32)
    calibs = [rig[c].astype(F32) for c in CAMERAS]
    cams = [cal.camera.astype(F32) for cal in calibs]
    size = max(cube_face_size(c) for c in cams)
    luts = [jax.jit(build_lut)(CubeRig(size, dtype=F32), c) for c in cams]
    fp, fc, bps, bcs, vps, vcs, ref = [], [], [], [], [], [], []
    for k in FRAMES:
        frame = generate_street(SEED, frame=k, rig=rig)
        actors = [actor_dict(a) for a in frame.actors]
        bps.append(gt.boxes_from_actors(actors, "t-1", pad_to=64))
        bcs.append(gt.boxes_from_actors(actors, "t", pad_to=64))
        e = frame.ego
        vps.append(gt.vehicle_to_world_from_carla(np.asarray(e.location_prev, np.float32), np.asarray(e.rotation_prev, np.float32)))
        vcs.append(gt.vehicle_to_world_from_carla(np.asarray(e.location, np.float32), np.asarray(e.rotation, np.float32)))
        fp.append([_faces(frame, cal, size, 0.0) for cal in calibs])
        fc.append([_faces(frame, cal, size, 1.0) for cal in calibs])
        ref.append([gt.fisheye_ground_truth(luts[j], cams[j], calibs[j].camera_to_vehicle, fp[-1][j], fc[-1][j], bps[-1],
                                            bcs[-1], vps[-1], vcs[-1], backward_flow=True) for j in range(len(CAMERAS))])
    c2v = Pose(np.stack([np.asarray(c.camera_to_vehicle.rotation_matrix, np.float32) for c in calibs]),
               np.stack([np.asarray(c.camera_to_vehicle.translation, np.float32) for c in calibs]))
    return Batch(luts, cams, c2v, _stack_faces(fp), _stack_faces(fc), bps, bcs, vps, vcs, ref)


def _sample(b: Batch, n: int):
    one = lambda f: type(f)(*(None if x is None else x[n] for x in dataclasses.astuple(f)))  # noqa: E731
    return one(b.faces_prev), one(b.faces), b.boxes_prev[n], b.boxes[n], b.v2w_prev[n], b.v2w[n]


def _assert_same(got: gt.CameraGroundTruth, want: gt.CameraGroundTruth):
    flat_g, tree_g = jax.tree_util.tree_flatten_with_path(got)
    flat_w, tree_w = jax.tree_util.tree_flatten_with_path(want)
    assert tree_g == tree_w
    for (path, g), (_, w) in zip(flat_g, flat_w, strict=True):
        g, w, name = np.asarray(g), np.asarray(w), jax.tree_util.keystr(path)
        assert g.shape == w.shape and g.dtype == w.dtype, name
        assert np.all(np.isfinite(g)) if g.dtype.kind == "f" else True, name
        if ".flow" in name and g.dtype.kind == "f":
            tol = RIG_FLOW_PX_F32 if "range" not in name else RIG_RANGE_REL_F32 * 1000.0
            np.testing.assert_allclose(g, w, atol=tol, rtol=0, err_msg=name)
        elif g.dtype.kind == "f":
            np.testing.assert_allclose(g, w, rtol=RIG_RANGE_REL_F32, atol=0, err_msg=name)
        else:
            np.testing.assert_array_equal(g, w, err_msg=name)


@pytest.mark.parametrize("batch_mode", ["loop", "vmap"])
def test_one_sample_equals_each_camera(batch, batch_mode):
    fp, fc, bp, bc, vp, vc = _sample(batch, 0)
    out = gt.rig_ground_truth(batch.luts, batch.cams, batch.c2v, fp, fc, bp, bc, vp, vc, backward_flow=True,
                              batch=batch_mode)
    assert out.images.range_m.shape == (len(CAMERAS), HEIGHT, WIDTH)
    assert out.flow.flow.shape == (len(CAMERAS), HEIGHT, WIDTH, 2)
    for j in range(len(CAMERAS)):
        _assert_same(jax.tree_util.tree_map(lambda x, j=j: x[j], out), batch.reference[0][j])
    assert np.any(np.asarray(out.instances.actor_id) > 0)  # the sample has instances to compare


@pytest.mark.parametrize("batch_mode", ["loop", "vmap"])
def test_per_camera_lists_of_faces_equal_the_stacked_faces(batch, batch_mode):
    """One sample's faces handed over as one array per camera (what the pipeline does: no copy into
    one stack) give each camera's ground truth."""
    fp, fc, bp, bc, vp, vc = _sample(batch, 1)
    listed = lambda f: type(f)(*(None if x is None else list(x) for x in dataclasses.astuple(f)))  # noqa: E731
    rows = gt.rig_ground_truth(batch.luts, batch.cams, batch.c2v, listed(fp), listed(fc), bp, bc, vp, vc,
                               backward_flow=True, batch=batch_mode, stacked=False)
    assert len(rows) == len(CAMERAS)
    for j in range(len(CAMERAS)):
        _assert_same(rows[j], batch.reference[1][j])


def test_batch_of_samples_unstacked_in_loop_mode(batch):
    boxes_prev = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *batch.boxes_prev)
    boxes = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *batch.boxes)
    v2w_p = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *batch.v2w_prev)
    v2w = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *batch.v2w)
    rows = gt.rig_ground_truth(batch.luts, batch.cams, batch.c2v, batch.faces_prev, batch.faces, boxes_prev, boxes,
                               v2w_p, v2w, backward_flow=True, batch="loop", stacked=False)
    assert len(rows) == len(FRAMES) and all(len(r) == len(CAMERAS) for r in rows)
    for n in range(len(FRAMES)):
        for j in range(len(CAMERAS)):
            _assert_same(rows[n][j], batch.reference[n][j])


def test_stacked_luts_and_rays_give_the_same_result(batch):
    fp, fc, bp, bc, vp, vc = _sample(batch, 1)
    cams = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *batch.cams)
    rays = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *[gt.pixel_rays(c) for c in batch.cams])
    out = gt.rig_ground_truth(stack_luts(batch.luts), cams, batch.c2v, fp, fc, bp, bc, vp, vc, rays=rays,
                              backward_flow=True, batch="loop", stacked=False)
    for j in range(len(CAMERAS)):
        _assert_same(out[j], batch.reference[1][j])


def test_known_images_at_t_minus_1_give_the_same_result(batch):
    """``images_prev`` (a sequence's previous images at t): those cameras resample only their faces
    at t, and their ground truth is each camera's; ``faces_prev`` is then not read. With
    ``labels_prev`` they also label only t."""
    fp, fc, bp, bc, vp, vc = _sample(batch, 1)
    known = [batch.reference[1][0].images_prev, None]
    blank = type(fp)(*(None if x is None else np.zeros_like(x) for x in dataclasses.astuple(fp)))
    blank_first = type(fp)(*(None if x is None else np.concatenate([z[:1], x[1:]])
                             for x, z in zip(dataclasses.astuple(fp), dataclasses.astuple(blank), strict=True)))
    rows = gt.rig_ground_truth(batch.luts, batch.cams, batch.c2v, blank_first, fc, bp, bc, vp, vc, backward_flow=True,
                               batch="loop", stacked=False, images_prev=known)
    for j in range(len(CAMERAS)):
        _assert_same(rows[j], batch.reference[1][j])
    for mode, faces_prev, faces in (("vmap", fp, fc), ("loop", batch.faces_prev, batch.faces)):  # vmap; two samples
        with pytest.raises(ValueError, match="images_prev needs batch='loop' and one sample"):
            gt.rig_ground_truth(batch.luts, batch.cams, batch.c2v, faces_prev, faces, bp, bc, vp, vc, batch=mode,
                                images_prev=known)
    with pytest.raises(ValueError, match="one entry per camera"):
        gt.rig_ground_truth(batch.luts, batch.cams, batch.c2v, fp, fc, bp, bc, vp, vc, batch="loop", images_prev=known[:1])
    # With its labels at t-1 too, the camera plans and labels only t, for the same result.
    ref = batch.reference[1][0]
    labels = [(ref.instances_prev, ref.semantic_prev), None]
    rows = gt.rig_ground_truth(batch.luts, batch.cams, batch.c2v, blank_first, fc, bp, bc, vp, vc, backward_flow=True,
                               batch="loop", stacked=False, images_prev=known, labels_prev=labels)
    for j in range(len(CAMERAS)):
        _assert_same(rows[j], batch.reference[1][j])
    with pytest.raises(ValueError, match="labels_prev needs images_prev"):
        gt.rig_ground_truth(batch.luts, batch.cams, batch.c2v, fp, fc, bp, bc, vp, vc, batch="loop",
                            images_prev=[None, None], labels_prev=labels)


def test_errors_name_the_argument(batch):
    fp, fc, bp, bc, vp, vc = _sample(batch, 0)
    with pytest.raises(ValueError, match="entries in .luts. for 2 cameras"):
        gt.rig_ground_truth(batch.luts[:1], batch.cams, batch.c2v, fp, fc, bp, bc, vp, vc, batch="loop")
    with pytest.raises(ValueError, match="'luts' must be stacked over the 2 cameras"):
        gt.rig_ground_truth(stack_luts(batch.luts[:1]), batch.cams, batch.c2v, fp, fc, bp, bc, vp, vc, batch="loop")
    with pytest.raises(ValueError, match="batch must be"):
        gt.rig_ground_truth(batch.luts, batch.cams, batch.c2v, fp, fc, bp, bc, vp, vc, batch="threads")
    with pytest.raises(ValueError, match="faces_prev"):
        gt.rig_ground_truth(batch.luts, batch.cams, batch.c2v, object(), fc, bp, bc, vp, vc)
    ragged = type(fc)(*(None if x is None else [x[0], x[1][:-1]] for x in dataclasses.astuple(fc)))
    with pytest.raises(ValueError, match="faces.rgb as a list needs one"):
        gt.rig_ground_truth(batch.luts, batch.cams, batch.c2v, fp, ragged, bp, bc, vp, vc, batch="loop")
    with pytest.raises(ValueError, match="samples"):  # one sample of faces, two of boxes
        stacked = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *batch.boxes)
        gt.rig_ground_truth(batch.luts, batch.cams, batch.c2v, batch.faces_prev, batch.faces, stacked, stacked,
                            vp, vc, batch="loop")
