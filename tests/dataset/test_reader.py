"""`jaxfish.dataset.open`: every field equals its file read independently (NumPy, OpenImageIO,
pickle, json), a hand-made miniature in SynWoodScape's released layout, the sensor extras,
``fields=`` selection, windows, pickling into spawned worker processes, collate, bad files."""

from __future__ import annotations

import io
import json
import multiprocessing
import pickle
import shutil
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest

import jaxfish.dataset as jd
from jaxfish import SYNWOODSCAPE_CORRECTED_TRANSLATIONS_CARLA, JaxfishError
from jaxfish.dataset import _reader
from jaxfish.io import load_calibration, write_events_npy, write_flo, write_image

from ..conftest import shared_path

# ----------------------------------------------------------------------------- independent readers


def oiio_read(path: Path) -> np.ndarray:
    inp = oiio.ImageInput.open(str(path))
    assert inp is not None, oiio.geterror()
    try:
        a = np.asarray(inp.read_image(0, 0, 0, inp.spec().nchannels, oiio.UNKNOWN))
    finally:
        inp.close()
    return a if a.ndim == 3 else a[..., None]


def flo_read(path: Path) -> np.ndarray:
    raw = np.fromfile(path, "<f4")
    w, h = np.frombuffer(raw[1:3].tobytes(), "<i4")
    return raw[3:].reshape(h, w, 2)


def boxes_csv(path: Path) -> list[list]:
    rows = []
    for line in path.read_text().splitlines():
        if line.strip():
            name, *nums = line.split(",")
            rows.append([name, *map(int, nums)])
    return rows


def assert_boxes_2d(b: jd.Boxes2D, path: Path) -> None:
    rows = boxes_csv(path)
    assert list(b.class_name) == [r[0] for r in rows]
    np.testing.assert_array_equal(b.class_id, [r[1] for r in rows])
    np.testing.assert_array_equal(b.xyxy, np.asarray([r[2:] for r in rows]).reshape(-1, 4))


# ----------------------------------------------------------------------------- a jaxfish-built dataset


@pytest.fixture(scope="module")
def built(reference_build):
    return reference_build[0]


