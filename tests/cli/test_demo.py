from typer.testing import CliRunner

from jaxfish.cli import app


def test_demo_writes_theta_maps_and_rig(tmp_path):
    result = CliRunner().invoke(app, ["demo", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    for name in ("FV", "MVL", "MVR", "RV"):
        assert (tmp_path / "out" / f"theta_{name}.png").is_file()
        assert (tmp_path / "out" / "calibration" / f"{name}.json").is_file()
