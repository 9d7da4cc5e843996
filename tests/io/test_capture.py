"""The capture layout: write a tiny capture, read every file back, and check it against the scene."""

from __future__ import annotations

import json

import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish as jf
from jaxfish.dataset import synthesize_capture
from jaxfish.io import DVS_EVENT_DTYPE, CaptureError, CaptureReader
from jaxfish.io._capture import face_stacks
from jaxfish.scene import (
    RADAR_DTYPE,
    SEMANTIC_LIDAR_DTYPE,
    CaptureConfig,
    generate_street,
    render_cube_faces,
)
from tests.tolerances import CARLA_DEPTH_QUANTUM_M

FACE = 32


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    rig = {k: v.resize(96, 72).astype(jnp.float32) for k, v in jf.default_rig().items() if k in ("FV", "MVL")}
    config = CaptureConfig(face_size=FACE, bev_size=32, front_width=32, front_height=24, lidar_channels=4,
                           lidar_points_per_channel=64, radar_points=32, dvs_substeps=2)
    root = tmp_path_factory.mktemp("capture")
    steps = []
    synthesize_capture(root, rig, frames=2, seed=5, config=config, progress=steps.append)
    return root, rig, config, steps


def test_layout_and_header(capture):
    root, rig, config, steps = capture
    header = json.loads((root / "capture.json").read_text())
    assert header["frames"] == [0, 1] and header["cameras"] == ["FV", "MVL"] and header["version"] == 1
    assert header["carla_semantic_tags"] == "0.9.10" and header["faces"] == list(config.faces)
    assert len(steps) == 2 * (len(rig) + 3)
    for rel in ("calibration/FV.json", "calibration/MVL.json", "sensors.json", "frames/000001/ego.json",
                "frames/000000/actors.json", "frames/000000/cameras/MVL/top/rgb_prev.png",
                "frames/000000/cameras/FV/bottom/dvs.npy", "frames/000000/bev/height_curr.exr",
                "frames/000000/front/instance_curr.png", "frames/000000/lidar.npy", "frames/000000/radar.npy",
                "frames/000000/semantic_lidar.npy", "frames/000000/imu.json", "frames/000000/gnss.json"):
        assert (root / rel).is_file(), rel


def test_read_back_matches_the_scene(capture):
    root, rig, config, _ = capture
    reader = CaptureReader(root)
    assert reader.frames == [0, 1] and set(reader.rig()) == {"FV", "MVL"}
    frame = generate_street(5, frame=1, rig=reader.rig())
    direct = render_cube_faces(frame, rig["FV"], FACE, time=1.0)
    for face in config.faces:
        img = reader.face(1, "FV", face, "curr")
        b = direct[face]
        np.testing.assert_array_equal(img.semantic, np.asarray(b.semantic))
        np.testing.assert_array_equal(img.actor_id, np.asarray(b.actor_id))
        assert np.max(np.abs(img.depth_m - np.asarray(b.depth_m))) <= CARLA_DEPTH_QUANTUM_M + 1e-6 * 1000
        assert img.rgb.dtype == np.uint8 and img.rgb.shape == (FACE, FACE, 3)
    stack = reader.faces_stack(1, "FV")
    assert stack.depth_m.shape == (len(config.faces), FACE, FACE)
    assert not any(a.flags.writeable for a in (stack.rgb, stack.depth_m, stack.semantic))  # JAX reads them in place
    for i, face in enumerate(config.faces):  # decoded into the stacks: the faces as read one by one
        img = reader.face(1, "FV", face, "curr")
        for k in ("rgb", "depth_m", "semantic", "actor_id"):
            np.testing.assert_array_equal(getattr(stack, k)[i], getattr(img, k))
    actors = reader.actors(1)
    assert [a["id"] for a in actors] == [a.id for a in frame.actors]
    np.testing.assert_allclose(actors[3]["transform"]["location"], frame.actors[3].location)
    np.testing.assert_allclose(reader.ego(1)["transform_prev"]["location"], frame.ego.location_prev)
    assert reader.dvs(0, "FV", "front").dtype == DVS_EVENT_DTYPE
    assert reader.semantic_lidar(0).dtype == SEMANTIC_LIDAR_DTYPE and reader.radar(0).dtype == RADAR_DTYPE
    lidar = reader.lidar(0)
    assert lidar.dtype == np.float32 and lidar.shape[1] == 4
    bev = reader.view(0, "bev")
    assert bev.rgb.shape == (32, 32, 3) and reader.height(0).shape == (32, 32)
    assert np.all(reader.height(0) >= 0.0) and reader.view(0, "front", "prev").rgb.shape == (24, 32, 3)
    assert set(reader.imu(0)) >= {"accelerometer", "gyroscope", "compass"} and "latitude" in reader.gnss(0)
    assert reader.sensors()["bev"]["metres_per_pixel"] == pytest.approx(config.bev_metres_per_pixel)


