"""The typer application shared by every sub-command module, and error reporting."""

from __future__ import annotations

import sys

import typer
from rich.console import Console

app = typer.Typer(
    name="jaxfish",
    help="jaxfish: surround-view fisheye reprojection, ground truth and datasets in JAX.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
console = Console(stderr=True)


def fail(message: str, code: int = 2) -> typer.Exit:
    """Print ``error: message`` to stderr and return an exit exception (``raise fail(...)``)."""
    console.print(f"[bold red]error:[/] {message}", highlight=False)
    return typer.Exit(code)


def main() -> None:
    """Console-script entry point: expected input errors become one clear line and exit code 2."""
    from .._errors import JaxfishError

    try:
        app()
    except (JaxfishError, FileNotFoundError, IsADirectoryError, PermissionError) as e:
        console.print(f"[bold red]error:[/] {e}", highlight=False)
        sys.exit(2)


@app.callback()
def _root() -> None:
    """jaxfish: surround-view fisheye reprojection, ground truth and datasets in JAX."""
