"""``jaxfish demo OUT``: the README's one-command demo. Renders the embedded street scene with
jaxfish's default rig in memory (`jaxfish.dataset.EmbeddedSource`: no capture files), builds the
dataset in ``OUT/dataset`` and writes one contact sheet per sample to
``OUT/contact_sheets/{sample}.png``; ``--write-capture`` renders to ``OUT/capture`` first and
builds from it (the same dataset bytes).

It writes only into folders it made: ``OUT/capture`` (with ``--write-capture``) must be new, empty
or a capture of the embedded scene (another demo's, rendered anew in place), ``OUT/dataset`` new,
empty or a jaxfish dataset, and none of its folders may be a symbolic link; it deletes no folder."""

from __future__ import annotations

import time
from pathlib import Path

import typer

from ._app import app, console, fail, say


def demo_config(scale: float):
    """The capture settings of the demo at ``scale`` (1 = SynWoodScape's sizes: fisheye 1280 x 966,
    BEV 1024 px at 0.04 m per pixel; 1152-px cube faces: focal 576 px/rad, above the default rig's
    largest radial density, ~555 px/rad, so `jaxfish.reprojection.warn_undersampled_faces` stays quiet;
    `jaxfish.reprojection.cube_face_size`'s 1792 px would also match the tangential density). The
    BEV keeps its ground coverage (metres per pixel grow as its size shrinks)."""
    from ..scene import CaptureConfig

    face = max(16, round(1152 * scale))
    bev = max(16, round(1024 * scale))
    front = max(16, round(1632 * scale))
    return CaptureConfig(face_size=face, bev_size=bev, bev_metres_per_pixel=0.04 * 1024 / bev, front_width=front, front_height=max(12, round(front * 3 / 4)),
                         lidar_channels=32 if scale >= 0.5 else 8, lidar_points_per_channel=1024 if scale >= 0.5 else 128,
                         radar_points=150 if scale >= 0.5 else 32, dvs_substeps=4 if scale >= 0.5 else 2)


def demo_rig(scale: float):
    """jaxfish's default rig, resized by ``scale`` (exact resize of the intrinsics)."""
    import jax.numpy as jnp

    from .. import default_rig

    rig = default_rig()
    if scale == 1.0:
        return rig
    return {k: v.resize(max(16, round(v.camera.width * scale)), max(12, round(v.camera.height * scale))).astype(jnp.float32)
            for k, v in rig.items()}