def test_reader_errors_name_the_file(tmp_path, capture):
    with pytest.raises(CaptureError, match="capture.json"):
        CaptureReader(tmp_path)
    root, *_ = capture
    reader = CaptureReader(root)
    with pytest.raises(CaptureError, match="frame 7"):
        reader.actors(7)
    (tmp_path / "capture.json").write_text('{"format": "other", "version": 1, "frames": [], "cameras": [], "faces": []}')
    with pytest.raises(CaptureError, match="format"):
        CaptureReader(tmp_path)
    with pytest.raises(CaptureError, match="instant"):
        reader.face(0, "FV", "front", "next")


def test_hostile_capture_files_name_the_file_and_field(tmp_path, capture):
    import shutil

    for text, message in (("null", "capture.json: expected a JSON object"),
                          (b"\xff\xfe{", "capture.json: not a UTF-8 text file"),
                          ("[" * 100000, "capture.json: JSON nested too deeply")):
        bad = tmp_path / "bad"
        bad.mkdir(exist_ok=True)
        target = bad / "capture.json"
        target.write_bytes(text) if isinstance(text, bytes) else target.write_text(text)
        with pytest.raises(CaptureError, match=message):
            CaptureReader(bad)
    root, *_ = capture
    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    reader = CaptureReader(copy)
    dvs = copy / "frames" / "000000" / "cameras" / "FV" / "front" / "dvs.npy"
    np.save(dvs, np.zeros((), DVS_EVENT_DTYPE))
    with pytest.raises(CaptureError, match=r"dvs\.npy: expected a 1-D array of events"):
        reader.dvs(0, "FV", "front")
    sensors = json.loads((copy / "sensors.json").read_text())
    sensors["bev"]["width"] = "abc"
    (copy / "sensors.json").write_text(json.dumps(sensors))
    with pytest.raises(CaptureError, match=r"sensors\.json: field 'bev\.width/height'"):
        CaptureReader(copy).view(0, "bev")
    with pytest.raises(CaptureError, match="seed must be an integer"):
        synthesize_capture(tmp_path / "never", {}, seed=-1)
    assert not (tmp_path / "never").exists()  # refused before anything is written


