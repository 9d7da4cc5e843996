"""``jaxfish synth --out CAPTURE_DIR``: render the embedded street scene as a CARLA-style capture;
``jaxfish synth --build DATASET_DIR``: render it in memory straight into the dataset builder (no
capture files; the same dataset bytes as ``synth --out`` then ``build``)."""

from __future__ import annotations

import time
from pathlib import Path

import typer

from ._app import app, console, fail, say, warn_undersampled


@app.command()
def synth(
    out: Path | None = typer.Option(None, "--out", "-o", help="Capture directory to write (created)."),
    build: Path | None = typer.Option(None, "--build", help="Dataset directory to build directly from the scene "
                                      "rendered in memory (no capture written; resumable like jaxfish build)."),
    workers: int | None = typer.Option(None, "--workers", "-w", help="With --build: N local workers (threads up to 2, processes beyond)."),
    frames: int = typer.Option(1, "--frames", "-n", help="Number of frames (each with its t-1 instant)."),
    seed: int = typer.Option(0, "--seed", "-s", help="Scene seed (the same seed gives the same capture)."),
    face_size: int = typer.Option(1152, "--face-size", help="Cube face size in pixels (90-degree faces, 8 to 65536); a size "
                                  "that undersamples the rig's fisheyes is warned about."),
    rig_dir: Path | None = typer.Option(None, "--rig", help="Calibration directory (default: jaxfish's own rig)."),
    bev_size: int = typer.Option(1024, "--bev-size", help="BEV top-view image size in pixels (8 to 65536)."),
    front_width: int = typer.Option(1632, "--front-width", help="Front perspective camera width in pixels (4:3, 8 to 65536)."),
    dvs_substeps: int = typer.Option(4, "--dvs-substeps", help="Sub-frames between t-1 and t for DVS events."),
    shard: str | None = typer.Option(None, "--shard", metavar="I/N", help="Render (or with --build, build) only "
                                     "shard I of N of the frames (frame k when k mod N = I), then `jaxfish merge` the "
                                     "folder; default: the SLURM job array's task when set; 'all': every frame."),
    texture: bool = typer.Option(False, "--texture", help="Give every material procedural surface detail (grain, "
                                 "blotches, colour variation): RGB with the PNG statistics of a CARLA render, "
                                 "for realistic benchmarks. Labels, depth and motion are the same."),
) -> None:
    """Render the embedded procedural street scene as a CARLA-style capture (layout:
    docs/capture_layout.md), or with --build straight into a SynWoodScape-style dataset. Every
    frame is a function of the seed and its number: --shard I/N runs render the same frames as
    one run, and `jaxfish merge` then lists them in capture.json (or writes dataset.json)."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from .. import default_rig, load_rig
    from ..cameras import MAX_IMAGE_SIDE
    from ..dataset import MAX_FRAMES, rig_names, steps_per_frame, synthesize_capture
    from ..scene import CaptureConfig
    from ._build import resolve_shard

    if (out is None) == (build is None):
        raise fail("give exactly one of --out CAPTURE_DIR (write a capture) and --build DATASET_DIR (build in memory)")
    if workers is not None and (build is None or workers < 1):
        raise fail("--workers needs --build and must be at least 1")
    if not 1 <= frames <= MAX_FRAMES:
        raise fail(f"--frames must be from 1 to {MAX_FRAMES}, got {frames}")
    if seed < 0:
        raise fail(f"--seed must be a non-negative integer, got {seed}")
    for option, size in (("--face-size", face_size), ("--bev-size", bev_size), ("--front-width", front_width)):
        if not 8 <= size <= MAX_IMAGE_SIDE:  # checked before anything is written: a camera refuses a larger side
            raise fail(f"{option} must be from 8 to {MAX_IMAGE_SIDE} pixels, got {size}")
    if dvs_substeps < 1:
        raise fail(f"--dvs-substeps must be at least 1, got {dvs_substeps}")
    chosen_shard = resolve_shard(shard)
    if rig_dir is not None:
        if not rig_dir.is_dir() or not rig_names(rig_dir):
            raise fail(f"{rig_dir}: not a directory of calibration JSON files")
        rig = load_rig(rig_dir, names=rig_names(rig_dir))
    else:
        rig = default_rig()
    warn_undersampled(face_size, {name: calib.camera for name, calib in rig.items()})
    config = CaptureConfig(face_size=face_size, bev_size=bev_size, front_width=front_width,
                           front_height=max(1, round(front_width * 3 / 4)), dvs_substeps=dvs_substeps,
                           textured=texture)
    start = time.perf_counter()
    if build is not None:
        from ..dataset import EmbeddedSource
        from ._build import run_build

        report = run_build(EmbeddedSource(rig, frames=frames, seed=seed, config=config), build,
                           frames=list(range(frames)), scheduler=None, workers=workers, processes=None,
                           backward_flow=False, bev=True, write_threads=2, shard=chosen_shard)
        if not report.ok:
            raise typer.Exit(1)
        return
    with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                  TimeElapsedColumn(), console=console, transient=False) as bar:
        own = len(chosen_shard.select(range(frames))) if chosen_shard is not None else frames
        task = bar.add_task("synth", total=own * steps_per_frame(rig))
        synthesize_capture(out, rig, frames=frames, seed=seed, config=config, shard=chosen_shard,
                           progress=lambda msg: bar.update(task, advance=1, description=msg))
    if chosen_shard is None:
        say(f"wrote {frames} frame(s) to {out} in {time.perf_counter() - start:.1f} s")
        return
    say(f"shard {chosen_shard}: wrote {own} of {frames} frame(s) to {out} in {time.perf_counter() - start:.1f} s; "
        f"once every shard is complete: jaxfish merge {out}")