@app.command()
def demo(
    out: Path = typer.Argument(..., help="Output directory (created): capture/, dataset/, contact_sheets/."),
    frames: int = typer.Option(2, "--frames", "-n", help="Number of samples to render and build."),
    scale: float = typer.Option(0.5, "--scale", help="Size factor of every image (1 = full SynWoodScape size)."),
    seed: int = typer.Option(0, "--seed", "-s", help="Scene seed."),
    workers: int | None = typer.Option(None, "--workers", "-w", help="Build on N local workers (threads up to 2, processes beyond)."),
    write_capture: bool = typer.Option(False, "--write-capture", help="Also write the rendered capture to OUT/capture "
                                       "and build from it (default: the scene goes to the builder in memory)."),
) -> None:
    """Render the embedded street scene, build its SynWoodScape-style dataset and write a contact
    sheet per sample (rows: RGB t-1, RGB t, depth, semantics, instances, motion, flow, events;
    columns: front, rear, top view, left, right)."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from ..dataset import EmbeddedSource, steps_per_frame, synthesize_capture, write_contact_sheet
    from ._build import run_build

    if frames < 1:
        raise fail(f"--frames must be at least 1, got {frames}")
    if not 0.01 <= scale <= 1.0:
        raise fail(f"--scale must lie in [0.01, 1], got {scale}")
    if seed < 0:
        raise fail(f"--seed must be a non-negative integer, got {seed}")
    if workers is not None and workers < 1:
        raise fail(f"--workers must be at least 1, got {workers}")
    start = time.perf_counter()
    rig = demo_rig(scale)
    config = demo_config(scale)
    capture, dataset = out / "capture", out / "dataset"
    _check_demo_folders(capture if write_capture else None, dataset)
    if write_capture:
        rerendered = not _reusable(capture, frames, seed, config.face_size)
        if rerendered:  # a different demo (or none) was here: render this one over it
            with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                          TimeElapsedColumn(), console=console) as bar:
                task = bar.add_task("render", total=frames * steps_per_frame(rig))
                synthesize_capture(capture, rig, frames=frames, seed=seed, config=config,
                                   progress=lambda msg: bar.update(task, advance=1, description=f"render {msg}"))
        source, rebuild = capture, rerendered
    else:
        # Rendered frame by frame as the builder asks (samples already built are not rendered).
        source, rebuild = EmbeddedSource(rig, frames=frames, seed=seed, config=config), _demo_dataset(dataset)
    # A scene rendered anew makes the samples of the one it replaced outdated: rebuild them.
    report = run_build(source, dataset, frames=list(range(frames)), scheduler=None, workers=workers,
                       processes=None, backward_flow=False, bev=True, write_threads=2, rebuild=rebuild)
    for sample in set(report.replaced) - set(report.built):  # the sheet of a sample that is gone
        (out / "contact_sheets" / f"{sample}.png").unlink(missing_ok=True)
    sheets = []
    for sample in report.samples:
        if sample in report.failed:
            continue
        sheets.append(write_contact_sheet(out / "dataset", sample, out / "contact_sheets" / f"{sample}.png"))
    say(f"capture: {capture if write_capture else 'rendered in memory (--write-capture writes it)'}\n"
        f"dataset: {out / 'dataset'} (layout and conventions in dataset.json)\n"
        f"contact sheets: {', '.join(str(p) for p in sheets)}\n"
        f"done in {time.perf_counter() - start:.1f} s")
    if not report.ok:
        raise typer.Exit(1)


def _check_demo_folders(capture: Path | None, dataset: Path) -> None:
    """Refuse (before rendering anything) folders the demo must not write into: a symbolic link
    (it would write into whatever it points to), a capture (when it writes one) that is not the
    embedded scene's (a CARLA recording) or a folder of other files, a dataset folder that is not
    a jaxfish dataset."""
    import json

    from ..dataset import check_output_folder
    from ..io import CaptureError, check_capture_folder

    for path in (capture, dataset, dataset.parent / "contact_sheets"):
        if path is not None and path.is_symlink():
            raise fail(f"{path}: a symbolic link; the demo writes only into folders it makes (use another OUT)")
    check_output_folder(dataset)
    if capture is None:
        return
    check_capture_folder(capture)
    try:
        source = json.loads((capture / "capture.json").read_text()).get("source")
    except (OSError, ValueError, AttributeError):
        return
    if source != "embedded":
        raise CaptureError(f"{capture / 'capture.json'}: a capture of source {source!r}, not one the demo rendered; "
                           f"the demo renders only over its own (use another OUT)")


def _reusable(capture: Path, frames: int, seed: int, face_size: int) -> bool:
    """Whether ``capture`` already holds this demo's frames (same seed and size): then re-running
    the demo resumes instead of rendering again."""
    import json

    try:
        meta = json.loads((capture / "capture.json").read_text())
    except (OSError, ValueError):
        return False
    return (meta.get("seed") == seed and meta.get("face_size") == face_size
            and set(range(frames)) <= set(meta.get("frames", [])))


def _demo_dataset(dataset: Path) -> bool:
    """Whether ``dataset`` is new or a dataset of the embedded scene (a demo's): its samples of
    another seed or size are then rebuilt in place; another dataset's are refused by the build."""
    import json

    try:
        meta = json.loads((dataset / "dataset.json").read_text())
    except (OSError, ValueError):
        return not (dataset / ".done").is_dir() or not any((dataset / ".done").iterdir())
    capture = meta.get("capture") if isinstance(meta, dict) else None
    return isinstance(capture, dict) and capture.get("source") == "embedded"