def test_every_field_equals_its_file(built):
    ds = jd.open(built)
    manifest = json.loads((built / "dataset.json").read_text())
    assert ds.layout == "jaxfish" == jd.LAYOUT_JAXFISH
    assert ds.samples == tuple(manifest["samples"]) and len(ds) == len(manifest["samples"]) == 2
    assert ds.cameras == tuple(manifest["cameras"])
    assert ds.corrections == ()
    for i, sid in enumerate(ds.samples):
        s = ds[i]
        assert s.id == sid
        veh = dict(line.split(maxsplit=1) for line in (built / f"vehicle_data/rgb_images/{sid}.txt").read_text()
                   .splitlines() if not line.startswith("#"))
        assert s.timestamp_s == pytest.approx(float(veh["timestamp_s"]), abs=1e-9)  # the text file rounds
        prev = dict(line.split(maxsplit=1) for line in (built / f"vehicle_data/previous_images/{sid}.txt").read_text()
                    .splitlines() if not line.startswith("#"))
        assert s.ego.previous_timestamp_s == pytest.approx(float(prev["timestamp_s"]), abs=1e-9)
        # The builder writes the ego state in the ISO vehicle frame (sensor_data); vehicle_data keeps CARLA's.
        sensor = json.loads((built / f"sensor_data/{sid}.json").read_text())
        assert s.timestamp_s == sensor["timestamp_s"]
        for key in ("vehicle_to_world", "velocity_mps", "acceleration_mps2", "angular_velocity_radps"):
            np.testing.assert_array_equal(getattr(s.ego, key), np.asarray(sensor["ego"][key]))
        np.testing.assert_allclose(s.ego.vehicle_to_world[:3, 3], np.fromstring(veh["location_m"], sep=" "), rtol=1e-6)
        np.testing.assert_array_equal(s.lidar, np.load(built / f"lidar_vehicle/{sid}.npy"))
        for cam in ds.cameras:
            c = s.cameras[cam]
            stem = f"{sid}_{cam}"
            np.testing.assert_array_equal(c.rgb, oiio_read(built / f"rgb_images/{stem}.png"))
            np.testing.assert_array_equal(c.rgb_prev, oiio_read(built / f"previous_images/{stem}_prev.png"))
            np.testing.assert_array_equal(c.depth, np.load(built / f"depth_maps/raw_data/{stem}.npy"))
            np.testing.assert_array_equal(c.z_depth, np.load(built / f"depth_maps/z_depth/{stem}.npy"))
            assert c.depth.dtype == np.float32
            np.testing.assert_array_equal(c.semantics, oiio_read(built / f"semantic_annotations/gtLabels/{stem}.png")[..., 0])
            np.testing.assert_array_equal(c.instances, oiio_read(built / f"instance_annotations/gtLabels/{stem}.png")[..., 0])
            np.testing.assert_array_equal(c.motion, oiio_read(built / f"motion_annotations/gtLabels/{stem}.png")[..., 0] == 255)
            np.testing.assert_array_equal(c.flow, flo_read(built / f"optical_flow/raw_data/{stem}.flo"))
            np.testing.assert_array_equal(c.flow_valid, oiio_read(built / f"optical_flow/kitti/{stem}.png")[..., 2] > 0)
            np.testing.assert_array_equal(c.flow_valid, oiio_read(built / f"optical_flow/valid_mask/{stem}.png")[..., 0] == 255)
            np.testing.assert_array_equal(c.flow_occlusion,
                                          oiio_read(built / f"optical_flow/occlusion_mask/{stem}.png")[..., 0] == 255)
            if cam == "BEV":
                assert c.events is None
                cam_model, pose = c.camera, c.pose
                bev = json.loads((built / "calibration_data/BEV.json").read_text())
                assert (cam_model.width, cam_model.height) == (bev["width"], bev["height"])
                np.testing.assert_allclose(np.asarray(pose.translation), bev["camera_to_vehicle"]["translation"],
                                           rtol=1e-6)
            else:
                np.testing.assert_array_equal(c.events, np.load(built / f"dvs_signals/raw_data/{stem}.npy"))
                ref = load_calibration(built / f"calibration_data/{cam}.json")
                np.testing.assert_array_equal(np.asarray(c.camera.k), np.asarray(ref.camera.k))
                np.testing.assert_array_equal(np.asarray(c.pose.as_matrix()), np.asarray(ref.camera_to_vehicle.as_matrix()))
            assert_boxes_2d(c.boxes_2d, built / f"box_2d_annotations/{stem}.txt")
            assert_boxes_2d(c.boxes_2d_full, built / f"box_2d_full_annotations/{stem}.txt")
        ext = json.loads((built / f"box_3d_annotations_ext/{sid}.json").read_text())["boxes"]
        with open(built / f"box_3d_annotations/{sid}.pkl", "rb") as fh:
            pkl = pickle.load(fh)
        b = s.boxes_3d
        np.testing.assert_array_equal(b.actor_id, [r["actor_id"] for r in ext])
        assert sorted(pkl) == list(b.actor_id)
        np.testing.assert_array_equal(b.class_id, [r["class_id"] for r in ext])
        assert b.class_name == tuple(r["class_name"] for r in ext)
        np.testing.assert_array_equal(b.corners_vehicle, [r["corners_vehicle"] for r in ext])
        np.testing.assert_array_equal(b.corners_world, [r["corners_world"] for r in ext])
        np.testing.assert_allclose(b.corners_world, np.stack([pkl[k] for k in sorted(pkl)]), atol=1e-6)
        bev_cal = json.loads((built / "calibration_data/BEV.json").read_text())
        np.testing.assert_array_equal(s.bev.height, np.load(built / f"bev_height/raw_data/{sid}_BEV.npy"))
        np.testing.assert_array_equal(s.bev.occupancy, oiio_read(built / f"bev_occupancy/{sid}_BEV.png")[..., 0] == 255)
        np.testing.assert_array_equal(s.bev.semantics, s.cameras["BEV"].semantics)
        assert s.bev.metres_per_pixel == bev_cal["metres_per_pixel"]
        np.testing.assert_array_equal(s.bev.pixel_to_vehicle_xy, bev_cal["pixel_to_vehicle_xy"])
        # The builder writes every sensor in the ISO vehicle frame beside the raw pickle; the reader takes those.
        np.testing.assert_array_equal(s.lidar, np.load(built / f"lidar_vehicle/{sid}.npy"))
        assert s.lidar_frame == jd.LIDAR_FRAME_VEHICLE
        semantic = np.load(built / f"semantic_lidar_vehicle/{sid}.npy")
        assert s.semantic_lidar.dtype == jd.SEMANTIC_LIDAR_DTYPE
        for name in jd.SEMANTIC_LIDAR_DTYPE.names:
            np.testing.assert_array_equal(s.semantic_lidar[name], semantic[name])
        np.testing.assert_array_equal(s.radar, np.load(built / f"radar_data/{sid}.npy"))
        for record, key in ((s.imu, "imu"), (s.gnss, "gnss")):
            assert (record is None) == (sensor[key] is None)