def test_reuse_decoded_prev_images_that_copy_the_previous_curr(tmp_path, capture):
    import shutil

    from jaxfish.io import forget_decoded_images

    root, *_ = capture
    copy = tmp_path / "cap"
    shutil.copytree(root, copy)
    face, view = copy / "frames/000001/cameras/FV/front", copy / "frames/000001/bev"
    for kind in ("rgb", "depth", "semantic"):  # frame 1's t-1 = frame 0's t, as scripts/carla_capture.py writes it
        shutil.copyfile(copy / f"frames/000000/cameras/FV/front/{kind}_curr.png", face / f"{kind}_prev.png")
        shutil.copyfile(copy / f"frames/000000/bev/{kind}_curr.png", view / f"{kind}_prev.png")
    shutil.copyfile(copy / "frames/000000/cameras/FV/left/rgb_prev.png", copy / "frames/000001/cameras/FV/left/rgb_prev.png")
    forget_decoded_images()
    reader, plain = CaptureReader(copy, reuse_decoded=True), CaptureReader(copy)
    curr0, bev0 = reader.face(0, "FV", "front", "curr", actor_ids=False), reader.view(0, "bev", "curr", actor_ids=False)
    left0 = reader.face(0, "FV", "left", "curr", actor_ids=False)
    prev1, bev1 = reader.face(1, "FV", "front", "prev", actor_ids=False), reader.view(1, "bev", "prev", actor_ids=False)
    for k in ("rgb", "depth_m", "semantic"):
        assert getattr(prev1, k) is getattr(curr0, k) and getattr(bev1, k) is getattr(bev0, k)  # not decoded again
        assert not getattr(prev1, k).flags.writeable
        np.testing.assert_array_equal(getattr(prev1, k), getattr(plain.face(1, "FV", "front", "prev"), k))
    # A prev file that is not a copy of the last curr read for its sensor is decoded from its own bytes.
    left1 = reader.face(1, "FV", "left", "prev", actor_ids=False)
    assert left1.rgb is not left0.rgb
    np.testing.assert_array_equal(left1.rgb, plain.face(1, "FV", "left", "prev").rgb)
    np.testing.assert_array_equal(left1.depth_m, plain.face(1, "FV", "left", "prev").depth_m)
    forget_decoded_images()
    assert reader.face(1, "FV", "front", "prev", actor_ids=False).rgb is not curr0.rgb
    # Decoded into given arrays: the arrays returned are views of them, a kept curr image is copied
    # into the arrays a later prev is decoded into, and the caller's arrays stay writable.
    forget_decoded_images()
    out0 = face_stacks(1, FACE)
    curr0 = reader.face(0, "FV", "front", "curr", actor_ids=False, out=tuple(a[0] for a in out0))
    out1 = face_stacks(1, FACE)
    prev1 = reader.face(1, "FV", "front", "prev", actor_ids=False, out=tuple(a[0] for a in out1))
    expected = plain.face(1, "FV", "front", "prev")
    for k, a0, a1 in zip(("rgb", "depth_m", "semantic"), out0, out1, strict=True):
        np.testing.assert_array_equal(a1[0], getattr(expected, k))
        np.testing.assert_array_equal(getattr(prev1, k), getattr(expected, k))
        assert np.shares_memory(getattr(curr0, k), a0) and np.shares_memory(getattr(prev1, k), a1)
        assert a0.flags.writeable
    forget_decoded_images()


def test_faces_stacks_hand_on_the_curr_stacks_that_a_prev_view_copies(tmp_path, capture):
    """With ``reuse_decoded``, a camera whose prev files all copy the curr files of its last
    decoded stacks gets those stacks (the same arrays); one face that is no copy decodes the view."""
    import shutil

    from jaxfish.io import forget_decoded_images

    root, *_ = capture
    copy = tmp_path / "cap"
    shutil.copytree(root, copy)
    reader, plain = CaptureReader(copy, reuse_decoded=True), CaptureReader(copy)
    for cam in ("FV", "MVL"):
        for face in reader.faces:
            for kind in ("rgb", "depth", "semantic"):  # frame 1's t-1 = frame 0's t
                shutil.copyfile(copy / f"frames/000000/cameras/{cam}/{face}/{kind}_curr.png",
                                copy / f"frames/000001/cameras/{cam}/{face}/{kind}_prev.png")
    last = reader.faces[-1]  # MVL: one face's depth is no copy
    shutil.copyfile(copy / f"frames/000001/cameras/MVL/{last}/depth_curr.png", copy / f"frames/000001/cameras/MVL/{last}/depth_prev.png")
    forget_decoded_images()
    views = [("FV", "prev"), ("MVL", "prev"), ("FV", "curr"), ("MVL", "curr")]
    frame0 = reader.faces_stacks(0, views, actor_ids=False)
    for actor_ids in (False, True):
        frame1 = reader.faces_stacks(1, views, actor_ids=actor_ids)
        for cam in ("FV", "MVL"):
            want = plain.faces_stacks(1, [(cam, "prev")])[(cam, "prev")]
            got = frame1[(cam, "prev")]
            for k in ("rgb", "depth_m", "semantic"):
                assert (getattr(got, k) is getattr(frame0[(cam, "curr")], k)) == (cam == "FV")
                assert not getattr(got, k).flags.writeable
                np.testing.assert_array_equal(getattr(got, k), getattr(want, k))
            if actor_ids:
                np.testing.assert_array_equal(got.actor_id, want.actor_id)
            else:
                assert got.actor_id is None
        frame0 = {(c, "curr"): reader.faces_stacks(0, [(c, "curr")], actor_ids=False)[(c, "curr")] for c in ("FV", "MVL")}
    forget_decoded_images()
    assert reader.faces_stacks(1, [("FV", "prev")])[("FV", "prev")].rgb is not frame0[("FV", "curr")].rgb


