"""One small capture per test process (the demo's settings at scale 0.05: fisheyes 64 x 48, BEV
51 px, 2 frames, seed 1), shared by tests/dataset and tests/cli so that it is rendered once and the
compiled ground-truth functions (same shapes) are reused."""

from __future__ import annotations

import atexit
import functools
import shutil
import tempfile
from pathlib import Path

from jaxfish.cli._demo import demo_config, demo_rig
from jaxfish.dataset import synthesize_capture

SCALE = 0.05
SEED = 1
FRAMES = 2


@functools.lru_cache(maxsize=1)
def small_capture_dir() -> Path:
    """Render (once per process) and return the shared small capture; removed at exit."""
    tmp = Path(tempfile.mkdtemp(prefix="jaxfish_small_capture_"))
    atexit.register(shutil.rmtree, tmp, True)
    return synthesize_capture(tmp / "capture", demo_rig(SCALE), frames=FRAMES, seed=SEED, config=demo_config(SCALE))
