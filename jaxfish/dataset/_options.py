"""What a build is asked to do and what it reports (`BuildOptions`, `BuildReport`), and its errors."""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path
from typing import Any

from .._errors import JaxfishError

DONE_DIR = ".done"
"""Folder of the per-sample completion markers."""


_NO_VALUE = object()


class DatasetError(JaxfishError):
    """A dataset build cannot start or a sample cannot be built (names the file and the reason)."""


class BuildInterrupted(KeyboardInterrupt):
    """`build_dataset` stopped by a ``KeyboardInterrupt`` (Ctrl-C; ``jaxfish build`` turns SIGTERM
    into one too). Its local workers have ended before it is raised and the files of the samples
    it cut off are removed, so complete samples stay and re-running the same build resumes.
    ``report``: the `BuildReport` so far; ``complete``: the requested samples that are complete."""

    def __init__(self, report: BuildReport, complete: list[str]):
        super().__init__(f"build interrupted: {len(complete)} of {len(report.samples)} sample(s) complete")
        self.report = report
        self.complete = complete


@dataclasses.dataclass(frozen=True)
class BuildOptions:
    """What a build computes (every option changes the bytes of some file, so `dataset.json`
    records them): ``backward_flow`` also writes ``optical_flow_backward`` (t -> t-1 on the t
    grid); ``bev`` builds the top-view camera's files when the capture has one;
    ``motion_threshold_m`` is the motion-mask threshold on the actor displacement;
    ``png_level`` is the zlib level (0-9) of every PNG (1: the fastest; higher levels write smaller
    PNGs more slowly, see docs/performance.md); ``write_threads`` writes a sample's files in a pool
    of that many threads (0 = inline); ``tune_allocator`` applies `tune_allocator` in the processes
    that build samples (on by default: the ground truth's programs then reuse their buffers instead
    of page-faulting fresh mappings, for a higher peak of memory, see docs/performance.md; False
    leaves glibc's allocator as it is, except in a process whose environment sets
    ``MALLOC_TRIM_THRESHOLD_``, as dask's nannies do, where glibc's dynamic mmap threshold is
    already off and tuning is always applied); ``batch_frames``
    computes the fisheye ground truth of that many consecutive samples in one batched call
    (`build_samples`; one dask task each): no faster on CPU, where the cameras and frames are
    looped anyway, but one wide `jax.vmap` program on an accelerator; it holds that many samples in
    memory (~0.5 GB each at full size). ``compile_cache`` is the folder of JAX's persistent
    compilation cache that every process of the build (the serial build's, each dask worker)
    writes its compiled programs to and loads them from (`jaxfish.dataset.use_compile_cache`):
    True (the default) for `jaxfish.dataset.default_compile_cache`, which each process resolves
    for itself, a path for that folder, False for none (every process compiles its programs)."""

    backward_flow: bool = False
    bev: bool = True
    motion_threshold_m: float = 0.5
    png_level: int = 1
    write_threads: int = 2
    tune_allocator: bool = True
    batch_frames: int = 1
    compile_cache: bool | str | os.PathLike = True

    def __post_init__(self) -> None:
        from ..io._images import is_png_level

        if not is_png_level(self.png_level):
            raise DatasetError(f"BuildOptions: png_level must be an integer from 0 to 9, got {self.png_level!r}")
        if self.write_threads < 0:
            raise DatasetError(f"BuildOptions: write_threads must be >= 0, got {self.write_threads}")
        if not isinstance(self.batch_frames, int) or self.batch_frames < 1:
            raise DatasetError(f"BuildOptions: batch_frames must be an integer >= 1, got {self.batch_frames!r}")
        cache = self.compile_cache
        if not isinstance(cache, (bool, str, os.PathLike)) or (isinstance(cache, str) and not cache.strip()):
            raise DatasetError(f"BuildOptions: compile_cache must be True, False or a folder, got {cache!r}")
        m = self.motion_threshold_m
        if isinstance(m, bool) or not isinstance(m, (int, float)) or not math.isfinite(m) or m < 0:
            raise DatasetError(f"BuildOptions: motion_threshold_m must be a finite number of metres >= 0, got {m!r}")

    def ground_truth(self):
        """The `jaxfish.pipeline.GroundTruthOptions` of this build."""
        from ..pipeline import GroundTruthOptions

        return GroundTruthOptions(backward_flow=self.backward_flow, motion_threshold_m=self.motion_threshold_m,
                                  bev=self.bev)

    def to_dict(self) -> dict[str, Any]:
        """The options that shape the output (``write_threads``, ``tune_allocator``,
        ``compile_cache`` and, on CPU, ``batch_frames`` do not): recorded in ``dataset.json`` and in every completion marker."""
        return {"backward_flow": self.backward_flow, "bev": self.bev, "motion_threshold_m": self.motion_threshold_m,
                "png_level": self.png_level}


@dataclasses.dataclass
class BuildReport:
    """What a build did: the requested ``samples`` (ids), those ``built`` now, ``skipped``
    (complete from an earlier run), ``failed`` ``{sample: reason}``, ``replaced`` (samples another
    capture or other options had made, whose files ``rebuild=True`` removed first; those requested
    are in ``built``), the number of temporary files of killed runs removed, the wall time and the
    rate of built samples per second. ``ok`` is True when nothing failed."""

    out_dir: Path
    samples: list[str]
    built: list[str] = dataclasses.field(default_factory=list)
    skipped: list[str] = dataclasses.field(default_factory=list)
    failed: dict[str, str] = dataclasses.field(default_factory=dict)
    seconds: float = 0.0
    stale_removed: int = 0
    replaced: list[str] = dataclasses.field(default_factory=list)

    @property
    def ok(self) -> bool:
        """True when no sample failed."""
        return not self.failed

    @property
    def samples_per_second(self) -> float:
        """Built samples per second of wall time (0 when nothing was built)."""
        return len(self.built) / self.seconds if self.seconds > 0 and self.built else 0.0

    def summary(self) -> str:
        """One paragraph: counts, the rate of the samples built (or, when none was built, how many
        were skipped as already complete), and one line per failed sample with its reason."""
        skipped = f"{len(self.skipped)} skipped as already complete"
        if self.built:
            rate = f"{self.samples_per_second:.2f} samples/s" + (f"; {skipped}" if self.skipped else "")
        else:
            rate = f"none built; {skipped}" if self.skipped else "none built"
        lines = [f"{len(self.built)} built, {len(self.skipped)} already complete, {len(self.failed)} failed "
                 f"of {len(self.samples)} sample(s) in {self.seconds:.1f} s ({rate}) -> {self.out_dir}"]
        if self.replaced:
            lines.append(f"  {len(self.replaced)} sample(s) made from another capture or with other options "
                         f"were removed first (rebuild): {sample_span(self.replaced)}")
        lines += [f"  sample {s} failed: {r}" for s, r in sorted(self.failed.items())]
        return "\n".join(lines)



def sample_span(samples) -> str:
    """The first five of ``samples`` (sorted), comma-separated, and how many more."""
    samples = sorted(samples)
    return ", ".join(samples[:5]) + (f" and {len(samples) - 5} more" if len(samples) > 5 else "")
