"""``jaxfish cube2fisheye`` and ``jaxfish reproject``: outputs, formats and clear errors."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from typer.testing import CliRunner

import jaxfish as jf
from jaxfish.cli import app
from jaxfish.io import read_image, save_calibration, write_image
from jaxfish.reprojection import FIVE_FACES

from ..conftest import shared_path

S = 32
W, H = 96, 72


def _run(*args):
    result = CliRunner().invoke(app, [str(a) for a in args])
    text = result.output + (getattr(result, "stderr", "") or "")
    return result, "".join(text.split())  # the console wraps long lines: compare without whitespace


@pytest.fixture(scope="module")
def small_calibration(tmp_path_factory):
    calib = jf.default_rig()["FV"].resize(W, H)
    return save_calibration(calib, tmp_path_factory.mktemp("calib") / "FV.json"), calib


def _faces(directory, kind):
    directory.mkdir(parents=True, exist_ok=True)
    for i, name in enumerate(FIVE_FACES):
        if kind == "rgb":
            write_image(directory / f"{name}.png", np.full((S, S, 3), 40 * i + 10, np.uint8))
        elif kind == "label":
            write_image(directory / f"{name}.png", np.full((S, S), i + 1, np.uint8))
        else:  # a 4 m sphere around the camera: planar z = 4 / |(x, y, 1)| in every face
            c = (np.arange(S) - (S - 1) / 2) / (S / 2)
            x, y = np.meshgrid(c, c, indexing="xy")
            write_image(directory / f"{name}.exr", (4.0 / np.sqrt(1 + x * x + y * y)).astype(np.float32))
    return directory


def test_cube2fisheye_rgb_label_depth(tmp_path, small_calibration):
    calib_path, calib = small_calibration
    out = tmp_path / "fisheye.png"
    result, text = _run("cube2fisheye", "--faces", _faces(tmp_path / "rgb", "rgb"), "--calibration", calib_path, "--out", out,
                        "--supersample", "2")
    assert result.exit_code == 0, text
    img = read_image(out)
    assert img.shape == (H, W, 3) and img.dtype == np.uint8
    # constant faces stay exact away from the seams (across them bilinear blends the two faces)
    assert np.isin(img, [0, 10, 50, 90, 130, 170]).mean() > 0.8
    _, rv = calib.camera.unproject(calib.camera.pixel_grid(jnp.float64))
    assert np.all(img[~np.asarray(rv)] == 0)  # outside the lens domain: 0

    out = tmp_path / "labels.png"
    result, text = _run("cube2fisheye", "--faces", _faces(tmp_path / "lab", "label"), "-c", calib_path, "-o", out,
                        "--kind", "label", "--supersample", "2")
    assert result.exit_code == 0, text
    lab = read_image(out)[..., 0]
    assert set(np.unique(lab)) <= {0, 1, 2, 3, 4, 5} and lab[H // 2, W // 2] == 1  # front face in the centre

    out = tmp_path / "depth.exr"
    result, text = _run("cube2fisheye", "--faces", _faces(tmp_path / "dep", "depth"), "-c", calib_path, "-o", out,
                        "--kind", "depth", "--supersample", "2")
    assert result.exit_code == 0, text
    depth = read_image(out)[..., 0]
    assert depth.dtype == np.float32
    valid = depth > 0
    assert valid.mean() > 0.8
    np.testing.assert_allclose(depth[valid], 4.0, rtol=2e-3)  # range, not planar z


def test_cube2fisheye_reads_a_capture_camera_directory(tmp_path, small_calibration):
    """A capture's camera directory (raw CARLA BGRA faces) gives what its decoded faces give."""
    from jaxfish.io._capture import write_images
    from jaxfish.scene import CameraImages

    calib_path, _ = small_calibration
    cam, plain = tmp_path / "cam", tmp_path / "plain"
    c = (np.arange(S) - (S - 1) / 2) / (S / 2)
    x, y = np.meshgrid(c, c, indexing="xy")
    for i, name in enumerate(FIVE_FACES):
        rgb = np.broadcast_to(np.array([10 + i, 100 + i, 200 + i], np.uint8), (S, S, 3))  # R != B: a swap shows
        tags = np.full((S, S), i + 1, np.uint8)
        depth = (4.0 / np.sqrt(1 + x * x + y * y)).astype(np.float32)
        (cam / name).mkdir(parents=True)
        write_images(cam / name, CameraImages(rgb, depth, tags, np.zeros((S, S), np.int32)), "prev")
        for kind, a in (("rgb", rgb), ("label", tags)):
            write_image(plain / kind / f"{name}.png", np.ascontiguousarray(a))
        write_image(plain / "depth" / f"{name}.exr", depth)
    for kind, ext in (("rgb", "png"), ("label", "png"), ("depth", "npy")):
        outs = [tmp_path / f"{kind}_{src}.{ext}" for src in ("capture", "plain")]
        for faces, out in zip((cam, plain / kind), outs, strict=True):
            result, text = _run("cube2fisheye", "--faces", faces, "-c", calib_path, "-o", out, "--kind", kind,
                                "--instant", "prev")
            assert result.exit_code == 0, text
        got, want = (np.load(o) if ext == "npy" else read_image(o) for o in outs)
        assert got.shape == want.shape and got.dtype == want.dtype
        if kind == "depth":
            np.testing.assert_allclose(got, want, atol=1e-3)  # CARLA's 24-bit depth code: ~6e-5 m steps
        else:
            assert np.array_equal(got, want)
    result, text = _run("cube2fisheye", "--faces", cam, "-c", calib_path, "-o", tmp_path / "c.png")  # no *_curr files
    assert result.exit_code == 2 and "front/rgb_curr.png" in text and not (tmp_path / "c.png").exists()
    write_image(cam / "top" / "depth_prev.png", np.zeros((S, S), np.uint8))  # not CARLA's BGRA depth code
    result, text = _run("cube2fisheye", "--faces", cam, "-c", calib_path, "-o", tmp_path / "d.npy", "--kind", "depth",
                        "--instant", "prev")
    assert result.exit_code == 2 and "top/depth_prev.png" in text and "decode_depth" in text, text
    write_image(cam / "top" / "depth_prev.png", np.zeros((S + 2, S + 2, 4), np.uint8))
    result, text = _run("cube2fisheye", "--faces", cam, "-c", calib_path, "-o", tmp_path / "d.npy", "--kind", "depth",
                        "--instant", "prev")
    assert result.exit_code == 2 and "top/depth_prev.png:facesize34x34differsfrom" in text and "front/depth_prev.png" in text