def test_ego_of_vehicle_data_maps_vehicle_corners_to_world_corners(built):
    """The ego pose read from vehicle_data (CARLA location / rotation) takes the ext file's
    vehicle-frame box corners to its world corners (6 decimals in the JSON)."""
    ds = jd.open(built, fields={"boxes_3d", "ego"}, cameras=[])
    for s in ds:
        m, b = s.ego.vehicle_to_world, s.boxes_3d
        assert len(b.actor_id) > 0
        np.testing.assert_allclose(b.corners_vehicle @ m[:3, :3].T + m[:3, 3], b.corners_world, atol=1e-4)


def test_vehicle_to_world_matrix_matches_the_core():
    from jaxfish.groundtruth import vehicle_to_world_from_carla

    loc, rot = np.array([3.0, -2.0, 0.5]), np.array([4.0, 120.0, -7.0])
    want = np.asarray(vehicle_to_world_from_carla(loc, rot, dtype=np.float64).as_matrix())
    np.testing.assert_allclose(jd.vehicle_to_world_matrix(loc, rot), want, atol=1e-12)


def test_indexing_slicing_and_field_validation(built):
    ds = jd.open(built, fields={"semantics"}, cameras=["FV"])
    assert ds.cameras == ("FV",)
    assert ds[-1].id == ds.samples[-1] and ds[-2].id == ds.samples[0]
    view = ds[1:]
    assert isinstance(view, jd.SynWoodScapeDataset) and view.samples == ds.samples[1:] and len(view) == 1
    assert view[0].id == ds.samples[1]
    assert len(ds[::-1]) == 2 and ds[::-1][0].id == ds.samples[-1]
    with pytest.raises(IndexError):
        ds[2]
    with pytest.raises(IndexError):
        ds[-3]
    with pytest.raises(TypeError):
        ds["00000"]
    s = ds[0]
    assert list(s.cameras) == ["FV"]
    c = s.cameras["FV"]
    assert c.semantics is not None and c.rgb is None and c.camera is None and s.boxes_3d is None
    assert s.lidar is None and s.timestamp_s is None and s.bev is None
    with pytest.raises(ValueError, match="unknown field.*'rbg'"):
        jd.open(built, fields={"rbg"})
    with pytest.raises(TypeError):
        jd.open(built, fields="rgb")
    with pytest.raises(ValueError, match="camera"):
        jd.open(built, cameras=["XX"])


def test_fields_selection_reads_nothing_else(built, monkeypatch):
    opened: list[str] = []

    def spy(fn):
        def wrapped(path, *args, **kwargs):
            opened.append(Path(path).relative_to(built).as_posix())
            return fn(path, *args, **kwargs)
        return wrapped

    for name in ("read_image", "read_flo", "read_events_npy", "read_boxes_2d_csv", "load_npy", "_pickle", "_json",
                 "_vehicle_text", "load_bev_calibration"):
        monkeypatch.setattr(_reader, name, spy(getattr(_reader, name)))
    ds = jd.open(built, fields={"rgb", "semantics"})
    opened.clear()
    ds[0]
    sid = ds.samples[0]
    want = sorted([f"rgb_images/{sid}_{c}.png" for c in ds.cameras]
                  + [f"semantic_annotations/gtLabels/{sid}_{c}.png" for c in ds.cameras])
    assert sorted(opened) == want
    ds = jd.open(built, fields={"lidar"}, cameras=[])
    opened.clear()
    s = ds[0]
    assert opened == [f"lidar_vehicle/{sid}.npy"] and s.cameras == {}


def test_window_with_and_without_sequence_file(built, tmp_path):
    ds = jd.open(built, fields={"timestamp_s"}, cameras=[])
    w = ds.window(0, 2)
    assert [s.id for s in w] == list(ds.samples)
    assert w[1].timestamp_s > w[0].timestamp_s
    with pytest.raises(jd.DatasetReadError, match="crosses the end of sequence 'seq_00000'"):
        ds.window(1, 2)
    # Without sequence.json (a build by an older jaxfish): consecutive frame numbers.
    older = tmp_path / "dataset"
    shutil.copytree(built, older)
    (older / "sequence.json").unlink()
    ds = jd.open(older, fields={"timestamp_s"}, cameras=[])
    assert [s.id for s in ds.window(0, 2)] == list(ds.samples)
    with pytest.raises(jd.DatasetReadError, match="end of the dataset"):
        ds.window(1, 2)
    with pytest.raises(ValueError):
        ds.window(0, 0)
    with pytest.raises(IndexError):
        ds.window(5, 1)


