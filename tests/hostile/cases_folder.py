"""Output folders jaxfish must not write into, and resumes that would mix captures or options."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from .corpus import Case, edit_json


def _marker(tmp: Path, *, fingerprint: bool = True, **options) -> None:
    """``{tmp}/out``: a dataset whose sample 00000 was made from ``{tmp}/capture`` with ``options``
    (its marker only: what the resume check reads)."""
    from jaxfish.dataset import LAYOUT_VERSION, BuildOptions, capture_fingerprint, frame_fingerprint
    from jaxfish.io import CaptureReader

    cap = tmp / "capture"
    doc = {"sample": "00000", "frame": 0, "layout_version": LAYOUT_VERSION, "files": {}}
    if fingerprint:
        doc["options"] = BuildOptions(**options).to_dict()
        doc["source"] = {**capture_fingerprint(CaptureReader(cap)), "frames/000000": frame_fingerprint(cap, 0)}
    (tmp / "out" / ".done").mkdir(parents=True)
    (tmp / "out" / ".done" / "00000.json").write_text(json.dumps(doc))


def _user_file(rel: str):
    def setup(tmp: Path) -> None:
        (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp / rel).write_bytes(b"the user's")
    return setup


def _reseeded(tmp: Path) -> None:
    _marker(tmp)
    edit_json(tmp / "capture" / "capture.json", lambda h: h.__setitem__("seed", 7))


def _frame_moved(tmp: Path) -> None:
    _marker(tmp)
    edit_json(tmp / "capture" / "frames/000000/ego.json", lambda e: e["transform"]["location"].__setitem__(0, 99.0))


def _symlinked(name: str):
    def setup(tmp: Path) -> None:
        (tmp / "demo").mkdir()
        (tmp / "demo" / name).symlink_to(tmp / "capture", target_is_directory=True)
    return setup


def _carla_capture(tmp: Path) -> None:
    shutil.copytree(tmp / "capture", tmp / "demo" / "capture")
    edit_json(tmp / "demo" / "capture" / "capture.json", lambda h: h.__setitem__("source", "carla"))


DEMO = "demo {tmp}/demo --frames 1 --scale 0.05"
DEMO_CAPTURE = DEMO + " --write-capture"
SYNTH = "synth --out {tmp}/out --face-size 8 --bev-size 8 --front-width 8 --dvs-substeps 1"

CASES = [
    Case("folder-build-into-foreign-folder", "build {capture} {tmp}/out", setup=_user_file("out/rec.mcap"),
         says=("{tmp}/out", "not a jaxfish dataset", "rec.mcap"), kept=("{tmp}/out/rec.mcap",),
         absent=("{tmp}/out/.done", "{tmp}/out/dataset.json")),
    Case("folder-build-into-a-file", "build {capture} {tmp}/out/rec.mcap", setup=_user_file("out/rec.mcap"),
         says=("rec.mcap", "not a folder"), kept=("{tmp}/out/rec.mcap",)),
    Case("folder-build-resume-other-options",
         "build {capture} {tmp}/out --frames 0 --backward-flow --png-level 9 --motion-threshold 5", setup=_marker,
         says=("{tmp}/out", "00000", "option backward_flow is False there, True", "option png_level is 1 there, 9",
               "option motion_threshold_m is 0.5 there, 5.0", "--rebuild"),
         absent=("{tmp}/out/dataset.json", "{tmp}/out/rgb_images")),
    Case("folder-build-resume-no-bev", "build {capture} {tmp}/out --frames 0 --no-bev", setup=_marker,
         says=("option bev is True there, False",), absent=("{tmp}/out/dataset.json",)),
    Case("folder-build-resume-reseeded-capture", "build {capture} {tmp}/out --frames 0", setup=_reseeded,
         says=("capture.json differs", "--rebuild"), absent=("{tmp}/out/dataset.json",)),
    Case("folder-build-resume-changed-frame", "build {capture} {tmp}/out --frames 1", setup=_frame_moved,
         says=("frames/000000 differs",), absent=("{tmp}/out/dataset.json",)),
    Case("folder-build-resume-marker-without-fingerprint", "build {capture} {tmp}/out --frames 0",
         setup=lambda t: _marker(t, fingerprint=False), says=("records no capture fingerprint",)),
    Case("folder-build-rebuild-other-options", "build {capture} {tmp}/out --frames 0 --rebuild",
         setup=lambda t: _marker(t, png_level=9), exit=0, stdout_says=("1 built", "removed first (rebuild): 00000"),
         kept=("{tmp}/out/dataset.json", "{tmp}/out/rgb_images/00000_FV.png")),
    Case("folder-synth-into-foreign-folder", SYNTH, setup=_user_file("out/rec.mcap"),
         says=("{tmp}/out", "not a jaxfish capture", "rec.mcap"), kept=("{tmp}/out/rec.mcap",),
         absent=("{tmp}/out/capture.json", "{tmp}/out/calibration")),
    Case("folder-synth-into-a-file", SYNTH.replace("{tmp}/out", "{tmp}/out/rec.mcap"), setup=_user_file("out/rec.mcap"),
         says=("rec.mcap", "not a folder"), kept=("{tmp}/out/rec.mcap",)),
    Case("folder-demo-symlinked-capture", DEMO_CAPTURE, setup=_symlinked("capture"),
         says=("{tmp}/demo/capture", "symbolic link"),
         kept=("{tmp}/capture/capture.json",), absent=("{tmp}/demo/dataset",)),
    Case("folder-demo-in-memory-leaves-a-symlinked-capture-alone", DEMO, setup=_symlinked("capture"), exit=0,
         stdout_says=("rendered in memory",), kept=("{tmp}/capture/capture.json",)),
    Case("folder-demo-symlinked-dataset", DEMO, setup=_symlinked("dataset"), says=("{tmp}/demo/dataset", "symbolic link"),
         absent=("{tmp}/demo/capture", "{tmp}/capture/.done")),
    Case("folder-demo-symlinked-contact-sheets", DEMO, setup=_symlinked("contact_sheets"),
         says=("{tmp}/demo/contact_sheets", "symbolic link"), absent=("{tmp}/demo/capture", "{tmp}/demo/dataset")),
    Case("folder-demo-foreign-capture-folder", DEMO_CAPTURE, setup=_user_file("demo/capture/rec.mcap"),
         says=("not a jaxfish capture", "rec.mcap"), kept=("{tmp}/demo/capture/rec.mcap",),
         absent=("{tmp}/demo/capture/capture.json", "{tmp}/demo/dataset")),
    Case("folder-demo-over-a-carla-capture", DEMO_CAPTURE, setup=_carla_capture, says=("source 'carla'", "use another OUT"),
         absent=("{tmp}/demo/dataset",)),
    Case("folder-demo-foreign-dataset-folder", DEMO, setup=_user_file("demo/dataset/rec.mcap"),
         says=("not a jaxfish dataset",), kept=("{tmp}/demo/dataset/rec.mcap",), absent=("{tmp}/demo/capture",)),
]