def test_cube2fisheye_errors_leave_no_output(tmp_path, small_calibration):
    calib_path, _ = small_calibration
    faces = _faces(tmp_path / "f", "rgb")
    out = tmp_path / "o.png"
    (faces / "top.png").unlink()
    (faces / "left.png").unlink()
    result, text = _run("cube2fisheye", "--faces", faces, "-c", calib_path, "-o", out)
    assert result.exit_code != 0 and "missingcubefacesleft,top" in text
    write_image(faces / "top.png", np.zeros((S + 2, S + 2, 3), np.uint8))
    write_image(faces / "left.png", np.zeros((S, S, 3), np.uint8))
    result, text = _run("cube2fisheye", "--faces", faces, "-c", calib_path, "-o", out)
    assert result.exit_code != 0 and "top.png:facesize34x34differs" in text
    (faces / "top.png").write_bytes(b"not a png")
    result, text = _run("cube2fisheye", "--faces", faces, "-c", calib_path, "-o", out)
    assert result.exit_code != 0 and "top.png" in text
    result, text = _run("cube2fisheye", "--faces", faces, "-c", tmp_path / "nope.json", "-o", out)
    assert result.exit_code != 0 and "nope.json" in text
    result, text = _run("cube2fisheye", "--faces", faces, "-c", calib_path, "-o", tmp_path / "d.png", "--kind", "depth")
    assert result.exit_code != 0 and "depthisfloatmetres" in text
    result, text = _run("cube2fisheye", "--faces", faces, "-c", calib_path, "-o", out, "--kind", "labels")
    assert result.exit_code != 0 and "--kind" in text
    write_image(faces / "top.png", np.zeros((S, S), np.uint8))  # one channel among RGB faces: named, no traceback
    result, text = _run("cube2fisheye", "--faces", faces, "-c", calib_path, "-o", out)
    assert result.exit_code != 0 and "top.png:" in text and "channel(s),but" in text, text
    write_image(faces / "top.png", np.zeros((S, S, 3), np.uint16))
    result, text = _run("cube2fisheye", "--faces", faces, "-c", calib_path, "-o", out)
    assert result.exit_code != 0 and "top.png:pixeltypeuint16" in text, text
    assert not out.exists() and not list(tmp_path.glob("*.part*")) and not list(faces.glob(".*"))