def _jpeg_over(path):
    """Re-encode an image file as a JPEG under its own (``.png``) name."""
    import os

    import OpenImageIO as oiio

    from jaxfish.io import read_image

    pixels = np.ascontiguousarray(read_image(path)[..., :3])
    jpeg = path.with_name("tmp.jpg")
    out = oiio.ImageOutput.create(str(jpeg))
    out.open(str(jpeg), oiio.ImageSpec(pixels.shape[1], pixels.shape[0], 3, oiio.UINT8))
    out.write_image(pixels)
    out.close()
    os.replace(jpeg, path)


@pytest.mark.parametrize("reuse", [False, True])
def test_label_and_depth_faces_must_be_lossless_pngs_and_regular_files(tmp_path, capture, reuse):
    import os
    import shutil

    from jaxfish import ImageError
    from jaxfish.io import forget_decoded_images

    root, *_ = capture
    copy = tmp_path / "cap"
    shutil.copytree(root, copy)
    face = copy / "frames/000000/cameras/FV/front"
    _jpeg_over(face / "rgb_curr.png")  # RGB may be lossy: it is read
    forget_decoded_images()
    reader = CaptureReader(copy, reuse_decoded=reuse)
    assert reader.face(0, "FV", "front", "curr").rgb.shape == (FACE, FACE, 3)
    for kind in ("semantic", "depth", "instance"):
        shutil.copyfile(face / f"{kind}_prev.png", face / f"{kind}_curr.png.bak")
        _jpeg_over(face / f"{kind}_curr.png")
        with pytest.raises(ImageError, match=rf"{kind}_curr\.png: expected a lossless PNG file, found JPEG data"):
            reader.face(0, "FV", "front", "curr")
        os.replace(face / f"{kind}_curr.png.bak", face / f"{kind}_curr.png")
    (face / "depth_prev.png").unlink()
    os.mkfifo(face / "depth_prev.png")  # reading it would block forever
    with pytest.raises(ImageError, match=r"depth_prev\.png: is a FIFO"):
        reader.face(0, "FV", "front", "prev")
    (face / "dvs.npy").unlink()
    os.mkfifo(face / "dvs.npy")
    with pytest.raises(CaptureError, match=r"dvs\.npy: is a FIFO"):
        reader.dvs(0, "FV", "front")
    forget_decoded_images()


def test_actor_ids_must_fit_the_16_bit_instance_ids(tmp_path, capture):
    import shutil

    root, *_ = capture
    copy = tmp_path / "cap"
    shutil.copytree(root, copy)
    path = copy / "frames/000000/actors.json"
    doc = json.loads(path.read_text())
    for bad in (65536, 70000, 2**70):
        doc["actors"][1]["id"] = bad
        path.write_text(json.dumps(doc))
        with pytest.raises(CaptureError, match=rf"actors\.json: field 'actors\[1\]\.id': actor id {bad} above 65535"):
            CaptureReader(copy).actors(0)
    doc["actors"][1]["id"] = 65535
    path.write_text(json.dumps(doc))
    assert CaptureReader(copy).actors(0)[1]["id"] == 65535
    path.write_text(path.read_text().replace('"location": [', '"location": [' + "1" + "0" * 400 + ", ", 1))
    with pytest.raises(CaptureError, match=r"actors\.json: field 'actors\[0\]\..*location\[0\]': .*401 digits"):
        CaptureReader(copy).actors(0)


def test_face_size_is_bounded(tmp_path, capture):
    import shutil

    root, *_ = capture
    copy = tmp_path / "cap"
    shutil.copytree(root, copy)
    header = json.loads((copy / "capture.json").read_text())
    header["face_size"] = 10**9
    (copy / "capture.json").write_text(json.dumps(header))
    with pytest.raises(CaptureError, match=r"capture\.json: field 'face_size': expected at most 65536 pixels"):
        CaptureReader(copy)


