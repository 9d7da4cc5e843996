"""The one-way pipeline: sources yield the same `Frame` for the same scene, `sample_truth` is the
one entry point, each stage of a sample runs once, and the in-memory embedded scene writes the
bytes of render -> capture -> build."""

from __future__ import annotations

import json

import equinox as eqx
import jax
import numpy as np
import pytest

import jaxfish.pipeline as jp
from jaxfish.cli._demo import demo_config, demo_rig
from jaxfish.dataset import CaptureSource, EmbeddedSource, build_dataset, clear_worker_cache, rig_constants_of
from tests.dataset.small_capture import FRAMES, SCALE, SEED
from tests.helpers import tree_bytes


def _embedded() -> EmbeddedSource:
    return EmbeddedSource(demo_rig(SCALE), frames=FRAMES, seed=SEED, config=demo_config(SCALE))


def _leaves_equal(a, b) -> None:
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    assert ta == tb
    for x, y in zip(la, lb, strict=True):
        x, y = np.asarray(x), np.asarray(y)
        assert x.dtype == y.dtype and x.shape == y.shape
        np.testing.assert_array_equal(x, y)


def test_the_embedded_scene_in_memory_is_the_frame_its_capture_decodes_to(small_capture):
    """Array for array (CARLA quantisation, calibrations through their JSON, actor and ego records),
    the in-memory source gives the pipeline what decoding the rendered capture gives."""
    captured, embedded = CaptureSource(small_capture), _embedded()
    assert captured.cameras == embedded.cameras and captured.faces == embedded.faces
    assert captured.face_size == embedded.face_size and captured.describe() == embedded.describe()
    for cam in captured.cameras:
        assert captured.calibration_bytes(cam) == embedded.calibration_bytes(cam)
    fp_c, fp_e = captured.fingerprint(), embedded.fingerprint()
    assert {k: v for k, v in fp_c.items() if k.startswith("calibration/")} == \
        {k: v for k, v in fp_e.items() if k.startswith("calibration/")}
    a, b = captured.read(1), embedded.read(1)
    assert a.index == b.index == 1 and a.cameras == b.cameras and a.carla_tags == b.carla_tags
    _leaves_equal(a.camera_frames, b.camera_frames)
    _leaves_equal(a.bev, b.bev)
    assert a.motion.actors == b.motion.actors
    _leaves_equal(a.motion, b.motion)
    assert a.sensors.ego == b.sensors.ego
    _leaves_equal((a.sensors.lidar, a.sensors.semantic_lidar, a.sensors.radar),
                  (b.sensors.lidar, b.sensors.semantic_lidar, b.sensors.radar))
    _leaves_equal(rig_constants_of(captured), rig_constants_of(embedded))


def test_the_embedded_scene_in_memory_writes_the_bytes_of_render_capture_build(small_capture, reference_build,
                                                                              tmp_path):
    """Every sample file is the same; the markers and dataset.json differ only by the source
    fingerprint (a capture's files against the embedded scene's settings)."""
    out = tmp_path / "dataset"
    report = build_dataset(_embedded(), out)
    assert report.ok and report.built == ["00000", "00001"], report.summary()
    ref, got = tree_bytes(reference_build[0]), tree_bytes(out)
    assert sorted(ref) == sorted(got)
    differ = sorted(k for k in ref if ref[k] != got[k])
    assert differ == [".done/00000.json", ".done/00001.json", "dataset.json"], differ
    for rel in differ:
        a, b = json.loads(ref[rel]), json.loads(got[rel])
        assert a.pop("source") != b.pop("source")
        assert a == b
    again = build_dataset(_embedded(), out)  # resumes from the embedded fingerprint
    assert again.ok and again.skipped == ["00000", "00001"] and not again.built
    # Two thread workers share one embedded source (frame 1 from frame 0's renders): the same bytes.
    threads = build_dataset(_embedded(), tmp_path / "threads", workers=2, processes=False)
    assert threads.ok and threads.built == ["00000", "00001"], threads.summary()
    assert tree_bytes(tmp_path / "threads") == got


