"""``jaxfish merge FOLDER``: finish a dataset (or a capture) that ``--shard I/N`` runs wrote."""

from __future__ import annotations

from pathlib import Path

import typer

from ._app import app, fail, say


@app.command()
def merge(
    folder: Path = typer.Argument(..., help="Dataset (or capture) folder the shards wrote into."),
    capture: Path | None = typer.Option(None, "--capture", help="The capture the shards were built from "
                                        "(default: the path their records name)."),
    verify: bool = typer.Option(False, "--verify", help="Also check every sample file's digest (BLAKE3; SHA-256 in older markers) against its marker."),
) -> None:
    """Check that every shard of a `jaxfish build --shard I/N` (or `jaxfish synth --shard I/N`)
    split has finished (all N shard records in .shards/, one N, the same frames, options and
    capture, every listed sample complete), then write dataset.json (capture.json's frame list) as
    one whole run would: the folder then holds the bytes of one build. Exit status 2, naming the
    missing shard, sample or mismatch, without writing anything, when a shard is missing,
    incomplete or from another build."""
    from ..dataset import merge_shards

    if not folder.is_dir():
        raise fail(f"{folder}: not a folder")
    if capture is not None and not capture.is_dir():
        raise fail(f"--capture {capture}: capture directory not found")
    report = merge_shards(folder, source=capture, verify=verify)
    say(report.summary())