def test_reproject_rectifies_a_fisheye(tmp_path, small_calibration):
    calib_path, calib = small_calibration
    # a fisheye image whose value is the incidence angle: a pinhole view straight ahead sees small angles
    rays, valid = calib.camera.unproject(calib.camera.pixel_grid(jnp.float64))
    theta = np.degrees(np.arccos(np.clip(np.asarray(rays)[..., 2], -1, 1)))
    src = write_image(tmp_path / "theta.exr", np.where(np.asarray(valid), theta, 0).astype(np.float32))
    out = tmp_path / "rect.npy"
    result, text = _run("reproject", src, "-c", calib_path, "-o", out, "--width", 40, "--height", 30, "--fov", 90)
    assert result.exit_code == 0, text
    rect = np.load(out)[..., 0]
    assert rect.shape == (30, 40) and rect.dtype == np.float32
    f = 20.0
    uu, vv = np.meshgrid(np.arange(40.0) - 19.5, np.arange(30.0) - 14.5, indexing="xy")
    expected = np.degrees(np.arctan(np.hypot(uu, vv) / f))
    np.testing.assert_allclose(rect, expected, atol=0.5)  # bilinear on a 96 x 72 fisheye
    result, text = _run("reproject", tmp_path / "missing.png", "-c", calib_path, "-o", tmp_path / "m.png")
    assert result.exit_code != 0 and "missing.png" in text
    small = write_image(tmp_path / "small.png", np.zeros((10, 10, 3), np.uint8))
    result, text = _run("reproject", small, "-c", calib_path, "-o", tmp_path / "m.png")
    assert result.exit_code != 0 and "10x10" in text and not (tmp_path / "m.png").exists()


def test_reproject_the_real_sample(tmp_path):
    """README example: rectify the SynWoodScape front sample to a pinhole view."""
    sample = shared_path("samples/synwoodscape_FV_rgb.png")
    calib = shared_path("calibration/synwoodscape/FV.json")
    out = tmp_path / "rect.png"
    result, text = _run("reproject", sample, "-c", calib, "-o", out, "--width", 160, "--height", 120, "--fov", 100)
    assert result.exit_code == 0, text
    img = read_image(out)
    assert img.shape == (120, 160, 3) and img.dtype == np.uint8 and img.std() > 10
    assert np.all(img.reshape(-1, 3).max(axis=0) > 0)


def test_reproject_to_and_from_other_lens_models(tmp_path, small_calibration):
    """Calibrations of any model (``jaxfish convert`` output) are read on both sides."""
    from jaxfish.io import load_calibration, save_camera_calibration
    from jaxfish.refit import convert_camera

    calib_path, calib = small_calibration
    kb = jf.Calibration(calib.name, convert_camera(calib.camera.astype(jnp.float64), "kb").camera, calib.camera_to_vehicle)
    kb_path = save_camera_calibration(kb, tmp_path / "kb.json")
    with pytest.raises(jf.CalibrationError, match="only 'radial_poly'.*load_camera_calibration"):
        load_calibration(kb_path)  # the model is named, not a missing WoodScape key
    rays, valid = calib.camera.unproject(calib.camera.pixel_grid(jnp.float64))
    theta = np.degrees(np.arccos(np.clip(np.asarray(rays)[..., 2], -1, 1)))
    src = write_image(tmp_path / "theta.exr", np.where(np.asarray(valid), theta, 0).astype(np.float32))
    out = tmp_path / "kb.npy"
    result, text = _run("reproject", src, "-c", calib_path, "-o", out, "--to", "fisheye", "--target-calibration", kb_path)
    assert result.exit_code == 0, text
    got = np.load(out)[..., 0]
    kb_rays, kb_valid = kb.camera.unproject(kb.camera.pixel_grid(jnp.float64))
    expected = np.degrees(np.arccos(np.clip(np.asarray(kb_rays)[..., 2], -1, 1)))
    inner = np.asarray(kb_valid) & (expected < 80)
    assert got.shape == (H, W)
    np.testing.assert_allclose(got[inner], expected[inner], atol=1.0)  # bilinear, KB fitted to the lens
    back = tmp_path / "back.npy"
    result, text = _run("reproject", src, "-c", kb_path, "-o", back, "--to", "pinhole",
                        "--width", 20, "--height", 20)
    assert result.exit_code == 0, text  # a KB source calibration
    result, text = _run("reproject", src, "-c", calib_path, "-o", tmp_path / "x.npy", "--to", "fisheye",
                        "--target-calibration", kb_path, "--width", 50)
    assert result.exit_code == 2 and "radial_polytargetonly" in text and not (tmp_path / "x.npy").exists()


