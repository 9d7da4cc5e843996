"""``jaxfish build CAPTURE_DIR OUT_DIR``: a capture in, a SynWoodScape-style dataset out."""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
from collections.abc import Sequence
from pathlib import Path

import typer

from ._app import app, console, fail, note, say


def parse_frames(text: str | None, available: Sequence[int] | None = None, *, source: str = "the capture"
                 ) -> list[int] | None:
    """``"0,2,5-7"`` -> ``[0, 2, 5, 6, 7]``; None / empty -> None (every frame); a text that
    names no frame (``","``) is refused.

    ``available``: the capture's frames (named ``source`` in messages). Every listed frame must be
    one of them, and a range is checked against them before it is expanded (``0-999999999`` names
    the first missing frames instead of building a billion-element list). Bad syntax or a frame
    not available prints ``error: --frames ...`` and exits 2."""
    if not text:
        return None
    spans: list[tuple[int, int]] = []
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        try:
            if "-" in part:
                a, b = (int(v) for v in part.split("-", 1))
                if b < a:
                    raise ValueError
            else:
                a = b = int(part)
        except ValueError as e:
            raise fail(f"--frames: cannot read {part!r} (use e.g. 0,2,5-7)") from e
        spans.append((a, b))
    if not spans:
        raise fail(f"--frames: {text!r} names no frame (use e.g. 0,2,5-7)")
    if available is None:
        return [f for a, b in spans for f in range(a, b + 1)]
    have = set(available)
    out: list[int] = []
    for a, b in spans:
        inside = sorted(f for f in have if a <= f <= b)
        if len(inside) != b - a + 1:  # at least one frame of the span is missing: name the first few
            missing = []
            f = a
            while len(missing) < 6 and f <= b:  # ends within len(inside) + 6 steps
                if f not in have:
                    missing.append(f)
                f += 1
            shown = ", ".join(map(str, missing[:5])) + (" ..." if len(missing) > 5 else "")
            raise fail(f"--frames: {shown} not in {source} (its frames: {_span(sorted(have))})")
        out.extend(inside)
    return out


def _span(frames: list[int]) -> str:
    """``0-9`` for consecutive frames, else up to 8 of them."""
    if frames and list(frames) == list(range(frames[0], frames[-1] + 1)):
        return f"{frames[0]}-{frames[-1]}" if len(frames) > 1 else str(frames[0])
    return ", ".join(map(str, frames[:8])) + (" ..." if len(frames) > 8 else "") if frames else "none"


INTERRUPTED_STATUS = 130
"""Exit status of a build stopped by SIGINT (Ctrl-C) or SIGTERM (128 + SIGINT, the shell's convention)."""


