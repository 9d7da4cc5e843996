"""Image sizes too large to render: ``reproject`` and ``cube2fisheye`` past their sample budget
(output pixels x ``--supersample``², `jaxfish.cli._reproject.MAX_OUTPUT_SAMPLES`) or a side past
`jaxfish.cameras.MAX_IMAGE_SIDE`, ``synth`` and ``refit`` sizes past that side. Every case is
refused before anything large is allocated: none of them renders."""

from __future__ import annotations

import json
from pathlib import Path

from .corpus import Case, edit_json

SAMPLE = "{shared}/samples/synwoodscape_FV_rgb.png"
REPROJECT = "reproject " + SAMPLE + " -c {calib} -o {tmp}/o.png"
FACES = "{capture}/frames/000000/cameras/FV"
SYNTH = "synth --out {tmp}/cap --face-size 8 --bev-size 8 --front-width 8 --dvs-substeps 1"
SYNTH_BUILD = SYNTH.replace("--out {tmp}/cap", "--build {tmp}/ds")


def _sized_calibration(name: str, width: int, height: int):
    """Setup: ``{tmp}/NAME``, the FV calibration with its image size set to ``width x height``."""

    def setup(tmp: Path) -> None:
        (tmp / name).write_bytes((tmp / "FV.json").read_bytes())
        edit_json(tmp / name, lambda obj: obj["intrinsic"].update(width=width, height=height))

    return setup


def _corr(tmp: Path) -> None:
    """Setup: ``{tmp}/corr.json``, a small board correspondences file (one view, four corners)."""
    view = {"name": "v0", "points": [[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0.1, 0.1, 0]],
            "pixels": [[600, 400], [700, 400], [600, 500], [700, 500]]}
    (tmp / "corr.json").write_text(json.dumps({"frame": "board", "views": [view]}))


CASES = [
    # reproject: the sample budget counts --supersample; --width/--height also per side
    Case("sizes-reproject-supersample-over-budget", REPROJECT + " --width 16384 --height 16384 --supersample 16",
         says=("--supersample 16", "--width/--height 16384x16384", "268435456"), absent=("{tmp}/o.png",)),
    Case("sizes-reproject-width-over-side", REPROJECT + " --width 70000 --height 8", says=("--width", "65536"),
         absent=("{tmp}/o.png",)),
    Case("sizes-reproject-target-calibration-over-budget",
         REPROJECT + " --to fisheye --target-calibration {tmp}/huge.json", setup=_sized_calibration("huge.json", 60000, 60000),
         says=("huge.json", "intrinsic.width/height 60000x60000", "268435456"), absent=("{tmp}/o.png",)),
    Case("sizes-reproject-target-size-options-over-budget",
         REPROJECT + " --to fisheye --target-calibration {calib} --width 60000 --height 60000",
         says=("--width/--height 60000x60000", "268435456"), absent=("{tmp}/o.png",)),
    Case("sizes-reproject-supersample-within-budget", REPROJECT + " --width 64 --height 48 --supersample 16", exit=0,
         stdout_says=("pinhole 64x48",)),
    # cube2fisheye: the fisheye calibration's image size at --supersample
    Case("sizes-cube2fisheye-calibration-over-budget", "cube2fisheye --faces " + FACES + " -c {tmp}/huge.json -o {tmp}/o.png",
         setup=_sized_calibration("huge.json", 60000, 60000),
         says=("huge.json", "intrinsic.width/height 60000x60000", "268435456"), absent=("{tmp}/o.png",)),
    Case("sizes-cube2fisheye-supersample-over-budget",
         "cube2fisheye --faces " + FACES + " -c {tmp}/big.json -o {tmp}/o.png --supersample 16",
         setup=_sized_calibration("big.json", 4096, 4096),
         says=("big.json", "intrinsic.width/height 4096x4096", "--supersample 16"), absent=("{tmp}/o.png",)),
    # synth: every rendered side at most MAX_IMAGE_SIDE, checked before the capture folder is made
    Case("sizes-synth-face-size-over-side", SYNTH.replace("--face-size 8", "--face-size 1000000"),
         says=("--face-size", "65536"), absent=("{tmp}/cap",)),
    Case("sizes-synth-bev-size-over-side", SYNTH.replace("--bev-size 8", "--bev-size 100000"),
         says=("--bev-size", "65536"), absent=("{tmp}/cap",)),
    Case("sizes-synth-front-width-over-side", SYNTH.replace("--front-width 8", "--front-width 100000"),
         says=("--front-width", "65536"), absent=("{tmp}/cap",)),
    Case("sizes-synth-build-face-size-over-side", SYNTH_BUILD.replace("--face-size 8", "--face-size 1000000"),
         says=("--face-size", "65536"), absent=("{tmp}/ds",)),
    # refit without --calibration: the image size of the initial camera
    Case("sizes-refit-width-over-side", "refit {tmp}/corr.json --model kb --width 100000 --height 966 -o {tmp}/o.json",
         setup=_corr, says=("--width", "100000", "65536"), absent=("{tmp}/o.json",)),
    Case("sizes-refit-height-over-side", "refit {tmp}/corr.json --model kb --width 1280 --height 70000 -o {tmp}/o.json",
         setup=_corr, says=("--height", "70000", "65536"), absent=("{tmp}/o.json",)),
]

def _embedded_frames_over_limit(tmp: Path):
    from jaxfish.cli._demo import demo_rig
    from jaxfish.dataset import EmbeddedSource

    return EmbeddedSource(demo_rig(0.05), frames=10**12)


CASES += [
    Case("sizes-synth-frames-over-limit", "synth --out {tmp}/cap --frames 1000000000000 --face-size 8",
         says=("--frames", "10000000"), absent=("{tmp}/cap",)),
    Case("sizes-embedded-source-frames-over-limit", call=_embedded_frames_over_limit, says=("frames", "10000000")),
]
