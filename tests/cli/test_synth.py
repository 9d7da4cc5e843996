import json

import jax.numpy as jnp
from typer.testing import CliRunner

import jaxfish as jf
from jaxfish.cli import app


def test_synth_writes_a_capture_with_a_given_rig(tmp_path):
    rig = {k: v.resize(64, 48).astype(jnp.float32) for k, v in jf.default_rig().items() if k == "RV"}
    jf.save_rig(rig, tmp_path / "rig")
    out = tmp_path / "cap"
    args = ["synth", "--out", str(out), "--frames", "1", "--seed", "2", "--face-size", "32", "--rig", str(tmp_path / "rig"),
            "--bev-size", "32", "--front-width", "32", "--dvs-substeps", "1"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    header = json.loads((out / "capture.json").read_text())
    assert header["cameras"] == ["RV"] and header["frames"] == [0] and header["seed"] == 2
    assert (out / "frames" / "000000" / "cameras" / "RV" / "left" / "depth_curr.png").is_file()


def test_synth_rejects_bad_options(tmp_path):
    result = CliRunner().invoke(app, ["synth", "--out", str(tmp_path / "x"), "--frames", "0"])
    assert result.exit_code == 2
    assert "--frames" in result.output