# ----------------------------------------------------------------------------- worker processes


def _read_in_worker(args):
    """What a DataLoader worker does: unpickle the dataset and read its own indices."""
    blob, indices = args
    ds = pickle.loads(blob)
    out = []
    for i in indices:
        s = ds[i]
        out.append((s, s.cameras["FV"].camera.width))
    return out


def test_pickled_dataset_reads_the_same_in_spawned_workers(built):
    ds = jd.open(built)
    ds[0]  # the parent's camera models are built ...
    blob = pickle.dumps(ds)  # ... and not pickled: paths and parsed JSON only
    assert ds._models and pickle.loads(blob)._models == {}
    ctx = multiprocessing.get_context("spawn")
    with ctx.Pool(2) as pool:
        results = pool.map(_read_in_worker, [(blob, [0]), (blob, [1, -1])])
    got = [r for part in results for r in part]
    assert [s.id for s, _ in got] == [ds.samples[0], ds.samples[1], ds.samples[1]]
    fields = [f for f in jd.CAMERA_FIELDS if f not in ("camera", "pose", "boxes_2d", "boxes_2d_full")]
    for (s, width), i in zip(got, [0, 1, 1], strict=True):
        ref = ds[i]
        assert width == ref.cameras["FV"].camera.width
        for cam in ds.cameras:
            for f in fields:
                a, b = getattr(s.cameras[cam], f), getattr(ref.cameras[cam], f)
                assert (a is None) == (b is None), (cam, f)
                if a is not None:
                    np.testing.assert_array_equal(a, b)
            np.testing.assert_array_equal(s.cameras[cam].boxes_2d.xyxy, ref.cameras[cam].boxes_2d.xyxy)
        np.testing.assert_array_equal(s.lidar, ref.lidar)
        np.testing.assert_array_equal(s.boxes_3d.corners_world, ref.boxes_3d.corners_world)
        assert s.timestamp_s == ref.timestamp_s


# ----------------------------------------------------------------------------- collate


def test_collate_stacks_cameras_and_pads_ragged_fields(built):
    ds = jd.open(built)
    samples = [ds[0], ds[1]]
    b = jd.collate(samples)
    assert b["id"] == list(ds.samples)
    np.testing.assert_array_equal(b["timestamp_s"], [s.timestamp_s for s in samples])
    fv = b["cameras"]["FV"]
    assert fv["rgb"].shape == (2,) + samples[0].cameras["FV"].rgb.shape
    np.testing.assert_array_equal(fv["rgb"][1], samples[1].cameras["FV"].rgb)
    assert len(fv["camera"]) == 2 and fv["camera_to_vehicle"].shape == (2, 4, 4)
    counts = [len(s.cameras["FV"].events) for s in samples]
    np.testing.assert_array_equal(fv["events_count"], counts)
    assert fv["events"].shape == (2, max(counts))
    for k, s in enumerate(samples):
        np.testing.assert_array_equal(fv["events"][k, : counts[k]], s.cameras["FV"].events)
        assert not np.any(fv["events"][k, counts[k]:]["t"])
        n = len(s.cameras["FV"].boxes_2d.class_id)
        assert fv["boxes_2d"]["count"][k] == n
        np.testing.assert_array_equal(fv["boxes_2d"]["xyxy"][k, :n], s.cameras["FV"].boxes_2d.xyxy)
        assert np.all(fv["boxes_2d"]["xyxy"][k, n:] == jd.PAD_INT)
        m = len(s.lidar)
        assert b["lidar_count"][k] == m
        np.testing.assert_array_equal(b["lidar"][k, :m], s.lidar)
        assert np.all(b["lidar"][k, m:] == jd.PAD_FLOAT)
        assert b["boxes_3d"]["count"][k] == len(s.boxes_3d.actor_id)
    assert b["cameras"]["BEV"]["events"] is None
    assert b["imu"]["accelerometer_mps2"].shape == (len(samples), 3)
    assert b["bev"]["height"].shape[0] == 2 and b["ego"]["vehicle_to_world"].shape == (2, 4, 4)
    with pytest.raises(ValueError, match="no samples"):
        jd.collate([])


