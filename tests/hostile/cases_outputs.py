"""Hostile output paths and selections: two outputs naming one file, a report that cannot be
written after the main output, a camera name a one-camera calibration does not have, and
selections that name nothing."""

from __future__ import annotations

from pathlib import Path

from .cases_show import OUT, _mini
from .corpus import Case


def _a_file_named_notafile(tmp: Path) -> None:
    (tmp / "notafile").write_text("a file, not a folder")


CASES = [
    Case("convert-out-is-the-report", "convert {calib} --to kb -o {tmp}/x.json -r {tmp}/./x.json",
         says=("--report", "the same file as --out"), absent=("{tmp}/x.json",)),
    Case("export-out-is-the-report", "export {calib} --format kalibr --out {tmp}/a.yaml -r {tmp}/a.yaml",
         says=("--report", "the same file as --out"), absent=("{tmp}/a.yaml",)),
    Case("export-report-unwritable", "export {calib} --format kalibr --out {tmp}/a.yaml -r {tmp}/notafile/r.json",
         setup=_a_file_named_notafile, says=("--report", "notafile", "not written either"), absent=("{tmp}/a.yaml",)),
    Case("convert-camera-name-not-in-the-file", "convert {calib}::NOPE --to kb -o {tmp}/n.json",
         says=("FV.json", "no camera 'NOPE'"), absent=("{tmp}/n.json",)),
    Case("export-camera-name-not-in-the-file", "export {calib}::RV --format kalibr --out {tmp}/a.yaml",
         says=("FV.json", "no camera 'RV'"), absent=("{tmp}/a.yaml",)),
    Case("show-sample-a-unicode-digit", "show {tmp}/ds ² --out {tmp}/o.png", setup=_mini, says=("SAMPLE", "'²'"),
         absent=OUT),
    Case("show-sample-thousands-of-digits", "show {tmp}/ds " + "9" * 5000 + " --out {tmp}/o.png", setup=_mini,
         says=("SAMPLE",), absent=OUT),
    Case("build-frames-name-none", "build {capture} {tmp}/out --frames ,", says=("--frames", "names no frame"),
         absent=("{tmp}/out/dataset.json",)),
    Case("bev-frames-name-none", "bev {capture} --out {tmp}/b --frames ' , '", says=("--frames", "names no frame"),
         absent=("{tmp}/b/scores.json",)),
]