def test_bad_numbers_and_output_paths_are_one_line_errors(tmp_path, small_calibration):
    calib_path, _ = small_calibration
    src = write_image(tmp_path / "in.png", np.zeros((H, W, 3), np.uint8))
    for args, text in ((("--pitch", "inf"), "--pitchmustbeafinite"), (("--yaw", "nan"), "--yawmustbeafinite"),
                       (("--width", 0), "--widthmustbeapositive"),
                       (("--width", 100000, "--height", 100000), "100000x100000:morethan")):
        result, out = _run("reproject", src, "-c", calib_path, "-o", tmp_path / "o.png", *args)
        assert result.exit_code == 2 and text in out, out
    (tmp_path / "adir").mkdir()
    result, out = _run("reproject", src, "-c", calib_path, "-o", tmp_path / "adir")
    assert result.exit_code == 2 and "isadirectory" in out
    assert not (tmp_path / "o.png").exists()


def test_errors_are_never_hard_wrapped(tmp_path):
    """Without a terminal rich wraps at 80 columns: a long path must stay on the one error line."""
    from tests.helpers import run_python

    long_dir = tmp_path / ("x" * 90)
    long_dir.mkdir()
    proc = run_python(["-c", "from jaxfish.cli import main; main()", "convert",
                       long_dir / "missing_calibration.json", "--to", "kb", "-o", tmp_path / "o.json"])
    assert proc.returncode == 2
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and "missing_calibration.json" in lines[0], proc.stderr


def test_report_lines_are_never_hard_wrapped_nor_read_as_markup(tmp_path):
    """The success lines (`jaxfish.cli._app.say`) keep a long path holding ``[...]`` whole, on one line."""
    from tests.helpers import run_python

    src = shared_path("calibration/woodscape/FV.json")
    out_dir = tmp_path / ("y" * 90 + "[bold]")
    out_dir.mkdir()
    proc = run_python(["-c", "from jaxfish.cli import main; main()", "convert", src, "--to", "kb", "-o", out_dir / "kb.json"])
    assert proc.returncode == 0, proc.stderr
    assert any(line == f"wrote {out_dir / 'kb.json'}" for line in proc.stdout.splitlines()), proc.stdout  # a result: stdout


def test_an_output_beyond_the_available_memory_is_refused(tmp_path, small_calibration, monkeypatch):
    """The estimate (80 bytes per sample) is checked against the memory available before any
    image is read: an output that would exhaust it exits 2, naming the size, and writes nothing."""
    from jaxfish.cli import _reproject

    calib_path, calib = small_calibration
    img = write_image(tmp_path / "fish.png", np.zeros((calib.camera.height, calib.camera.width, 3), np.uint8))
    out = tmp_path / "o.png"
    monkeypatch.setattr(_reproject, "_available_memory", lambda: 1 << 30)  # 1 GiB free; 4096² needs ~1.6
    result, text = _run("reproject", img, "-c", calib_path, "-o", out, "--width", 4096, "--height", 4096)
    assert result.exit_code == 2, text
    assert "--width/--height4096x4096" in text and "GiBofmemoryisavailable" in text  # _run drops spaces
    assert not out.exists()
    monkeypatch.setattr(_reproject, "_available_memory", lambda: None)  # unknown: not refused
    result, text = _run("reproject", img, "-c", calib_path, "-o", out, "--width", 64, "--height", 48)
    assert result.exit_code == 0 and out.exists(), text


def test_cube2fisheye_refuses_a_supersampled_fisheye_beyond_the_available_memory(tmp_path, small_calibration,
                                                                                   monkeypatch):
    """cube2fisheye's own estimate (`CUBE_BYTES_PER_SAMPLE` per fisheye pixel x supersample²) names
    the calibration file and the per-sample figure; nothing is written."""
    from jaxfish.cli import _reproject

    calib_path, calib = small_calibration
    faces = _faces(tmp_path / "rgb", "rgb")
    out = tmp_path / "fisheye.png"
    samples = calib.camera.width * calib.camera.height * 16 * 16
    need = _reproject.CUBE_BASE_BYTES + samples * _reproject.CUBE_BYTES_PER_SAMPLE
    monkeypatch.setattr(_reproject, "_available_memory", lambda: need - 1)
    result, text = _run("cube2fisheye", "--faces", faces, "--calibration", calib_path, "--out", out, "--supersample", 16)
    assert result.exit_code == 2, text
    assert "intrinsic.width/height" in text and f"({_reproject.CUBE_BYTES_PER_SAMPLE}bytespersample)" in text
    assert not out.exists()
    monkeypatch.setattr(_reproject, "_available_memory", lambda: need)  # just enough: built
    result, text = _run("cube2fisheye", "--faces", faces, "--calibration", calib_path, "--out", out, "--supersample", 16)
    assert result.exit_code == 0 and out.exists(), text
