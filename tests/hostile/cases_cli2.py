"""CLI streams, ``refit --example`` and undersized cube faces (issue #21 items 9-11)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .corpus import Case


def _tiny_faces(tmp: Path) -> None:
    """8-px cube faces for a full-size 1280 x 966 fisheye: grossly undersampled."""
    from jaxfish.io import write_image
    from jaxfish.reprojection import FIVE_FACES

    (tmp / "faces").mkdir()
    for i, name in enumerate(FIVE_FACES):
        write_image(tmp / "faces" / f"{name}.png", np.full((8, 8, 3), 30 * i, np.uint8))


CASES = [
    Case("cli-refit-example-into-directory", "refit --example {tmp}", says=("--example", "is a directory")),
    Case("cli-refit-example-without-path", "refit --example", says=("--example",)),
    Case("cli-refit-example-ignores-other-options", "refit --example {tmp}/c.json --loss nonsense", exit=0,
         stdout_says=("wrote {tmp}/c.json",)),
    Case("cli-cube2fisheye-undersized-faces-warn", "cube2fisheye --faces {tmp}/faces -c {calib} -o {tmp}/f.png",
         setup=_tiny_faces, exit=0, says=("warning:", "cube_face_size"), stdout_says=("wrote {tmp}/f.png",)),
    Case("cli-synth-undersized-faces-warn", "synth --out {tmp}/cap --face-size 8 --bev-size 8 --front-width 8 "
         "--dvs-substeps 1", exit=0, says=("warning:", "cube_face_size"), stdout_says=("wrote 1 frame(s)",)),
    Case("cli-convert-report-on-stdout", "convert {calib} --to kb --out {tmp}/kb.json", exit=0,
         stdout_says=("radial_poly -> kannala_brandt", "wrote {tmp}/kb.json")),
]