# ----------------------------------------------------------------------------- the released layout


RELEASE_CAMERAS = ("FV", "RV", "MVL", "MVR")
H, W = 6, 8


def write_release_miniature(root: Path, ids=("00000", "00001", "00003")) -> dict:
    """A tiny dataset in SynWoodScape's released layout (no dataset.json, no jaxfish extras), with
    the release's own calibration files (../shared, CARLA-key translations). Returns what it wrote."""
    rng = np.random.default_rng(0)
    truth: dict = {}
    (root / "calibration_data").mkdir(parents=True)
    for cam in RELEASE_CAMERAS:
        shutil.copyfile(shared_path(f"calibration/synwoodscape/{cam}.json"), root / "calibration_data" / f"{cam}.json")
    for n, sid in enumerate(ids):
        for cam in (*RELEASE_CAMERAS, "BEV"):
            stem = f"{sid}_{cam}"
            rec = {"rgb": rng.integers(0, 256, (H, W, 3), dtype=np.uint8),
                   "rgb_prev": rng.integers(0, 256, (H, W, 3), dtype=np.uint8),
                   "depth": rng.uniform(0.5, 1000, (H, W)).astype(np.float32),
                   "semantics": rng.integers(0, 25, (H, W), dtype=np.uint8),
                   "instances": rng.integers(0, 200, (H, W), dtype=np.uint8),
                   "motion": rng.integers(0, 2, (H, W)).astype(bool),
                   "flow": rng.normal(size=(H, W, 2)).astype(np.float32)}
            write_image(root / "rgb_images" / f"{stem}.png", rec["rgb"])
            write_image(root / "previous_images" / f"{stem}_prev.png", rec["rgb_prev"])
            (root / "depth_maps/raw_data").mkdir(parents=True, exist_ok=True)
            np.save(root / "depth_maps/raw_data" / f"{stem}.npy", rec["depth"])
            write_image(root / "semantic_annotations/gtLabels" / f"{stem}.png", rec["semantics"])
            write_image(root / "instance_annotations/gtLabels" / f"{stem}.png", rec["instances"])
            write_image(root / "motion_annotations/gtLabels" / f"{stem}.png", rec["motion"].astype(np.uint8) * 255)
            write_flo(root / "optical_flow/raw_data" / f"{stem}.flo", rec["flow"])
            (root / "box_2d_annotations").mkdir(exist_ok=True)
            (root / "box_2d_annotations" / f"{stem}.txt").write_text("vehicle, 10, 1, 2, 5, 4\n" if cam == "FV" else "")
            if cam != "BEV":
                ev = np.zeros(3 + n, [("x", "<u2"), ("y", "<u2"), ("t", "<i8"), ("pol", "?")])
                ev["x"], ev["t"] = np.arange(3 + n), np.arange(3 + n) * 1000
                write_events_npy(root / "dvs_signals/raw_data" / f"{stem}.npy", ev)
                rec["events"] = ev
            truth[stem] = rec
        (root / "box_3d_annotations").mkdir(exist_ok=True)
        boxes = {7: rng.normal(size=(8, 3)), 3: rng.normal(size=(8, 3))}
        (root / "box_3d_annotations" / f"{sid}.pkl").write_bytes(pickle.dumps(boxes))
        truth[f"{sid}.boxes"] = boxes
        (root / "lidar_data").mkdir(exist_ok=True)
        lidar = {"points": rng.normal(size=(5 + n, 4)).astype(np.float32)}
        (root / "lidar_data" / f"{sid}.pkl").write_bytes(pickle.dumps(lidar))
        truth[f"{sid}.lidar"] = lidar
        for sub, t in (("rgb_images", 0.1 * (int(sid) + 1)), ("previous_images", 0.1 * int(sid))):
            (root / "vehicle_data" / sub).mkdir(parents=True, exist_ok=True)
            (root / "vehicle_data" / sub / f"{sid}.txt").write_text(
                f"timestamp_s {t:.9g}\nlocation_m 1 2 0\nrotation_deg 0 30 0\nvelocity_mps 1 0 0\n"
                "acceleration_mps2 0 0 0\nangular_velocity_degps 0 0 10\n")
    return truth


@pytest.fixture
def release(tmp_path):
    root = tmp_path / "synwoodscape"
    return root, write_release_miniature(root)


