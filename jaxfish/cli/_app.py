"""The typer application shared by every sub-command module, and error reporting."""

from __future__ import annotations

import sys

import typer
from rich.console import Console
from rich.markup import escape

app = typer.Typer(
    name="jaxfish",
    help="jaxfish: surround-view fisheye reprojection, ground truth and datasets in JAX.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
console = Console(stderr=True)
"""stderr: progress bars, warnings, errors and other diagnostics."""
results = Console(stderr=False)
"""stdout: what a command produces (written paths, summaries, reports), so ``jaxfish convert ... >
report.txt`` keeps only the report."""


def print_error(message: object) -> None:
    """``error: message`` on one line of stderr: never hard-wrapped at 80 columns (rich's width
    without a terminal: logs and pipes would split paths), never read as rich markup."""
    console.print(f"[bold red]error:[/] {escape(str(message))}", highlight=False, soft_wrap=True)


def say(text: object) -> None:
    """A result line (written paths, summaries, numbers) on stdout: like `print_error`, never
    hard-wrapped at 80 columns and never read as rich markup (a path may hold ``[...]``)."""
    results.print(str(text), highlight=False, markup=False, soft_wrap=True)


def note(text: object) -> None:
    """A diagnostic line on stderr (not a result), with `say`'s no-wrap, no-markup guarantees."""
    console.print(str(text), highlight=False, markup=False, soft_wrap=True)


def print_warning(message: object) -> None:
    """``warning: message`` on one line of stderr (the command goes on)."""
    console.print(f"[bold yellow]warning:[/] {escape(str(message))}", highlight=False, soft_wrap=True)


def warn_undersampled(face_size: int, cameras: dict) -> None:
    """``warning: ...`` on stderr when ``face_size``-px cube faces undersample one of ``cameras``
    (``{name: camera}``; `jaxfish.reprojection.warn_undersampled_faces`, CONVENTIONS §7)."""
    import warnings

    from ..reprojection import UndersampledFacesWarning, warn_undersampled_faces

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UndersampledFacesWarning)
        message = warn_undersampled_faces(face_size, cameras)
    if message:
        print_warning(message)


def fail(message: str, code: int = 2) -> typer.Exit:
    """Print ``error: message`` to stderr and return an exit exception (``raise fail(...)``)."""
    print_error(message)
    return typer.Exit(code)


def check_outputs(directories: tuple[str, ...] = (), **paths: object) -> None:
    """Refuse, before any work, output paths (options by name, None: not given) that are
    directories (``--out DIR`` would fail only at the end, after other outputs were written),
    except the options named in ``directories``, and two options naming the same file (the second
    write would replace the first)."""
    from pathlib import Path

    given = {option: Path(str(path)) for option, path in paths.items() if path is not None}
    for option, path in given.items():
        if option not in directories and path.is_dir():
            raise fail(f"--{option.replace('_', '-')} {path}: is a directory, expected a file path")
    seen: dict[Path, str] = {}
    for option, path in given.items():
        key = path.resolve()
        if key in seen:
            raise fail(f"--{option.replace('_', '-')} {path}: the same file as --{seen[key].replace('_', '-')}; "
                       f"give each output its own path")
        seen[key] = option


def main() -> None:
    """Console-script entry point: expected input errors become one clear line and exit code 2."""
    from .._errors import JaxfishError

    try:
        app()
    except (JaxfishError, OSError) as e:  # a missing, existing, unreadable or unwritable path
        if isinstance(e, OSError) and not isinstance(e, JaxfishError) and e.filename is not None and e.strerror:
            print_error(f"{e.filename}: {e.strerror}")  # not Python's "[Errno 17] File exists: 'path'"
        else:
            print_error(e)
        sys.exit(2)


@app.callback()
def _root() -> None:
    """jaxfish: surround-view fisheye reprojection, ground truth and datasets in JAX."""