def test_consecutive_frames_share_their_instant(small_capture):
    """The embedded scene's frame 1 at t-1 is its frame 0 at t: the capture writer's ``*_prev.png``
    files of frame 1 are byte copies of frame 0's ``*_curr.png`` (so that the builder decodes
    them once), and the in-memory source, which keeps frame 0's renders at t for them, reads the
    frame 1 a fresh source renders."""
    frames = small_capture / "frames"
    pairs = [(p, frames / "000001" / p.relative_to(frames / "000000").with_name(p.name.replace("_curr", "_prev")))
             for p in sorted((frames / "000000").rglob("*_curr.png"))]
    assert len(pairs) >= 4 * 5 * 4 + 4  # every face's four images and the BEV's
    for curr, prev in pairs:
        assert prev.read_bytes() == curr.read_bytes(), prev
    in_order = _embedded()
    in_order.read(0)
    after, alone = in_order.read(1), _embedded().read(1)
    _leaves_equal(after.camera_frames, alone.camera_frames)
    _leaves_equal(after.bev, alone.bev)


def test_a_sequence_takes_its_images_at_t_minus_1_from_the_previous_sample(small_capture, monkeypatch):
    """Frame 1 after frame 0 resamples only its faces at t (its faces at t-1 are frame 0's at t,
    byte for byte), plans and labels only its instant t, and gives the bits of frame 1 alone; a
    frame whose faces at t-1 differ from the kept ones, or whose faces are writable, resamples
    both instants, and one whose boxes or ego pose at t-1 differ labels both."""
    from jaxfish.groundtruth import _fisheye, _rig

    pairs: list[int] = []
    plans: list[int] = []
    pair, plan = _rig.fisheye_images_pair, _fisheye._jit_instant_plan
    monkeypatch.setattr(_rig, "fisheye_images_pair", lambda *a: (pairs.append(1), pair(*a))[1])
    monkeypatch.setattr(_fisheye, "_jit_instant_plan", lambda *a: (plans.append(1), plan(*a))[1])
    source = CaptureSource(small_capture)
    constants = rig_constants_of(source)
    cameras = len(constants.cameras)

    def truth(frame):
        pairs.clear()
        plans.clear()
        out = jp.sample_truth(frame, constants)
        return out, len(pairs)

    def arrays(t):
        return [(c.truth, c.z_depth_m, c.depth_rgb, c.semantic_rgb, c.instance_rgb, c.flow_rgb, c.events)
                for c in t.camera_truths()]

    jp.forget_last_images()
    _, resampled = truth(source.read(0))
    assert resampled == cameras
    frame1 = source.read(1)
    after, resampled = truth(frame1)
    planned = len(plans)
    assert resampled == 0  # every camera took its images at t-1 from frame 0
    jp.forget_last_images()
    alone, resampled = truth(frame1)
    assert resampled == cameras
    views = 0 if alone.bev is None else 1  # the BEV top view reuses its images and labels at t-1 too
    assert planned == len(plans) - cameras - views  # and its labels at t-1: each camera plans only t
    _leaves_equal(arrays(after), arrays(alone))
    # The same faces at t-1 with other boxes or another ego pose at t-1: the images are reused,
    # the labels are not.
    moved_boxes = eqx.tree_at(lambda f: f.motion.boxes_prev.box_to_world.translation, frame1,
                              frame1.motion.boxes_prev.box_to_world.translation + np.float32(0.25))
    moved_ego = eqx.tree_at(lambda f: f.motion.vehicle_to_world_prev.translation, frame1,
                            frame1.motion.vehicle_to_world_prev.translation + np.float32(0.25))
    for moved in (moved_boxes, moved_ego):
        jp.forget_last_images()
        truth(source.read(0))
        other, resampled = truth(moved)
        assert resampled == 0 and len(plans) == planned + cameras + views
        jp.forget_last_images()
        _leaves_equal(arrays(other), arrays(truth(moved)[0]))
    _, resampled = truth(source.read(0))  # frame 0's faces at t-1 are not frame 1's at t
    assert resampled == cameras
    jp.forget_last_images()
    pairs.clear()
    batched = jp.sample_truths([source.read(0), frame1], constants)  # in order, as a sequence
    assert len(pairs) == cameras  # frame 0's two instants; frame 1 only its t
    _leaves_equal(arrays(batched[1]), arrays(alone))
    # A frame whose faces at t-1 are frame 1's at t reuses them only when they were kept read-only.
    shifted = eqx.tree_at(lambda f: f.camera_frames, frame1,
                          tuple(eqx.tree_at(lambda c: c.faces_prev, cf, cf.faces) for cf in frame1.camera_frames))
    writable = jax.tree_util.tree_map(np.array, frame1)
    assert writable.camera_frames[0].faces.rgb.flags.writeable
    for kept, expected in ((frame1, 0), (writable, cameras)):
        truth(kept)
        _, resampled = truth(shifted)
        assert resampled == expected


