"""``jaxfish refit`` and ``jaxfish convert`` end to end."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

import jaxfish as jf
from jaxfish.cli import _refit as _refit  # noqa: F401  (registers refit and convert)
from jaxfish.cli import app
from jaxfish.io import (
    CorrespondenceError,
    load_camera_calibration,
    load_correspondences,
    save_camera_calibration,
    save_correspondences,
)
from tests.conftest import shared_path
from tests.refit.synthetic import initial_camera, scene


def test_convert_to_kb_and_back(tmp_path):
    src = shared_path("calibration/woodscape/FV.json")
    runner = CliRunner()
    result = runner.invoke(app, ["convert", str(src), "--to", "kb", "-o", str(tmp_path / "kb.json"),
                                 "-r", str(tmp_path / "kb_report.json")])
    assert result.exit_code == 0, result.output
    data = json.loads((tmp_path / "kb.json").read_text())
    assert data["intrinsic"]["model"] == "kannala_brandt"
    report = json.loads((tmp_path / "kb_report.json").read_text())
    assert report["converged"] and report["rms_px"] < 1.0 and report["num_target_invalid"] == 0
    assert report["max_px"] >= report["rms_px"] > 0
    original = jf.load_calibration(src)
    kb = load_camera_calibration(tmp_path / "kb.json")
    np.testing.assert_allclose(np.asarray(kb.camera_to_vehicle.translation),
                               np.asarray(original.camera_to_vehicle.translation), atol=1e-12)
    result = runner.invoke(app, ["convert", str(tmp_path / "kb.json"), "--to", "woodscape", "-o",
                                 str(tmp_path / "ws.json")])
    assert result.exit_code == 0, result.output
    back = jf.load_calibration(tmp_path / "ws.json")  # WoodScape's own loader reads it
    assert back.name == original.name
    assert abs(float(back.camera.k[0]) - float(original.camera.k[0])) < 0.05 * float(original.camera.k[0])


def test_convert_keeps_the_synwoodscape_flavor(tmp_path):
    """A SynWoodScape file converts to a file of the same flavor (CARLA-frame translation key), so
    the vehicle origin it implies is unchanged (``carla_capture.py --vehicle-origin auto``)."""
    src = shared_path("calibration/synwoodscape/MVL.json")
    original = jf.load_calibration(src)
    assert original.flavor == "synwoodscape"
    runner = CliRunner()
    for model, name in (("kb", "kb.json"), ("woodscape", "ws.json")):
        source = src if model == "kb" else tmp_path / "kb.json"
        result = runner.invoke(app, ["convert", str(source), "--to", model, "-o", str(tmp_path / name)])
        assert result.exit_code == 0, result.output
        data = json.loads((tmp_path / name).read_text())
        assert set(data["extrinsic"]) == set(json.loads(src.read_text())["extrinsic"])  # SynWoodScape's keys
        out = load_camera_calibration(tmp_path / name)
        assert out.flavor == "synwoodscape"
        np.testing.assert_allclose(np.asarray(out.camera_to_vehicle.translation),
                                   np.asarray(original.camera_to_vehicle.translation), atol=1e-12)
    assert jf.load_calibration(tmp_path / "ws.json").flavor == "synwoodscape"


def test_refit_from_board_correspondences(tmp_path):
    corr, truth, _, _ = scene(noise_px=0.2)
    save_correspondences(corr, tmp_path / "corners.json", frame="board")
    loaded, frame, names = load_correspondences(tmp_path / "corners.json")
    assert frame == "board" and names == [f"view{i}" for i in range(5)] and loaded.size == corr.size
    init = jf.Calibration("FV", initial_camera(), jf.Pose.identity(dtype=np.float64))
    save_camera_calibration(init, tmp_path / "init.json")
    result = CliRunner().invoke(app, ["refit", str(tmp_path / "corners.json"), "-c", str(tmp_path / "init.json"),
                                      "-o", str(tmp_path / "fit.json"), "-r", str(tmp_path / "report.json")])
    assert result.exit_code == 0, result.output
    fit = jf.load_calibration(tmp_path / "fit.json")
    np.testing.assert_allclose(float(fit.camera.k[0]), float(truth.k[0]), rtol=2e-3)
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["converged"] and report["rms_px"] < 0.5
    assert set(report["per_view_rms_px"]) == set(names)
    assert report["parameters"]["k1"]["std"] > 0 and not report["parameters"]["k1"]["fixed"]
    assert len(report["residuals_px"]["view0"]) == int(np.sum(np.asarray(corr.view) == 0))
    n = len(report["covariance"]["names"])
    assert np.asarray(report["covariance"]["matrix"]).shape == (n, n)


def test_refit_input_errors(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"frame": "board", "views": [{"points": [[0, 0, 1]], "pixels": [[1, 2, 3]]}]}))
    with pytest.raises(CorrespondenceError, match=r"bad\.json: field 'views\[0\]\.pixels'"):
        load_correspondences(bad)
    result = CliRunner().invoke(app, ["refit", str(bad), "-o", str(tmp_path / "x.json")])
    assert result.exit_code != 0 and isinstance(result.exception, CorrespondenceError)
    good = tmp_path / "good.json"
    good.write_text(json.dumps({"frame": "camera", "views": [{"points": [[0, 0, 1]], "pixels": [[1, 2]]}]}))
    result = CliRunner().invoke(app, ["refit", str(good), "-o", str(tmp_path / "x.json")])
    assert result.exit_code == 2 and "--model" in result.output


def test_refit_and_convert_reject_bad_numbers_and_outputs_first(tmp_path):
    corr, _, _, _ = scene(noise_px=0.2)
    save_correspondences(corr, tmp_path / "c.json", frame="board")
    runner = CliRunner()
    for args, text in ((["--width", "0", "--height", "0"], "must be positive"),
                       (["--width", "64", "--height", "48", "--focal", "nan"], "--focal must be")):
        result = runner.invoke(app, ["refit", str(tmp_path / "c.json"), "--model", "kb", *args, "-o", str(tmp_path / "o.json")])
        assert result.exit_code == 2 and text in result.output, result.output
    (tmp_path / "rep").mkdir()
    src = shared_path("calibration/woodscape/FV.json")
    result = runner.invoke(app, ["convert", str(src), "--to", "kb", "-o", str(tmp_path / "kb.json"), "-r", str(tmp_path / "rep")])
    assert result.exit_code == 2 and "is a directory" in result.output
    assert not (tmp_path / "o.json").exists() and not (tmp_path / "kb.json").exists()  # nothing half-done


def test_build_options_reject_a_non_finite_motion_threshold():
    from jaxfish.dataset import BuildOptions, DatasetError

    for bad in (float("nan"), float("inf"), -0.1):
        with pytest.raises(DatasetError, match="motion_threshold_m"):
            BuildOptions(motion_threshold_m=bad)


def test_hostile_calibration_files_and_models_get_one_clear_error(tmp_path):
    src = json.loads(shared_path("calibration/woodscape/FV.json").read_text())
    runner = CliRunner()
    huge = json.dumps({**src, "intrinsic": {**src["intrinsic"], "k2": "HUGE"}}).replace('"HUGE"', "1" + "0" * 400)
    cases = {"huge.json": (huge, "field 'intrinsic.k2': expected a finite number, got an integer of 401 digits"),
             "deep.json": ("[" * 100000 + "]" * 100000, "nested too deeply"),
             "null.json": ("null", "field '<root>': expected an object")}
    for name, (text, message) in cases.items():
        (tmp_path / name).write_text(text)
        result = runner.invoke(app, ["convert", str(tmp_path / name), "--to", "kb", "-o", str(tmp_path / "x.json")])
        assert result.exit_code != 0 and message in str(result.exception or result.output), (name, result.output)
        assert not (tmp_path / "x.json").exists()
    kb = {"intrinsic": {"model": "kannala_brandt", "fx": 0.0, "fy": 300.0, "cx": 640.0, "cy": 480.0, "k1": 0.0,
                        "k2": 0.0, "k3": 0.0, "k4": 0.0, "width": 1280, "height": 966}}
    kb = {**src, **kb}
    (tmp_path / "fx0.json").write_text(json.dumps(kb))
    result = runner.invoke(app, ["convert", str(tmp_path / "fx0.json"), "--to", "kb", "-o", str(tmp_path / "x.json")])
    assert "field 'intrinsic.fx': a focal length must be positive" in str(result.exception), result.output
    result = runner.invoke(app, ["refit", str(tmp_path / "fx0.json"), "--model", "nosuch", "-o", str(tmp_path / "x.json")])
    assert result.exit_code == 2 and "--model/--to 'nosuch': unknown lens model" in result.output, result.output


def test_convert_writes_its_calibration_and_report_both_or_neither(tmp_path):
    src = shared_path("calibration/woodscape/FV.json")
    blocker = tmp_path / "file"
    blocker.write_text("")  # a file where the report's folder should be: the report cannot be written
    result = CliRunner().invoke(app, ["convert", str(src), "--to", "kb", "-o", str(tmp_path / "kb.json"),
                                      "-r", str(blocker / "report.json")])
    assert result.exit_code == 2 and "--report" in result.output and "not written either" in result.output, result.output
    assert not (tmp_path / "kb.json").exists()


def test_refit_on_copies_of_one_correspondence_says_degenerate_and_writes_nothing(tmp_path):
    views = [{"points": [[0.1, 0.2, 1.0]] * 20, "pixels": [[700.0, 500.0]] * 20}]
    (tmp_path / "dup.json").write_text(json.dumps({"frame": "camera", "views": views}))
    src = shared_path("calibration/woodscape/FV.json")
    result = CliRunner().invoke(app, ["refit", str(tmp_path / "dup.json"), "-c", str(src), "-o", str(tmp_path / "fit.json"),
                                      "-r", str(tmp_path / "report.json")])
    assert result.exit_code == 1, result.output
    assert "degenerate" in result.output and "20 points (1 distinct)" in result.output, result.output
    assert "nan" not in result.output.lower()
    assert not (tmp_path / "fit.json").exists() and not (tmp_path / "report.json").exists()


def test_convert_and_refit_write_nothing_their_loader_refuses_or_that_is_not_finite(tmp_path, capsys):
    """The last guard before the files: a calibration that reading back would refuse (fy = 0) or a
    report holding a non-finite number writes neither file (exit status 1), naming the field."""
    import equinox as eqx
    import jax.numpy as jnp
    import typer

    from jaxfish.cameras._kannala_brandt import KannalaBrandt
    from jaxfish.cli._refit import _write_outputs

    good = KannalaBrandt(330.0, 330.0, 640.0, 480.0, [0.01, 0.0, 0.0, 0.0], width=1280, height=966)
    flat = eqx.tree_at(lambda c: c.fy, good, jnp.zeros_like(good.fy))  # as a fit could end: no constructor check
    out, report = tmp_path / "out.json", tmp_path / "report.json"
    for camera, summary, field in ((flat, {"rms_px": 0.1}, "intrinsic.fy"), (good, {"max_px": float("inf")}, "max_px")):
        calib = jf.Calibration("FV", camera, jf.Pose.identity(dtype=np.float64))
        with pytest.raises(typer.Exit) as info:
            _write_outputs(calib, out, report, summary)
        assert info.value.exit_code == 1
        assert f"'{field}'" in capsys.readouterr().err
        assert not out.exists() and not report.exists() and not list(tmp_path.iterdir()), field
    _write_outputs(jf.Calibration("FV", good, jf.Pose.identity(dtype=np.float64)), out, report, {"rms_px": 0.1})
    assert load_camera_calibration(out).name == "FV" and json.loads(report.read_text()) == {"rms_px": 0.1}


def test_convert_refuses_an_error_beyond_max_error_unless_forced(tmp_path):
    """The default domain is the image's valid pixels; SynWoodScape FV -> UCM errs by 3.6 px there:
    nothing written, exit 2, the file, the error and the domain named; --force writes both files and
    the report states the domain in degrees and pixels."""
    src = shared_path("calibration/synwoodscape/FV.json")
    out, rep = tmp_path / "ucm.json", tmp_path / "rep.json"
    runner = CliRunner()
    result = runner.invoke(app, ["convert", str(src), "--to", "ucm", "-o", str(out), "-r", str(rep)])
    assert result.exit_code == 2, result.output
    assert str(src) in result.output and "exceeds --max-error 2 px" in result.output
    assert "1280x966 image's valid pixels (up to 110.6 deg off-axis, 804 px from the principal point)" in result.output
    assert not out.exists() and not rep.exists()
    result = runner.invoke(app, ["convert", str(src), "--to", "ucm", "-o", str(out), "-r", str(rep), "--force"])
    assert result.exit_code == 0, result.output
    report = json.loads(rep.read_text())
    assert report["max_px"] > 2.0 and report["forced"] and report["num_target_invalid"] == 0
    assert report["domain"]["kind"] == "image" and report["domain"]["image_width"] == 1280
    assert report["domain"]["theta_max_deg"] == pytest.approx(110.6, abs=0.1)
    assert report["domain"]["max_radius_px"] == pytest.approx(804.0, abs=2.0)
    assert load_camera_calibration(out).camera.__class__.__name__ == "UnifiedCamera"
    result = runner.invoke(app, ["convert", str(src), "--to", "ucm", "-o", str(out), "--max-error", "5"])
    assert result.exit_code == 0, result.output


def test_convert_to_double_sphere_over_the_image_is_the_global_fit(tmp_path):
    src = shared_path("calibration/synwoodscape/MVR.json")
    out, rep = tmp_path / "ds.json", tmp_path / "rep.json"
    result = CliRunner().invoke(app, ["convert", str(src), "--to", "ds", "-o", str(out), "-r", str(rep)])
    assert result.exit_code == 0, result.output
    report = json.loads(rep.read_text())
    assert report["max_px"] < 2.0 and report["rms_px"] < 0.4 and report["num_starts"] > 1
    assert -0.3 < float(load_camera_calibration(out).camera.xi) < -0.15
