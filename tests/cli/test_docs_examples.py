"""The examples of docs/cli.md run as written: every ``uv run jaxfish ...`` line of its
"Examples, one per command" block, in order, in-process, from a scratch folder (``../shared`` is
the shared test data); a ``> FILE`` redirection receives stdout only."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

from typer.testing import CliRunner

from jaxfish.cli import app
from tests.conftest import shared_path

DOCS = Path(__file__).resolve().parents[2] / "docs" / "cli.md"


def example_commands() -> list[str]:
    """The ``uv run jaxfish`` lines of the first bash block after "## Examples, one per command"."""
    text = DOCS.read_text()
    section = text[text.index("## Examples, one per command"):]
    block = re.search(r"```bash\n(.*?)```", section, flags=re.S).group(1)
    return [line.split("  #")[0].strip() for line in block.splitlines() if line.startswith("uv run jaxfish ")]


def test_every_command_has_an_example():
    names = {shlex.split(c)[3] for c in example_commands()}
    assert names == {"demo", "synth", "build", "bev", "show", "cube2fisheye", "reproject", "refit", "convert"}


def test_the_examples_run_as_written(tmp_path, monkeypatch):
    root = tmp_path / "repo"
    root.mkdir()
    (tmp_path / "shared").symlink_to(shared_path(".").resolve())  # ../shared from the scratch root
    monkeypatch.chdir(root)
    runner = CliRunner()
    outputs = {}
    for command in example_commands():
        words = shlex.split(command)[3:]
        redirect = None
        if ">" in words:
            i = words.index(">")
            words, redirect = words[:i], words[i + 1]
        result = runner.invoke(app, words)
        assert result.exit_code == 0, (command, result.output, result.exception)
        assert "warning:" not in result.stderr, (command, result.stderr)  # no example trips its own warning
        if redirect is not None:
            Path(redirect).write_text(result.stdout)
        outputs.setdefault(words[0], []).append(result)
    out = root / "out"
    resumed = outputs["build"][1].stdout
    assert "0 built, 1 already complete" in resumed and "1 skipped as already complete" in resumed
    assert "samples/s" not in resumed
    assert (out / "FV.png").is_file() and (out / "FV_pinhole.png").is_file() and (out / "bev" / "scores.json").is_file()
    assert (out / "show.png").is_file()
    report = json.loads((out / "fit_report.json").read_text())
    assert report["converged"] and report["rms_px"] < 0.35
    fitted = report["parameters"]
    for k, truth in (("k1", 336.0), ("k2", -24.0), ("k3", 36.0), ("k4", -4.0)):
        assert abs(fitted[k]["value"] - truth) < 5 * fitted[k]["std"], (k, fitted[k])
    kb = (out / "FV_kb.txt").read_text()  # the redirected report: stdout only
    assert kb.startswith("radial_poly -> kannala_brandt") and f"wrote {Path('out/FV_kb.json')}" in kb
    assert json.loads((out / "FV_kb.json").read_text())["intrinsic"]["model"] == "kannala_brandt"