def test_each_stage_of_a_sample_runs_once(small_capture, reference_build, tmp_path, monkeypatch):
    """Following the samples through the builder: each frame's actor records are parsed once, the
    rig's constants are built once per process (LUTs, rays, event maps), the ground truth is one
    `sample_truths` call per sample and the sink writes every file once."""
    from jaxfish.dataset import _build
    from jaxfish.io import CaptureReader

    calls: dict[str, list] = {"actors": [], "ego": [], "constants": [], "truth": [], "files": []}
    actors, ego = CaptureReader.actors, CaptureReader.ego
    monkeypatch.setattr(CaptureReader, "actors", lambda self, f: calls["actors"].append(f) or actors(self, f))
    monkeypatch.setattr(CaptureReader, "ego", lambda self, f: calls["ego"].append(f) or ego(self, f))
    build_constants, truths = _build.rig_constants, _build.sample_truths
    monkeypatch.setattr(_build, "rig_constants", lambda *a, **k: calls["constants"].append(1) or build_constants(*a, **k))
    monkeypatch.setattr(_build, "sample_truths",
                        lambda frames, *a: calls["truth"].append([f.index for f in frames]) or truths(frames, *a))
    hashed = _build.file_digest
    monkeypatch.setattr(_build, "file_digest", lambda p: calls["files"].append(p) or hashed(p))
    clear_worker_cache()
    out = tmp_path / "dataset"
    report = build_dataset(small_capture, out)
    assert report.ok, report.summary()
    assert sorted(calls["actors"]) == [0, 1] and sorted(calls["ego"]) == [0, 1]
    assert calls["constants"] == [1] and calls["truth"] == [[0], [1]]
    listed = {rel for f in (0, 1) for rel in json.loads((out / f".done/0000{f}.json").read_text())["files"]}
    assert len(calls["files"]) == len(set(calls["files"])) == len(listed)  # every sample file written once
    assert {p.relative_to(out).as_posix() for p in calls["files"]} == listed
    assert tree_bytes(out) == tree_bytes(reference_build[0])


def test_sample_truth_is_typed_and_batches_equal_single_frames(small_capture):
    source = CaptureSource(small_capture)
    constants = rig_constants_of(source)
    frames = [source.read(f) for f in source.frames]
    options = jp.GroundTruthOptions(batch="loop")
    one = [jp.sample_truth(f, constants, options) for f in frames]
    both = jp.sample_truths(frames, constants, options)
    for a, b in zip(one, both, strict=True):
        assert a.names == ("FV", "RV", "MVL", "MVR", "BEV") and a.index == b.index
        for ca, cb in zip(a.camera_truths(), b.camera_truths(), strict=True):
            h, w = ca.truth.images.valid.shape
            assert ca.z_depth_m.shape == (h, w) and ca.semantic_rgb.shape == (h, w, 3)
            _leaves_equal((ca.truth.semantic, ca.truth.instances.actor_id, ca.truth.flow, ca.depth_rgb),
                          (cb.truth.semantic, cb.truth.instances.actor_id, cb.truth.flow, cb.depth_rgb))
        assert a.bev is not None and a.bev.view.events is None and a.bev.height_m.shape == a.bev.occupancy.shape
        assert a.corners_vehicle.shape == a.corners_world.shape and a.corners_world.dtype == np.float64
    with pytest.raises(ValueError, match="batch must be"):
        jp.GroundTruthOptions(batch="threads")
    with pytest.raises(ValueError, match="cameras"):
        jp.sample_truth(frames[0], jp.RigConstants(constants.cameras[:2], None, constants.faces, constants.face_size))


