"""Correspondences of a camera rig (edge I/O): the correspondences JSON with a ``camera`` on
every view::

    {"frame": "board",                        # "board" | "vehicle"
     "views": [{"name": "t000",               # the target view: views of one name share its pose
                "camera": "FV",               # the camera that observed it
                "points": [[x, y, z], ...],   # metres, in the target's frame (or the vehicle's)
                "pixels": [[u, v], ...],      # pixel-centre convention
                "weights": [1.0, ...]}]}      # optional, >= 0

``frame: "board"``: each target view (name) has one unknown pose shared by the cameras that saw
it (a board held still while the rig's cameras capture it); ``"vehicle"``: the points are
surveyed in the vehicle frame (no target pose to fit; every camera's mounting is then determined).
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any

import numpy as np

from ..refit import Correspondences
from ._correspondences import CorrespondenceError, correspondence_array
from ._json import read_json, write_json

RIG_FRAMES: tuple[str, ...] = ("board", "vehicle")
"""Values of a rig correspondences file's ``frame``."""


@dataclasses.dataclass(frozen=True)
class RigCorrespondences:
    """A rig's correspondences: `frame` (`RIG_FRAMES`), `target_names` (the view names, in order
    of first appearance; the view index of every `Correspondences`) and `observations`
    (``{camera name: Correspondences}``, cameras in order of first appearance)."""

    frame: str
    target_names: tuple[str, ...]
    observations: dict[str, Correspondences]


def is_rig_correspondences(data: Any) -> bool:
    """Whether a parsed correspondences object is a rig's (its views name cameras)."""
    return isinstance(data, dict) and isinstance(data.get("views"), list) and any(
        isinstance(v, dict) and "camera" in v for v in data["views"])


def rig_correspondences_from_dict(data: Any, *, source: str = "<correspondences>", dtype=None) -> RigCorrespondences:
    """Validate a parsed rig correspondences object (format in this module's docstring)."""
    if not isinstance(data, dict):
        raise CorrespondenceError(f"{source}: field '<root>': expected an object")
    extra = sorted(set(data) - {"frame", "views"})
    if extra:
        raise CorrespondenceError(f"{source}: field '{extra[0]}': unexpected key (allowed: frame, views)")
    frame = data.get("frame", "board")
    if frame not in RIG_FRAMES:
        raise CorrespondenceError(f"{source}: field 'frame': a rig's frame is one of {RIG_FRAMES}, got {frame!r}")
    views = data.get("views")
    if not isinstance(views, list) or not views:
        raise CorrespondenceError(f"{source}: field 'views': expected a non-empty list of views")
    targets: dict[str, int] = {}
    per_cam: dict[str, list[tuple[np.ndarray, np.ndarray, np.ndarray, int]]] = {}
    seen: set[tuple[str, str]] = set()
    for i, view in enumerate(views):
        where = f"views[{i}]"
        if not isinstance(view, dict):
            raise CorrespondenceError(f"{source}: field '{where}': expected an object")
        extra = sorted(set(view) - {"name", "camera", "points", "pixels", "weights"})
        if extra:
            raise CorrespondenceError(f"{source}: field '{where}.{extra[0]}': unexpected key")
        for key in ("name", "camera", "points", "pixels"):
            if key not in view:
                raise CorrespondenceError(f"{source}: field '{where}.{key}': missing (every view of a rig names its "
                                          "target view and camera)")
        name, cam = view["name"], view["camera"]
        for key, val in (("name", name), ("camera", cam)):
            if not isinstance(val, str) or not val:
                raise CorrespondenceError(f"{source}: field '{where}.{key}': expected a non-empty string, got {val!r}")
        if (name, cam) in seen:
            raise CorrespondenceError(f"{source}: field '{where}': camera {cam!r} observes target view {name!r} twice")
        seen.add((name, cam))
        p = correspondence_array(view["points"], 3, source, f"{where}.points")
        q = correspondence_array(view["pixels"], 2, source, f"{where}.pixels")
        if len(p) != len(q):
            raise CorrespondenceError(f"{source}: field '{where}.pixels': {len(q)} pixels for {len(p)} points")
        w = correspondence_array(view["weights"], None, source, f"{where}.weights") if "weights" in view else np.ones(len(p))
        if len(w) != len(p) or np.any(w < 0):
            raise CorrespondenceError(f"{source}: field '{where}.weights': expected {len(p)} non-negative numbers")
        t = targets.setdefault(name, len(targets))
        per_cam.setdefault(cam, []).append((p, q, w, t))
    n = len(targets)
    obs = {}
    for cam, parts in per_cam.items():
        obs[cam] = Correspondences(
            np.concatenate([x[0] for x in parts]).reshape(-1, 3), np.concatenate([x[1] for x in parts]).reshape(-1, 2),
            np.concatenate([np.full(len(x[0]), x[3], np.int32) for x in parts]), np.concatenate([x[2] for x in parts]),
            n_views=n, dtype=dtype if dtype is not None else np.float64)
    return RigCorrespondences(frame, tuple(targets), obs)


def load_rig_correspondences(path: str | os.PathLike, *, dtype=None) -> RigCorrespondences:
    """Read a rig correspondences JSON file; malformed files raise `CorrespondenceError` naming
    the file and field."""
    path = Path(path)
    return rig_correspondences_from_dict(read_json(path, CorrespondenceError), source=str(path), dtype=dtype)


def rig_correspondences_to_dict(rig: RigCorrespondences) -> dict[str, Any]:
    """The JSON object of a rig's correspondences (inverse of `rig_correspondences_from_dict`)."""
    views = []
    for cam, corr in rig.observations.items():
        view = np.asarray(corr.view)
        pts, pix, w = (np.asarray(x, dtype=np.float64) for x in (corr.points, corr.pixels, corr.weight))
        for t, name in enumerate(rig.target_names):
            m = view == t
            if m.any():
                views.append({"name": name, "camera": cam, "points": pts[m].tolist(), "pixels": pix[m].tolist(),
                              "weights": w[m].tolist()})
    return {"frame": rig.frame, "views": views}


def save_rig_correspondences(rig: RigCorrespondences, path: str | os.PathLike) -> Path:
    """Write a rig's correspondences as JSON, atomically."""
    path = Path(path)
    write_json(path, rig_correspondences_to_dict(rig), indent=None)
    return path
