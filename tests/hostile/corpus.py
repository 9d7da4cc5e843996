"""The hostile-input corpus: one `Case` per hostile input, run in-process through the CLI's real
entry point (`jaxfish.cli.main`) or as a library call.

A case joins the corpus in one line of a ``cases_*.py`` module of this folder (a ``CASES`` list)::

    Case("build-frames-huge", "build {capture} {tmp}/out --frames 0-999999999", says=("--frames",)),

Placeholders in a CLI command line: ``{tmp}`` (the case's own empty folder), ``{capture}`` (a fresh
copy of the small test capture, under ``{tmp}/capture``, made only when named), ``{calib}`` (a copy
of the real SynWoodScape FV calibration at ``{tmp}/FV.json``, made only when named). A ``setup``
runs after the copies and before the command, with the case's folder; it breaks the input.

What every CLI case asserts: the exit status (2 by default: bad input), no Python traceback on
either stream, every ``says`` substring on stderr, nothing left whose name marks it half-written
(``*.part*``, ``.tmp*``) and none of the ``absent`` paths created. A library case (``call``)
asserts that the call raises ``raises`` (a `jaxfish.JaxfishError` by default) with every ``says``
substring in its message, or, with ``raises=None``, that it returns and ``check`` accepts the result.
"""

from __future__ import annotations

import json
import os
import shlex
import shutil
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

SHARED = Path(__file__).resolve().parents[2].parent / "shared"
FV_CALIBRATION = SHARED / "calibration" / "synwoodscape" / "FV.json"


@dataclass(frozen=True)
class Case:
    """One hostile input and what jaxfish must do with it (see the module docstring)."""

    id: str
    command: str | None = None
    """A CLI command line after ``jaxfish`` (placeholders allowed); or None for a library case."""
    setup: Callable[[Path], None] | None = None
    exit: int = 2
    says: tuple[str, ...] = ()
    absent: tuple[str, ...] = ()
    """Paths (placeholders allowed) that must not exist after the run: nothing half-written."""
    call: Callable[[Path], Any] | None = None
    raises: type[BaseException] | None | str = "JaxfishError"
    check: Callable[[Any], bool] | None = None
    stdout_says: tuple[str, ...] = ()
    kept: tuple[str, ...] = ()
    """Paths (placeholders allowed) that must still exist after the run: the user's files."""
    env: tuple[tuple[str, str], ...] = ()
    """Environment variables ``(name, value)`` set while a CLI case runs (restored after it)."""


def edit_json(path: Path, edit: Callable[[Any], Any]) -> None:
    """Rewrite the JSON file ``path`` with ``edit(obj)`` (which may mutate and return None)."""
    obj = json.loads(path.read_text())
    new = edit(obj)
    path.write_text(json.dumps(obj if new is None else new))


def json_text(path: Path, text: str) -> None:
    """Write raw (possibly invalid or huge) JSON text."""
    path.write_text(text)


def prepare(case: Case, tmp: Path) -> dict[str, str]:
    """Make the copies a case names and run its setup; returns the placeholder values."""
    from tests.dataset.small_capture import small_capture_dir

    text = case.command or ""
    values = {"tmp": str(tmp), "shared": str(SHARED)}
    if "{capture}" in text or case.call is not None or case.setup is not None:
        cap = tmp / "capture"
        if not cap.exists():
            shutil.copytree(small_capture_dir(), cap)
        values["capture"] = str(cap)
    if FV_CALIBRATION.exists():
        shutil.copyfile(FV_CALIBRATION, tmp / "FV.json")
        values["calib"] = str(tmp / "FV.json")
    elif "{calib}" in text:
        import pytest

        pytest.skip(f"{FV_CALIBRATION} not found: the real calibrations live in ../shared beside the checkout")
    if case.setup is not None:
        case.setup(tmp)
    return values


def run_cli(argv: list[str], capsys) -> tuple[int, str, str]:
    """``jaxfish ARGV`` in this process through the console-script entry point: (exit, out, err).
    An exception other than SystemExit escaping it is a traceback, and is re-raised."""
    from jaxfish.cli import main

    old = sys.argv
    sys.argv = ["jaxfish", *argv]
    code: int = 0
    try:
        main()
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    finally:
        sys.argv = old
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def half_written(root: Path) -> list[Path]:
    """Files under ``root`` whose names mark an unfinished write."""
    return [p for p in root.rglob("*") if ".part" in p.name or p.name.startswith(".tmp")]


def run_case(case: Case, tmp: Path, capsys) -> None:
    """Run one case and assert its contract (see the module docstring)."""
    import jaxfish

    values = prepare(case, tmp)
    if case.command is not None:
        argv = [a.format(**values) for a in shlex.split(case.command)]
        saved = {name: os.environ.get(name) for name, _ in case.env}
        os.environ.update(dict(case.env))
        try:
            code, out, err = run_cli(argv, capsys)
        finally:
            for name, value in saved.items():
                if value is None:
                    os.environ.pop(name, None)
                else:
                    os.environ[name] = value
        assert "Traceback" not in err and "Traceback" not in out, err[-3000:]
        assert code == case.exit, f"exit {code}, expected {case.exit}\nstdout: {out[-2000:]}\nstderr: {err[-2000:]}"
        for text in case.says:
            assert text.format(**values) in err, f"{text!r} not on stderr: {err[-2000:]}"
        for text in case.stdout_says:
            assert text.format(**values) in out, f"{text!r} not on stdout: {out[-2000:]}"
    else:
        assert case.call is not None, f"case {case.id}: give a command or a call"
        expected = getattr(jaxfish, case.raises) if isinstance(case.raises, str) else case.raises
        if expected is None:
            result = case.call(tmp)
            assert case.check is None or case.check(result), f"case {case.id}: unexpected result {result!r}"
        else:
            import pytest

            with pytest.raises(expected) as info:
                case.call(tmp)
            for text in case.says:
                assert text.format(**values) in str(info.value), f"{text!r} not in {info.value}"
    assert not half_written(tmp), half_written(tmp)
    for path in case.absent:
        assert not Path(path.format(**values)).exists(), path
    for path in case.kept:
        assert Path(path.format(**values)).exists(), path
