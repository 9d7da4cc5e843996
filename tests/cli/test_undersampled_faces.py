"""Cube faces too small for a fisheye are warned about (CONVENTIONS §7: a face's focal S/2 must
reach the fisheye's largest d rho / d theta), naming ``cube_face_size`` and the smallest sufficient
size; the demo's and synth's defaults never trip their own warning."""

from __future__ import annotations

import inspect
import math
import warnings

import numpy as np
import pytest
from typer.testing import CliRunner

import jaxfish as jf
from jaxfish.cli import app
from jaxfish.cli._demo import demo_config, demo_rig
from jaxfish.cli._synth import synth
from jaxfish.io import save_calibration, write_image
from jaxfish.reprojection import FIVE_FACES, UndersampledFacesWarning, max_radial_density, warn_undersampled_faces


def _polynomial_density(cam) -> float:
    """max d rho / d theta of a WoodScape lens over the incidence angles inside its image (NumPy)."""
    k = np.asarray(cam.k, np.float64)
    cx = cam.width / 2 + float(cam.cx_offset) - 0.5
    cy = cam.height / 2 + float(cam.cy_offset) - 0.5
    r = max(math.hypot(x - cx, y - cy) for x in (-0.5, cam.width - 0.5) for y in (-0.5, cam.height - 0.5))
    th = np.linspace(1e-4, math.pi, 200001)
    rho = th * (k[0] + th * (k[1] + th * (k[2] + th * k[3])))
    d = k[0] + th * (2 * k[1] + th * (3 * k[2] + th * 4 * k[3]))
    return float(d[rho <= r].max())


def test_max_radial_density_of_lens_models():
    for calib in jf.default_rig().values():
        truth = _polynomial_density(calib.camera)
        assert 0.97 * truth <= max_radial_density(calib.camera) <= truth * 1.001
        assert max_radial_density(calib.camera) > 1.5 * float(calib.camera.k[0])  # not k1: the periphery is denser
    pin = jf.Pinhole.from_fov(640, 480, 90.0)  # f = 320: f / cos^2 at the corner, 400 px off-axis
    assert 0.98 * 320 * (1 + (400 / 320) ** 2) <= max_radial_density(pin) <= 320 * (1 + (400 / 320) ** 2) * 1.001
    ds = jf.DoubleSphere(fx=313.2, fy=313.2, cx=638.0, cy=514.0, xi=-0.18, alpha=0.59, width=1280, height=1024)
    assert 375 < max_radial_density(ds) < 395  # ~fx / (1 - alpha)... near the centre: 384 px/rad


def test_undersized_faces_warn_once_naming_cube_face_size():
    rig = {name: c.camera for name, c in jf.default_rig().items()}
    densest = max(max_radial_density(c) for c in rig.values())
    with pytest.warns(UndersampledFacesWarning) as caught:
        message = warn_undersampled_faces(256, rig)
    assert len(caught) == 1 and str(caught[0].message) == message
    assert "cube_face_size" in message and f"at least {math.ceil(2 * densest)} px" in message
    assert "128 px/rad" in message and "1280x966" in message
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert warn_undersampled_faces(math.ceil(2 * densest), rig) is None


@pytest.mark.parametrize("scale", [1.0, 0.5, 0.05])
def test_demo_faces_do_not_undersample_its_rig(scale):
    rig = {name: c.camera for name, c in demo_rig(scale).items()}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert warn_undersampled_faces(demo_config(scale).face_size, rig) is None


def test_synth_default_faces_do_not_undersample_the_default_rig():
    default = inspect.signature(synth).parameters["face_size"].default.default
    rig = {name: c.camera for name, c in jf.default_rig().items()}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert warn_undersampled_faces(default, rig) is None


def test_cube2fisheye_warns_on_stderr_when_faces_are_too_small(tmp_path):
    calib = jf.default_rig()["FV"].resize(96, 72)  # largest radial density ~41 px/rad: faces >= 82 px
    path = save_calibration(calib, tmp_path / "FV.json")
    need = math.ceil(2 * max_radial_density(calib.camera))
    for size, warned in ((32, True), (need, False)):
        faces = tmp_path / f"faces{size}"
        faces.mkdir()
        for i, name in enumerate(FIVE_FACES):
            write_image(faces / f"{name}.png", np.full((size, size, 3), 40 * i + 10, np.uint8))
        result = CliRunner().invoke(app, ["cube2fisheye", "--faces", str(faces), "-c", str(path),
                                          "-o", str(tmp_path / f"fisheye{size}.png")])
        assert result.exit_code == 0, result.output
        assert ("warning:" in result.stderr) is warned, result.stderr
        if warned:
            text = " ".join(result.stderr.split())
            assert "cube_face_size" in text and f"at least {need} px" in text and text.count("warning:") == 1
        assert "wrote" in result.stdout and "wrote" not in result.stderr


def test_synth_warns_about_its_faces(tmp_path):
    from jaxfish.io import save_rig

    save_rig({"FV": jf.default_rig()["FV"].resize(64, 48)}, tmp_path / "rig")
    args = ["synth", "--out", str(tmp_path / "cap"), "--frames", "1", "--face-size", "16", "--rig", str(tmp_path / "rig"),
            "--bev-size", "16", "--front-width", "16", "--dvs-substeps", "1"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    text = " ".join(result.stderr.split())
    assert text.count("warning:") == 1 and "the FV camera" in text and "cube_face_size" in text
    assert "wrote 1 frame(s)" in result.stdout