@pytest.mark.parametrize("cores, expected", [(1, 1), (2, 2), (16, 4)])
def test_faces_are_decoded_by_at_most_decode_threads_threads(capture, monkeypatch, cores, expected):
    """The decode pool is as large as the process's cores allow, at most `DECODE_THREADS`; the
    stacks are the same whatever its size."""
    import concurrent.futures

    from jaxfish.io import _capture

    assert _capture.DECODE_THREADS == 4
    sizes = []
    real = concurrent.futures.ThreadPoolExecutor

    class Spy(real):
        def __init__(self, max_workers=None, *args, **kwargs):
            sizes.append(max_workers)
            super().__init__(max_workers, *args, **kwargs)

    monkeypatch.setattr(_capture, "usable_cores", lambda: cores)
    monkeypatch.setattr(concurrent.futures, "ThreadPoolExecutor", Spy)
    reader = CaptureReader(capture[0])
    views = [("FV", "curr"), ("MVL", "prev")]
    stacks = reader.faces_stacks(0, views)
    assert sizes == [expected]
    monkeypatch.setattr(concurrent.futures, "ThreadPoolExecutor", real)
    for view in views:
        want = CaptureReader(capture[0]).faces_stacks(0, [view])[view]
        for field in ("rgb", "depth_m", "semantic", "actor_id"):
            np.testing.assert_array_equal(getattr(stacks[view], field), getattr(want, field))


def test_face_stacks_are_aligned_so_that_jax_takes_them_without_a_copy(capture):
    """A capture's face stacks start at a multiple of `ARRAY_ALIGNMENT` bytes; on the CPU backend
    JAX then reads the array's own memory instead of copying it at every call."""
    import jax

    from jaxfish.io._capture import ARRAY_ALIGNMENT, aligned_empty

    for shape, dtype in (((2, 5, 5, 3), np.uint8), ((3, 7, 7), np.float32), ((1,), np.float64)):
        a = aligned_empty(shape, dtype)
        assert a.shape == shape and a.dtype == dtype and a.flags.c_contiguous and a.flags.writeable
        assert a.ctypes.data % ARRAY_ALIGNMENT == 0
    stacks = CaptureReader(capture[0]).faces_stack(0, "FV")
    for a in (stacks.rgb, stacks.depth_m, stacks.semantic):
        assert a.ctypes.data % ARRAY_ALIGNMENT == 0
        if jax.default_backend() == "cpu":
            assert jax.device_put(a).unsafe_buffer_pointer() == a.ctypes.data


def test_two_sequences_read_at_once_each_get_their_own_kept_stacks(tmp_path, capture):
    """Two sequences (owners, e.g. two threads building samples) reading one capture alternately:
    with a slot each (`set_sequence_slots`), a prev view that copies the curr files one of them
    decoded gets that owner's stacks though the other read since; with one slot it is decoded again."""
    import shutil

    from jaxfish._sequences import acting_for
    from jaxfish.io import forget_decoded_images
    from jaxfish.pipeline import set_sequence_slots

    root, *_ = capture
    copy = tmp_path / "cap"
    shutil.copytree(root, copy)
    reader = CaptureReader(copy, reuse_decoded=True)
    for face in reader.faces:
        for kind in ("rgb", "depth", "semantic"):  # frame 1's t-1 = frame 0's t
            shutil.copyfile(copy / f"frames/000000/cameras/FV/{face}/{kind}_curr.png",
                            copy / f"frames/000001/cameras/FV/{face}/{kind}_prev.png")
    before = set_sequence_slots(2)
    try:
        for slots, kept in ((2, True), (1, False)):
            set_sequence_slots(slots)
            forget_decoded_images()
            with acting_for("a"):
                frame0 = reader.faces_stacks(0, [("FV", "curr")])[("FV", "curr")]
            with acting_for("b"):  # another sequence reads another frame's curr files meanwhile
                reader.faces_stacks(1, [("FV", "curr")])
            with acting_for("a"):
                prev1 = reader.faces_stacks(1, [("FV", "prev")])[("FV", "prev")]
            for k in ("rgb", "depth_m", "semantic"):
                assert (getattr(prev1, k) is getattr(frame0, k)) == kept
                np.testing.assert_array_equal(getattr(prev1, k), getattr(frame0, k))
    finally:
        set_sequence_slots(before)
        forget_decoded_images()