@contextlib.contextmanager
def stop_on_signals():
    """While in the block, the first SIGINT or SIGTERM raises ``KeyboardInterrupt`` in the main
    thread and later ones are ignored, so that the build's stop (ending its workers, removing the
    samples it cut off) runs to its end. A signal ignored on entry (a background job's SIGINT)
    stays ignored; the previous handlers are restored on exit."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    fired: list[int] = []

    def handler(signum, _frame) -> None:
        if not fired:
            fired.append(signum)
            raise KeyboardInterrupt

    previous = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        if signal.getsignal(sig) not in (signal.SIG_IGN, None):
            previous[sig] = signal.signal(sig, handler)
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


def run_build(capture_dir, out_dir: Path, *, frames: list[int] | None, scheduler: str | None,
              workers: int | None, processes: bool | None, backward_flow: bool, bev: bool, write_threads: int,
              motion_threshold_m: float = 0.5, png_level: int = 1, batch_frames: int = 1, rebuild: bool = False,
              shard=None, compile_cache=True):
    """Run `jaxfish.dataset.build_dataset` of ``capture_dir`` (a capture directory or any
    `jaxfish.dataset.FrameSource`) with a rich progress bar (samples/s); returns the report.
    ``shard``: a `jaxfish.dataset.Shard` to build only that shard (`resolve_shard`).
    SIGINT or SIGTERM stops the build (`jaxfish.dataset.BuildInterrupted`): one ``interrupted:``
    line on stderr (then one line per sample that failed before), exit status `INTERRUPTED_STATUS`."""
    try:
        with stop_on_signals():
            return _run_build(capture_dir, out_dir, frames=frames, scheduler=scheduler, workers=workers,
                              processes=processes, backward_flow=backward_flow, bev=bev, write_threads=write_threads,
                              motion_threshold_m=motion_threshold_m, png_level=png_level, batch_frames=batch_frames, rebuild=rebuild,
                              shard=shard, compile_cache=compile_cache)
    except KeyboardInterrupt as e:
        from ..dataset import BuildInterrupted

        done, failed = "", {}
        if isinstance(e, BuildInterrupted):
            done, failed = f"{len(e.complete)} of {len(e.report.samples)} sample(s) complete; ", e.report.failed
        lines = [f"  sample {s} failed: {r}" for s, r in sorted(failed.items())]
        print("\n".join([f"interrupted: {done}run the same command to resume", *lines]), file=sys.stderr, flush=True)
        raise typer.Exit(INTERRUPTED_STATUS) from None


def _run_build(capture_dir, out_dir: Path, *, frames: list[int] | None, scheduler: str | None,
               workers: int | None, processes: bool | None, backward_flow: bool, bev: bool, write_threads: int,
               motion_threshold_m: float, png_level: int, batch_frames: int, rebuild: bool, shard=None,
               compile_cache=True):
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from ..dataset import BuildOptions, as_source, build_dataset

    # ``frames`` were checked against the capture by the caller (`parse_frames`, or the demo's own range)
    frames_ = frames if frames is not None else as_source(capture_dir).frames
    if shard is not None:
        frames_ = shard.select(frames_)
    total = len(frames_)
    options = BuildOptions(backward_flow=backward_flow, bev=bev, motion_threshold_m=motion_threshold_m,
                           png_level=png_level, write_threads=write_threads, batch_frames=batch_frames,
                           compile_cache=_usable_compile_cache(compile_cache))
    from ..dataset import is_complete, sample_id

    complete_before = {sample_id(f) for f in frames_
                       if is_complete(out_dir, sample_id(f))}  # skipped: not counted in the rate
    built = []
    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                  TextColumn("{task.fields[rate]}"), TimeElapsedColumn(), console=console) as bar:
        task = bar.add_task("build", total=total, rate="")

        def tick(sample: str, error: str | None) -> None:
            skipped = error is None and sample in complete_before
            if error is None and not skipped:
                built.append(sample)
            elapsed = bar.tasks[0].elapsed or 0.0
            rate = f"{len(built) / elapsed:.2f} samples/s" if elapsed > 0 and built else bar.tasks[0].fields["rate"]
            state = " [red]failed[/]" if error else " skipped (already complete)" if skipped else ""
            bar.update(task, advance=1, description=f"sample {sample}{state}", rate=rate)

        report = build_dataset(capture_dir, out_dir, frames=frames, options=options, scheduler=scheduler,
                               workers=workers, processes=processes, progress=tick, rebuild=rebuild, shard=shard)
    failures = [f"  sample {s} failed: {r}" for s, r in sorted(report.failed.items())]
    say("\n".join(line for line in report.summary().split("\n") if line not in failures))  # the result: stdout
    for line in failures:  # why samples failed: diagnostics, on stderr
        note(line)
    if shard is not None:
        say(f"shard {shard}: " + (f"complete, record {shard.record_path(out_dir)} written; once every shard is "
                                  f"complete: jaxfish merge {out_dir}" if report.ok else
                                  "not complete (no shard record): run the same command again"))
    return report


def resolve_shard(text: str | None):
    """The `jaxfish.dataset.Shard` of ``--shard`` (``I/N``, or ``all``: the whole build), or when
    ``--shard`` is not given, of the SLURM job array (`jaxfish.dataset.slurm_shard`), else None.
    A bad value prints ``error: ...`` and exits 2."""
    from ..dataset import DatasetError, parse_shard, slurm_shard

    try:
        if text is not None:
            return None if text.strip().lower() == "all" else parse_shard(text)
        return slurm_shard()
    except DatasetError as e:
        raise fail(str(e)) from None


SHARD_HELP = ("Build only shard I of N (e.g. 0/4: the k-th of the sorted frames goes to shard k mod N) into the "
              "shared OUT_DIR, then `jaxfish merge OUT_DIR`; default: the SLURM job array's task "
              "(SLURM_ARRAY_TASK_ID / SLURM_ARRAY_TASK_COUNT) when set; 'all': the whole build.")


def _usable_compile_cache(setting):
    """``setting`` (`jaxfish.dataset.BuildOptions.compile_cache`), or False with a ``warning:`` line
    on stderr when its folder cannot be used: the build goes on without the cache."""
    from ..dataset import compile_cache_folder, compile_cache_problem

    folder = compile_cache_folder(setting)
    problem = None if folder is None else compile_cache_problem(folder)
    if problem is None:
        return setting
    note(f"warning: {problem}; building without it (every process compiles its programs)")
    return False


@app.command()
def build(
    capture_dir: Path = typer.Argument(..., help="Capture directory (docs/capture_layout.md)."),
    out_dir: Path = typer.Argument(..., help="Dataset directory to write (created; an existing build is resumed)."),
    frames: str | None = typer.Option(None, "--frames", "-f", help="Frames to build, e.g. 0,2,5-7 (default: all)."),
    scheduler: str | None = typer.Option(None, "--scheduler", help="Address of a dask.distributed scheduler."),
    workers: int | None = typer.Option(None, "--workers", "-w", help="Build on N local workers."),
    processes: bool | None = typer.Option(
        None, "--processes/--threads",
        help="Local workers as processes (a local dask cluster) or threads of this process "
             "(default: threads for up to 2 workers, processes beyond)."),
    backward_flow: bool = typer.Option(False, "--backward-flow", help="Also write backward flow (t -> t-1)."),
    bev: bool = typer.Option(True, "--bev/--no-bev", help="Build the top-view (BEV) camera's files."),
    write_threads: int = typer.Option(2, "--write-threads", help="Threads writing files (0 = write inline)."),
    motion_threshold_m: float = typer.Option(0.5, "--motion-threshold", help="Motion-mask threshold (metres)."),
    png_level: int = typer.Option(1, "--png-level", min=0, max=9,
                                  help="zlib level of every PNG: 1 fastest; higher levels write smaller PNGs more slowly."),
    batch_frames: int = typer.Option(1, "--batch-frames", min=1,
                                     help="Consecutive samples per batched ground-truth call (one vmapped program on a GPU)."),
    rebuild: bool = typer.Option(False, "--rebuild",
                                 help="Rebuild the samples OUT_DIR holds from another capture or with other options."),
    shard: str | None = typer.Option(None, "--shard", metavar="I/N", help=SHARD_HELP),
    compile_cache: Path | None = typer.Option(
        None, "--compile-cache", metavar="DIR",
        help="Folder of compiled programs shared by the build's processes and later builds "
             "(default: $JAXFISH_COMPILE_CACHE, else $XDG_CACHE_HOME/jaxfish/xla)."),
    no_compile_cache: bool = typer.Option(False, "--no-compile-cache",
                                          help="Compile every program in every process (no cache folder)."),
) -> None:
    """Build a SynWoodScape-style dataset from a capture: every camera's images, depth, semantics,
    instances, motion, flow, events and boxes, plus dataset.json. Resumable (complete samples are
    skipped); a folder whose samples another capture or other options made is refused unless
    --rebuild; exit status 1 when any sample failed (each is listed with its reason). With --shard
    I/N (or in a SLURM job array) only shard I of N, without dataset.json: `jaxfish merge`
    finishes the folder once every shard is complete."""
    if not capture_dir.is_dir():
        raise fail(f"{capture_dir}: capture directory not found")
    if workers is not None and workers < 1:
        raise fail(f"--workers must be at least 1, got {workers}")
    if write_threads < 0:
        raise fail(f"--write-threads must be >= 0, got {write_threads}")
    chosen_shard = resolve_shard(shard)
    chosen = None
    if frames:  # checked against the capture's frames before anything is expanded or written
        from ..io import CaptureReader

        chosen = parse_frames(frames, CaptureReader(capture_dir).frames, source=str(capture_dir / "capture.json"))
    report = run_build(capture_dir, out_dir, frames=chosen, scheduler=scheduler, workers=workers,
                       processes=processes, backward_flow=backward_flow, bev=bev, write_threads=write_threads,
                       motion_threshold_m=motion_threshold_m, png_level=png_level, batch_frames=batch_frames,
                       rebuild=rebuild, shard=chosen_shard,
                       compile_cache=_compile_cache_setting(compile_cache, no_compile_cache))
    if not report.ok:
        raise typer.Exit(1)


def _compile_cache_setting(folder: Path | None, off: bool):
    """`jaxfish.dataset.BuildOptions.compile_cache` of ``--compile-cache DIR`` / ``--no-compile-cache``."""
    if off and folder is not None:
        raise fail("--compile-cache and --no-compile-cache: give one of them")
    return False if off else (folder if folder is not None else True)