def test_release_layout_miniature(release):
    root, truth = release
    with pytest.warns(UserWarning, match="#113"):
        ds = jd.open(root)
    assert ds.layout == jd.LAYOUT_RELEASE == "synwoodscape-release"
    assert ds.samples == ("00000", "00001", "00003")
    assert ds.cameras == ("FV", "RV", "MVL", "MVR", "BEV")
    fixed = [c for c in RELEASE_CAMERAS if "MVL" in c or "MVR" in c]
    assert len(ds.corrections) == 2 and all(any(f"{c}.json" in x for x in ds.corrections) for c in fixed)
    assert any("range or z-depth" in n for n in ds.notes)
    for i, sid in enumerate(ds.samples):
        s = ds[i]
        assert s.timestamp_s == pytest.approx(0.1 * (int(sid) + 1))
        for cam in ds.cameras:
            c, rec = s.cameras[cam], truth[f"{sid}_{cam}"]
            for f in ("rgb", "rgb_prev", "depth", "semantics", "instances", "motion", "flow"):
                np.testing.assert_array_equal(getattr(c, f), rec[f], err_msg=f"{sid} {cam} {f}")
            assert c.z_depth is None and c.flow_valid is None and c.boxes_2d_full is None
            if cam == "BEV":
                assert c.events is None and c.camera is None and c.pose is None
            else:
                np.testing.assert_array_equal(c.events, rec["events"])
                ref = load_calibration(root / "calibration_data" / f"{cam}.json", apply_errata=True)
                np.testing.assert_array_equal(np.asarray(c.pose.as_matrix()), np.asarray(ref.camera_to_vehicle.as_matrix()))
                carla = np.asarray(c.pose.translation) * [1, -1, 1]
                np.testing.assert_allclose(carla, SYNWOODSCAPE_CORRECTED_TRANSLATIONS_CARLA[cam], atol=1e-6)
        fv = s.cameras["FV"].boxes_2d
        assert fv.class_name == ("vehicle",) and fv.xyxy.tolist() == [[1, 2, 5, 4]]
        assert len(s.cameras["RV"].boxes_2d.class_id) == 0
        boxes = truth[f"{sid}.boxes"]
        np.testing.assert_array_equal(s.boxes_3d.actor_id, [3, 7])
        np.testing.assert_array_equal(s.boxes_3d.corners_world, np.stack([boxes[3], boxes[7]]))
        assert list(s.boxes_3d.class_id) == [-1, -1]
        m = jd.vehicle_to_world_matrix([1, 2, 0], [0, 30, 0])  # the miniature's vehicle_data at t
        np.testing.assert_allclose(s.boxes_3d.corners_vehicle @ m[:3, :3].T + m[:3, 3], s.boxes_3d.corners_world,
                                   atol=1e-12)
        np.testing.assert_array_equal(s.lidar, truth[f"{sid}.lidar"]["points"])
        assert s.lidar_frame == jd.LIDAR_FRAME_SENSOR and s.semantic_lidar is None and s.radar is None
        assert s.bev is None and s.imu is None and s.gnss is None
    # windows over consecutive frame numbers: 00002 is missing
    assert [s.id for s in ds.window(0, 2)] == ["00000", "00001"]
    with pytest.raises(jd.DatasetReadError, match="gap.*00002"):
        ds.window(1, 2)
    with pytest.raises(jd.DatasetReadError, match="end of the dataset"):
        ds.window(2, 2)
    b = jd.collate([ds[0], ds[2]])
    assert b["cameras"]["FV"]["events_count"].tolist() == [3, 5]
    assert b["boxes_3d"]["corners_vehicle"].shape == (2, 2, 8, 3)
    (root / "vehicle_data/rgb_images/00000.txt").write_text("timestamp_s 0.1\n")  # no ego pose
    with pytest.warns(UserWarning):
        assert jd.open(root, fields={"boxes_3d"})[0].boxes_3d.corners_vehicle is None
    with pytest.raises(jd.DatasetReadError, match="00000.txt: field 'ego'"):
        ds[0]