def test_deferred_events_read_the_file_when_converted_and_name_it_when_it_changed(tmp_path, capture):
    import shutil

    from jaxfish.io import DeferredEvents

    root, *_ = capture
    copy = tmp_path / "cap"
    shutil.copytree(root, copy)
    reader = CaptureReader(copy)
    path = copy / "frames/000001/cameras/FV/front/dvs.npy"
    eager = reader.dvs(1, "FV", "front")
    assert eager.size > 0
    deferred = reader.dvs(1, "FV", "front", defer=True)
    assert isinstance(deferred, DeferredEvents) and deferred.path == path
    assert deferred.shape == eager.shape and len(deferred) == eager.size and deferred.dtype == DVS_EVENT_DTYPE
    first, second = np.asarray(deferred), np.asarray(deferred)
    np.testing.assert_array_equal(first, eager)
    assert first.dtype == DVS_EVENT_DTYPE and first is not second and first.flags.writeable
    with pytest.raises(ValueError, match="copy=False"):
        np.asarray(deferred, copy=False)
    # the header's faults are named when the events are deferred, as when they are read
    np.save(path, np.zeros((5, 4), np.float32))
    with pytest.raises(CaptureError, match=r"dvs\.npy: expected dtype"):
        reader.dvs(1, "FV", "front", defer=True)
    np.save(path, np.zeros((2, 2), DVS_EVENT_DTYPE))
    with pytest.raises(CaptureError, match=r"dvs\.npy: expected a 1-D array of events"):
        reader.dvs(1, "FV", "front", defer=True)
    path.write_bytes(b"garbage")
    with pytest.raises(CaptureError, match=r"dvs\.npy: not a readable \.npy array"):
        reader.dvs(1, "FV", "front", defer=True)
    # a file changed after the events were deferred: named when they are read
    np.save(path, eager)
    deferred = reader.dvs(1, "FV", "front", defer=True)
    outside = eager.copy()
    outside["y"][-1] = FACE
    np.save(path, outside)
    with pytest.raises(CaptureError, match=rf"dvs\.npy: field 'y': event at y = {FACE} outside the {FACE}-px face"):
        np.asarray(deferred)
    np.save(path, eager[:-1])
    with pytest.raises(CaptureError, match=rf"dvs\.npy: holds {eager.size - 1} events, {eager.size} when its frame was read"):
        np.asarray(deferred)
    path.unlink()
    with pytest.raises(CaptureError, match=r"dvs\.npy: file missing"):
        np.asarray(deferred)
    # a header the check does not read (version 3.0) is read at once
    with open(path, "wb") as fh:
        np.lib.format.write_array(fh, eager, version=(3, 0))
    read_now = reader.dvs(1, "FV", "front", defer=True)
    assert isinstance(read_now, np.ndarray)
    np.testing.assert_array_equal(read_now, eager)


def test_a_capture_source_defers_its_face_events_and_the_truth_is_the_same(capture):
    from jaxfish.dataset import CaptureSource
    from jaxfish.io import DeferredEvents
    from jaxfish.pipeline import camera_events, rig_constants

    root, *_ = capture
    deferred, loaded = CaptureSource(root).read(1), CaptureSource(root, defer_events=False).read(1)
    assert all(isinstance(e, DeferredEvents) for cf in deferred.camera_frames for e in cf.events)
    assert all(isinstance(e, np.ndarray) for cf in loaded.camera_frames for e in cf.events)
    source = CaptureSource(root)
    constants = rig_constants(source.rig(), faces=source.faces, face_size=source.face_size)
    for k, a, b in zip(constants.cameras, deferred.camera_frames, loaded.camera_frames, strict=True):
        np.testing.assert_array_equal(camera_events(a.events, k.event_table), camera_events(b.events, k.event_table))
