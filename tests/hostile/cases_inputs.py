"""Hostile values that parse as JSON but mean nothing: numbers written as strings in
correspondences, two views of one name, a capture listing a camera twice."""

from __future__ import annotations

import json
from pathlib import Path

from .corpus import Case, edit_json

_PTS = [[0.1 * i, 0.2, 1.0] for i in range(20)]
_PIX = [[700.0 + i, 500.0] for i in range(20)]


def _views(*views: dict):
    def setup(tmp: Path) -> None:
        (tmp / "c.json").write_text(json.dumps({"frame": "camera", "views": list(views)}))
    return setup


def _camera_twice(tmp: Path) -> None:
    edit_json(tmp / "capture" / "capture.json", lambda d: d["cameras"].append(d["cameras"][0]))


REFIT = "refit {tmp}/c.json -c {calib} -o {tmp}/fit.json"

CASES = [
    Case("inputs-refit-weights-as-strings", REFIT,
         setup=_views({"points": _PTS, "pixels": _PIX, "weights": ["1"] * 20}),
         says=("c.json", "views[0].weights", "numbers"), absent=("{tmp}/fit.json",)),
    Case("inputs-refit-points-as-strings", REFIT,
         setup=_views({"points": [[str(v) for v in p] for p in _PTS], "pixels": _PIX}),
         says=("c.json", "views[0].points", "numbers"), absent=("{tmp}/fit.json",)),
    Case("inputs-refit-pixels-as-booleans", REFIT, setup=_views({"points": _PTS, "pixels": [[True, False]] * 20}),
         says=("c.json", "views[0].pixels", "numbers"), absent=("{tmp}/fit.json",)),
    Case("inputs-refit-two-views-one-name", REFIT,
         setup=_views({"name": "a", "points": _PTS, "pixels": _PIX}, {"name": "a", "points": _PTS, "pixels": _PIX}),
         says=("c.json", "views[1].name", "'a'"), absent=("{tmp}/fit.json",)),
    Case("inputs-capture-camera-twice", "build {capture} {tmp}/out", setup=_camera_twice,
         says=("capture.json", "'cameras'", "distinct"), absent=("{tmp}/out",)),
    Case("inputs-capture-no-camera", "build {capture} {tmp}/out",
         setup=lambda tmp: edit_json(tmp / "capture" / "capture.json", lambda d: d["cameras"].clear()),
         says=("capture.json", "'cameras'", "non-empty"), absent=("{tmp}/out",)),
]