def test_release_sensor_extras_and_sequence_file(release):
    """The files `jaxfish build` adds for sequences and sensors are read when present."""
    root, _ = release
    sid = "00001"
    sensor = {"timestamp_s": 0.25, "previous_timestamp_s": 0.15,
              "ego": {"vehicle_to_world": np.eye(4).tolist(), "velocity_mps": [1, 2, 3],
                      "acceleration_mps2": [0, 0, 1], "angular_velocity_radps": [0, 0, 0.5]},
              "imu": {"accelerometer_mps2": [0, 0, 9.81], "gyroscope_radps": [0, 0, 0.1], "compass_rad": 1.5},
              "gnss": {"latitude_deg": 48.1, "longitude_deg": 11.5, "altitude_m": 500.0}}
    (root / "sensor_data").mkdir()
    (root / "sensor_data" / f"{sid}.json").write_text(json.dumps(sensor))
    pts = np.arange(12, dtype=np.float32).reshape(3, 4)
    sem = np.zeros(2, jd.SEMANTIC_LIDAR_DTYPE)
    sem["object_tag"] = [4, 10]
    radar = np.zeros(4, [(k, "<f4") for k in ("velocity", "azimuth", "altitude", "depth", "x", "y", "z")])
    radar["depth"] = [1, 2, 3, 4]
    for folder, arr in (("lidar_vehicle", pts), ("semantic_lidar_vehicle", sem), ("radar_data", radar)):
        (root / folder).mkdir()
        np.save(root / folder / f"{sid}.npy", arr)
    valid = np.zeros((H, W), np.uint8)
    valid[2:, :] = 255
    occ = np.zeros((H, W), np.uint8)
    occ[0, :3] = 255
    write_image(root / "optical_flow/valid_mask" / f"{sid}_FV.png", valid)
    write_image(root / "optical_flow/occlusion_mask" / f"{sid}_FV.png", occ)
    seq = {"sequences": [{"name": "a", "samples": ["00000", "00001"], "dt_s": 0.1},
                         {"name": "b", "samples": ["00003"], "dt_s": 0.1}],
           "neighbours": {"00000": {"previous": None, "next": "00001"}}}
    (root / "sequence.json").write_text(json.dumps(seq))
    with pytest.warns(UserWarning):
        ds = jd.open(root)
    s = ds[1]
    assert s.timestamp_s == 0.25 and s.ego.previous_timestamp_s == 0.15
    np.testing.assert_array_equal(s.ego.velocity_mps, [1, 2, 3])
    np.testing.assert_array_equal(s.imu.accelerometer_mps2, [0, 0, 9.81])
    assert s.imu.compass_rad == 1.5 and s.gnss.latitude_deg == 48.1 and s.gnss.altitude_m == 500.0
    np.testing.assert_array_equal(s.lidar, pts)
    assert s.lidar_frame == jd.LIDAR_FRAME_VEHICLE
    np.testing.assert_array_equal(s.semantic_lidar, sem)
    np.testing.assert_array_equal(s.radar, radar)
    np.testing.assert_array_equal(s.cameras["FV"].flow_valid, valid == 255)
    np.testing.assert_array_equal(s.cameras["FV"].flow_occlusion, occ == 255)
    assert s.cameras["RV"].flow_valid is None
    assert ds[0].lidar_frame == jd.LIDAR_FRAME_SENSOR  # sample 00000 has no lidar_vehicle file
    assert [x.id for x in ds.window(0, 2)] == ["00000", "00001"]
    with pytest.raises(jd.DatasetReadError, match="end of sequence 'b'"):
        ds.window(2, 2)
    with pytest.raises(jd.DatasetReadError, match="end of sequence 'a'"):
        ds.window(1, 2)


# ----------------------------------------------------------------------------- bad files


def npy_bytes(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a)
    return buf.getvalue()


def flo_bytes(f: np.ndarray) -> bytes:
    h, w = f.shape[:2]
    return np.float32(202021.25).tobytes() + np.asarray([w, h], "<i4").tobytes() + f.astype("<f4").tobytes()