def test_events_are_mapped_beside_the_programs_only_with_a_spare_core(small_capture, monkeypatch):
    """A serial build on several cores maps the face events in a thread of its own; thread workers
    on every core, or a process pinned to one core, map them after the programs. The events and
    their renderings are the same either way."""
    import jaxfish.pipeline._truth as truth_module

    monkeypatch.setattr(truth_module, "usable_cores", lambda: 2)
    slots = jp.set_sequence_slots(1)
    try:
        assert truth_module._events_beside_programs()
        jp.set_sequence_slots(2)
        assert not truth_module._events_beside_programs()
        jp.set_sequence_slots(1)
        monkeypatch.setattr(truth_module, "usable_cores", lambda: 1)
        assert not truth_module._events_beside_programs()
    finally:
        jp.set_sequence_slots(slots)
    source = CaptureSource(small_capture)
    constants = rig_constants_of(source)
    frame = source.read(source.frames[0])
    options = jp.GroundTruthOptions(batch="loop", bev=False)
    results = []
    for beside in (True, False):
        monkeypatch.setattr(truth_module, "_events_beside_programs", lambda beside=beside: beside)
        jp.forget_last_images()  # each computes the sample alone
        results.append(jp.sample_truth(frame, constants, options))
    for a, b in zip(*(r.cameras for r in results), strict=True):
        assert a.events is not None and len(a.events) > 0
        assert a.events.tobytes() == b.events.tobytes() and np.array_equal(a.events_rgb, b.events_rgb)
        _leaves_equal((a.truth.semantic, a.truth.flow), (b.truth.semantic, b.truth.flow))


def test_sources_refuse_what_they_do_not_have(small_capture):
    from jaxfish import JaxfishError
    from jaxfish.io import CaptureError

    with pytest.raises(CaptureError, match="frame 5"):
        _embedded().read(5)
    with pytest.raises(JaxfishError, match="frames must be an integer from 1 to"):
        EmbeddedSource(demo_rig(SCALE), frames=0)
    with pytest.raises(CaptureError, match="frame 9"):
        CaptureSource(small_capture).read(9)


def test_the_written_part_of_a_truth_drops_only_what_no_file_is_made_of(small_capture):
    """`written_part` replaces each camera's images and labels at t-1 (but the RGB image) and its
    flow's targets by None and keeps every other array (the same objects); the builder writes
    from it the files of the manifests, backward flows included (tests/dataset/test_build_bytes.py)."""
    from jaxfish.dataset._sink import written_part

    source = CaptureSource(small_capture)
    truth = jp.sample_truth(source.read(1), rig_constants_of(source))
    part = written_part(truth)
    cams = list(zip(truth.camera_truths(), part.camera_truths(), strict=True))
    assert [c.name for c, _ in cams] == [*source.cameras, "BEV"]
    for full, kept in cams:
        g, w = full.truth, kept.truth
        dropped = {"images_prev.range_m": w.images_prev.range_m, "images_prev.tag": w.images_prev.tag,
                   "images_prev.valid": w.images_prev.valid, "semantic_prev": w.semantic_prev,
                   "instances_prev": w.instances_prev, "flow.target_uv": w.flow.target_uv,
                   "flow.target_range_m": w.flow.target_range_m}
        assert all(v is None for v in dropped.values()), [k for k, v in dropped.items() if v is not None]
        for a, b in ((w.images_prev.rgb, g.images_prev.rgb), (w.images.rgb, g.images.rgb),
                     (w.images.range_m, g.images.range_m), (w.instances.actor_id, g.instances.actor_id),
                     (w.flow.flow, g.flow.flow), (w.flow.valid, g.flow.valid), (w.flow.in_image, g.flow.in_image),
                     (w.semantic, g.semantic), (w.motion, g.motion)):
            assert a is b
        assert kept.events is full.events and kept.depth_rgb is full.depth_rgb and kept.flow_rgb is full.flow_rgb
    same = [(p, leaf) for p, leaf in jax.tree_util.tree_flatten_with_path(part)[0]]
    whole = dict(jax.tree_util.tree_flatten_with_path(truth)[0])
    assert all(whole[p] is leaf for p, leaf in same)  # every array kept is the truth's own
    assert part.bev.height_m is truth.bev.height_m and part.index == truth.index and len(same) < len(whole)
