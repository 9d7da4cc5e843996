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