@pytest.mark.parametrize(("rel", "content", "field"), [
    ("rgb_images/00000_FV.png", b"not a png", "rgb"),
    ("semantic_annotations/gtLabels/00000_RV.png", None, "semantics"),
    ("depth_maps/raw_data/00000_MVL.npy", b"\x93NUMPY garbage", "depth"),
    ("depth_maps/raw_data/00000_FV.npy", npy_bytes(np.zeros((3, 3), np.float32)), "depth"),
    ("depth_maps/raw_data/00000_RV.npy", npy_bytes(np.zeros((H, W), np.int32)), "depth"),
    ("optical_flow/raw_data/00000_MVL.flo", flo_bytes(np.zeros((H, W + 1, 2), np.float32)), "flow"),
    ("optical_flow/raw_data/00000_FV.flo", b"PIEH", "flow"),
    ("dvs_signals/raw_data/00000_MVR.npy", None, "events"),
    ("box_2d_annotations/00000_FV.txt", b"vehicle,10,1\n", "boxes_2d"),
    ("box_3d_annotations/00000.pkl", b"\x80\x04 broken", "boxes_3d"),
    ("lidar_data/00000.pkl", pickle.dumps([1, 2]), "lidar"),
    ("vehicle_data/rgb_images/00000.txt", b"timestamp_s abc\n", "timestamp_s"),
])
def test_bad_files_name_their_path_and_field(release, rel, content, field):
    root, _ = release
    path = root / rel
    if content is None:
        path.unlink()
    else:
        path.write_bytes(content)
    with pytest.warns(UserWarning):
        ds = jd.open(root)
    with pytest.raises(jd.DatasetReadError) as err:
        ds[0]
    assert isinstance(err.value, JaxfishError)
    assert str(path) in str(err.value) and f"'{field}'" in str(err.value)
    assert ds[1].id == "00001"  # the other samples still read


@pytest.mark.parametrize(("text", "fields", "field"), [
    ("{", {"timestamp_s"}, "timestamp_s"),
    ("[]", {"ego"}, "ego"),
    ('{"timestamp_s": "soon"}', {"timestamp_s"}, "timestamp_s"),
    ('{"timestamp_s": 1.0, "imu": {"accelerometer_mps2": [0, 0]}}', {"imu"}, "imu"),
    ('{"timestamp_s": 1.0, "gnss": {"latitude_deg": null}}', {"gnss"}, "gnss"),
    ('{"timestamp_s": 1.0, "ego": {"vehicle_to_world": [[1, 0], [0, 1]]}}', {"ego"}, "ego"),
])
def test_bad_sensor_file_names_its_field(release, text, fields, field):
    root, _ = release
    (root / "sensor_data").mkdir()
    path = root / "sensor_data" / "00000.json"
    path.write_text(text)
    with pytest.warns(UserWarning):
        ds = jd.open(root, fields=fields, cameras=[])
    with pytest.raises(jd.DatasetReadError) as err:
        ds[0]
    assert str(path) in str(err.value) and f"'{field}'" in str(err.value)


def test_bad_dataset_level_files(tmp_path, release):
    with pytest.raises(jd.DatasetReadError, match="not a dataset"):
        jd.open(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(jd.DatasetReadError, match="neither dataset.json nor rgb_images"):
        jd.open(tmp_path / "empty")
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "dataset.json").write_text('{"format": "other"}')
    with pytest.raises(jd.DatasetReadError, match=r"dataset.json: field 'format'"):
        jd.open(bad)
    (bad / "dataset.json").write_text("{not json")
    with pytest.raises(jd.DatasetReadError, match=r"dataset.json: field 'format'"):
        jd.open(bad)
    root, _ = release
    cal = root / "calibration_data" / "MVL.json"
    cal.write_text("{")
    with pytest.raises(jd.DatasetReadError, match=r"MVL.json: field 'camera'"):
        jd.open(root)
    (root / "calibration_data" / "MVL.json").unlink()
    with pytest.raises(jd.DatasetReadError, match=r"MVL.json: field 'camera': file missing"):
        jd.open(root)
    (root / "sequence.json").write_text("[]")
    shutil.copyfile(shared_path("calibration/synwoodscape/MVL.json"), cal)
    with pytest.raises(jd.DatasetReadError, match=r"sequence.json: field 'sequences'"):
        jd.open(root)


def test_through_grain(built):
    """grain (dev group) reads the dataset as a random-access source and batches with `collate`."""
    grain = pytest.importorskip("grain")
    ds = jd.open(built, fields={"rgb", "semantics", "lidar"})
    loader = grain.DataLoader(data_source=ds, sampler=grain.samplers.IndexSampler(len(ds), num_epochs=1, shuffle=False),
                              operations=[grain.transforms.Batch(2, batch_fn=jd.collate)], worker_count=0)
    batches = list(loader)
    assert len(batches) == 1 and batches[0]["id"] == list(ds.samples)
    np.testing.assert_array_equal(batches[0]["cameras"]["MVL"]["semantics"][1], ds[1].cameras["MVL"].semantics)
    mapped = grain.MapDataset.source(ds).batch(2, batch_fn=jd.collate)
    np.testing.assert_array_equal(mapped[0]["lidar"], batches[0]["lidar"])
