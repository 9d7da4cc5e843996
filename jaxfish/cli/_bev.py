"""``jaxfish bev SOURCE --out DIR``: the true top view, the camera-fused top view (the dense gather,
`jaxfish.bev.fuse_cameras_dense`) and the IPM baseline of a capture (frames) or of a built
SynWoodScape-layout dataset (samples), with colour renderings and, for fused and IPM against the
truth, the mIoU on all cells and on the cells the method observed, with its coverage.

Written per sample ``ID`` (a capture frame's id is ``f"{frame:05d}"``), every PNG carrying the BEV
scale and axes as metadata (``jaxfish.io.read_bev_metadata``)::

    DIR/{truth,fused}/ID_semantic.png        class index (255 = no observation)
    DIR/{truth,fused}/ID_semantic_color.png  SynWoodScape palette (black = no observation)
    DIR/{truth,fused}/ID_height.npy / .png   float32 metres above the ground / viridis 0-4 m
    DIR/{truth,fused}/ID_occupancy.png       255 occupied, 0 free (or unobserved)
    DIR/ipm/ID_semantic.png, ID_semantic_color.png
    DIR/scores.json                          per-sample and pooled per-class IoU, mIoU (null: no score), coverage

mIoU ignores class 0 (``unlabeled``, void) and averages, for both methods alike, over the classes
present in the true top view (a class only a prediction has lowers the IoU of the true classes it
covers, but is not averaged itself). "All cells": a cell the method did not observe is a miss;
"observed": only the cells the method observed (its coverage), classes present in their truth.
"""

from __future__ import annotations

import json
from pathlib import Path

import typer

from ._app import app, console, fail, results, say

FISHEYES = ("FV", "MVL", "MVR", "RV")
NO_LABEL = 255


def _load_npy(path: Path, shape: tuple[int, int], what: str, calibration: str):
    """A dataset ``.npy`` map of real numbers (an integer or float dtype) of ``shape`` (rows,
    columns: what ``calibration`` gives), as float32; a corrupt file, another dtype (strings,
    booleans, complex, structured) or another shape is a `JaxfishError` naming the file, ``what``
    it is and the dtype or shape."""
    import numpy as np

    from .._errors import JaxfishError
    from ..io import load_npy

    try:
        arr = load_npy(path)
    except (ValueError, OSError, EOFError) as e:
        raise JaxfishError(f"{path}: not a readable .npy array ({e})") from None
    if arr.dtype.fields is not None or arr.dtype.kind not in "fiu":
        raise JaxfishError(f"{path}: dtype {arr.dtype}: {what} must hold real numbers (float32 metres)")
    if arr.shape != tuple(shape):
        raise JaxfishError(f"{path}: shape {arr.shape}: {what} must have shape {tuple(shape)} ({shape[1]} x {shape[0]} "
                           f"pixels, as {calibration} gives)")
    return arr.astype(np.float32)


def _parse_frames(text: str | None, available: list[int]) -> list[int]:
    """The frames ``--frames`` lists (every frame of the capture without it), checked against the
    capture before a range is expanded (`parse_frames`)."""
    from ._build import parse_frames

    chosen = parse_frames(text, available)
    return list(available) if chosen is None else chosen


def _write_view(out: Path, stem: str, meta: dict, semantic, height=None, occupancy=None) -> list[Path]:
    """Write one top view's files; returns their paths."""
    import jax
    import numpy as np

    from .. import bev as jbev
    from .. import groundtruth as gt
    from ..io import write_depth_npy, write_png_with_metadata

    sem = np.asarray(semantic)
    idx = np.where((sem >= 0) & (sem < NO_LABEL), sem, NO_LABEL).astype(np.uint8)
    paths = [
        write_png_with_metadata(out / f"{stem}_semantic.png", idx, dict(meta, content="class index, 255 = no observation")),
        write_png_with_metadata(out / f"{stem}_semantic_color.png", np.asarray(jax.jit(gt.colorize_labels)(sem)),
                                dict(meta, content="SynWoodScape palette", palette=gt.SYNWOODSCAPE_PALETTE.tolist())),
    ]
    if height is not None:
        h = np.asarray(height, np.float32)
        lo, hi = jbev.HEIGHT_COLOR_RANGE_M
        paths += [write_depth_npy(out / f"{stem}_height.npy", h),
                  write_png_with_metadata(out / f"{stem}_height.png", np.asarray(jax.jit(jbev.colorize_height)(h)),
                                          dict(meta, content="height above the ground (m), viridis", color_range_m=[lo, hi]))]
    if occupancy is not None:
        paths.append(write_png_with_metadata(out / f"{stem}_occupancy.png", np.asarray(occupancy).astype(np.uint8) * 255,
                                             dict(meta, content="occupancy: 255 occupied, 0 free or unobserved")))
    return paths


def _capture_items(source: Path, frames: str | None):
    """Yield (id, bev camera, pose, maps, truth dict) per capture frame (through `jaxfish.pipeline`:
    each frame read once, the rig's constants built once)."""
    import numpy as np

    from ..dataset import CaptureSource, rig_constants_of
    from ..io import CaptureError
    from ..pipeline import GroundTruthOptions, bev_truth, camera_maps

    src = CaptureSource(source, reuse_decoded=False)
    chosen = _parse_frames(frames, src.frames)
    if not src.has_bev():  # has_bev names a missing or malformed sensors.json itself
        raise CaptureError(f"{source / 'sensors.json'}: field 'bev' missing (the capture has no BEV camera)")
    constants = rig_constants_of(src)
    options = GroundTruthOptions()
    for frame in chosen:
        f = src.read(frame, bev=True, sensors=False)
        truth = bev_truth(f, constants, options)
        cm = camera_maps(f, constants)
        maps = {"names": list(cm.names), "cameras": list(cm.cameras), "cameras_to_vehicle": list(cm.cameras_to_vehicle),
                "range_m": cm.range_m, "semantic": cm.semantic, "valid": cm.valid,
                "rays": {k.name: k.rays for k in constants.cameras}, "range_resolution_rad": cm.range_resolution_rad}
        yield (f"{frame:05d}", truth.camera, truth.camera_to_vehicle, maps,
               {"semantic": np.asarray(truth.view.truth.semantic), "height_m": truth.height_m,
                "occupancy": truth.occupancy})


def _dataset_range_resolution(source: Path) -> float | None:
    """The angle of one cube-face pixel of the capture a jaxfish dataset was built from
    (``dataset.json`` -> ``capture.face_size``): the angular step of its resampled range maps;
    None when not recorded (range maps rendered per fisheye pixel)."""
    import math

    from .._errors import JaxfishError
    from ..io._json import read_json

    path = source / "dataset.json"
    if not path.is_file():
        return None
    meta = read_json(path, JaxfishError)
    face = meta.get("capture", {}).get("face_size") if isinstance(meta, dict) and isinstance(meta.get("capture"), dict) else None
    if isinstance(face, int) and not isinstance(face, bool) and face > 0:
        return math.pi / 2 / face
    return None


def _height_tolerance_rad(maps) -> float:
    """`fuse_cameras_dense`'s plane-test angle for these range maps: its default, or 0.6 of the
    angular step of the images they were resampled from (half a step, and a margin) if larger."""
    from .. import bev as jbev

    res = maps.get("range_resolution_rad")
    return max(jbev.GATHER_HEIGHT_TOLERANCE_RAD, 0.6 * res) if res else jbev.GATHER_HEIGHT_TOLERANCE_RAD


def _dataset_items(source: Path, samples: str | None):
    """Yield (id, bev camera, pose, maps, truth dict or None) per built sample."""
    import numpy as np

    from .. import bev as jbev
    from .._errors import JaxfishError
    from ..io import load_bev_calibration, load_calibration, read_label_png

    cal = source / "calibration_data"
    names = [n for n in FISHEYES if (cal / f"{n}.json").is_file()]
    if len(names) != len(FISHEYES):
        raise JaxfishError(f"{cal}: needs {', '.join(f'{n}.json' for n in FISHEYES)} (found {names})")
    calibs = [load_calibration(cal / f"{n}.json").astype(np.float32) for n in names]
    cam, pose = load_bev_calibration(cal / "BEV.json")
    depth_dir = source / "depth_maps" / "raw_data"
    ids = sorted(p.stem[: -len("_FV")] for p in depth_dir.glob("*_FV.npy"))
    if samples is not None:
        want = [s.strip() for s in samples.split(",") if s.strip()]
        missing = sorted(set(want) - set(ids))
        if missing:
            raise JaxfishError(f"{depth_dir}: sample(s) {missing} have no {{id}}_FV.npy range map")
        ids = want
    if not ids:
        raise JaxfishError(f"{depth_dir}: no samples (*_FV.npy range maps)")
    cameras = [c.camera for c in calibs]
    resolution = _dataset_range_resolution(source)
    for sid in ids:
        rng, sem = [], []
        for n, c in zip(names, calibs, strict=True):
            p = depth_dir / f"{sid}_{n}.npy"
            if not p.is_file():
                raise JaxfishError(f"{p}: range map missing")
            r = _load_npy(p, (c.camera.height, c.camera.width), f"{n}'s range map", f"calibration_data/{n}.json")
            lab_path = source / "semantic_annotations" / "gtLabels" / f"{sid}_{n}.png"
            lab = read_label_png(lab_path)
            if lab.shape != r.shape:
                raise JaxfishError(f"{lab_path}: labels {lab.shape} do not match {n}'s calibration "
                                   f"{c.camera.width} x {c.camera.height}")
            rng.append(r)
            sem.append(lab)
        rng_a = np.stack(rng)
        maps = {"names": names, "cameras": cameras, "cameras_to_vehicle": [c.camera_to_vehicle for c in calibs],
                "range_m": rng_a, "semantic": np.stack(sem).astype(np.int32), "valid": rng_a > 0,
                "range_resolution_rad": resolution}
        truth = None
        tpath = source / "semantic_annotations" / "gtLabels" / f"{sid}_BEV.png"
        if tpath.is_file():
            tsem = read_label_png(tpath)
            if tsem.shape != (cam.height, cam.width):
                raise JaxfishError(f"{tpath}: {tsem.shape} does not match BEV.json's {cam.width} x {cam.height}")
            hpath = source / "bev_height" / "raw_data" / f"{sid}_BEV.npy"
            height = _load_npy(hpath, (cam.height, cam.width), "the BEV height map", "calibration_data/BEV.json") \
                if hpath.is_file() else None
            occ = np.asarray(jbev.occupancy_map(height)) if height is not None else None
            truth = {"semantic": tsem, "height_m": height, "occupancy": occ}
        yield sid, cam, pose, maps, truth


@app.command()
def bev(
    source: Path = typer.Argument(..., help="A capture directory (capture.json) or a built dataset (calibration_data/)."),
    out: Path = typer.Option(..., "--out", "-o", help="Output directory (created)."),
    frames: str | None = typer.Option(None, "--frames", help="Capture frames, e.g. '0,2-4' (default: all)."),
    samples: str | None = typer.Option(None, "--samples", help="Dataset sample ids, e.g. '00000,00003' (default: all)."),
) -> None:
    """True top view, camera-fused top view and IPM baseline of a capture or a built dataset, with mIoU."""
    if (source / "capture.json").is_file():
        if samples is not None:
            raise fail("--samples is for built datasets; use --frames for a capture")
        items = _capture_items(source, frames)
        kind = "capture"
    elif (source / "calibration_data").is_dir():
        if frames is not None:
            raise fail("--frames is for captures; use --samples for a built dataset")
        items = _dataset_items(source, samples)
        kind = "dataset"
    else:
        raise fail(f"{source}: neither a capture (capture.json) nor a built dataset (calibration_data/)")
    from .._errors import JaxfishError

    written: list[Path] = []
    folders = [out / "fused", out / "ipm", out / "truth", out]  # innermost first
    new_folders = [d for d in folders if not d.exists()]
    try:
        per_sample, pooled = _run(items, out, kind, written)
    except (JaxfishError, OSError) as e:  # a bad input, or a file that cannot be written
        for p in written:  # no top views without their scores: this run's files go
            p.unlink(missing_ok=True)
        for d in new_folders:  # and the folders it created, if nothing else is in them
            try:
                d.rmdir()
            except OSError:
                pass
        if isinstance(e, OSError) and not isinstance(e, JaxfishError) and e.filename is not None:
            raise fail(f"{e.filename}: {e.strerror}") from None
        raise fail(str(e)) from None
    _report(source, kind, out, per_sample, pooled)


_SCORES: list = []
VOID_CLASS = 0  # SynWoodScape "unlabeled": not scored
METHODS = ("fused", "ipm")


def _truth_counts(truth, num_classes: int):
    """Pixels of each class ``0..num_classes-1`` in a true label map."""
    import numpy as np

    t = np.asarray(truth).reshape(-1)
    return np.bincount(t[(t >= 0) & (t < num_classes)].astype(np.int64), minlength=num_classes)


def _class_iou(inter, union, truth_count):
    """Per-class IoU (NaN where not scored: the void class and classes absent from the truth) and
    their mean (NaN when none is scored)."""
    import numpy as np

    inter, union, truth_count = (np.asarray(a, np.float64) for a in (inter, union, truth_count))
    scored = truth_count > 0
    scored[VOID_CLASS] = False
    iou = np.where(scored, inter / np.maximum(union, 1), np.nan)
    return iou, float(np.mean(iou[scored])) if scored.any() else float("nan")


def _json_number(x):
    """A float for JSON: None (null) instead of NaN / infinity (bare NaN is not valid JSON)."""
    import math

    return float(x) if math.isfinite(x) else None


def _scores():
    """`jaxfish.bev.bev_scores` over the SynWoodScape classes, compiled once per process."""
    import jax

    from .. import bev as jbev
    from ..groundtruth import SYNWOODSCAPE_CLASSES

    if not _SCORES:
        _SCORES.append(jax.jit(lambda p, t: jbev.bev_scores(p, t, num_classes=len(SYNWOODSCAPE_CLASSES),
                                                            void_class=VOID_CLASS)))
    return _SCORES[0]


def _counts(s):
    """The per-class counts of a `BevScores` as int64 NumPy: (all: inter, union, truth), (observed: ...)."""
    import numpy as np

    def c(a):
        return np.asarray(a, np.int64)

    return ((c(s.all_cells.intersection), c(s.all_cells.union), c(s.truth_count)),
            (c(s.observed_cells.intersection), c(s.observed_cells.union), c(s.observed_truth_count)))


def _run(items, out: Path, kind: str, written: list[Path]):
    """Fuse (dense gather), project (IPM) and (with a true top view) score every item on all cells
    and on each method's observed cells; the files written are appended to ``written`` as they are
    written (so a caller can remove them when a later item fails). Returns the per-sample rows and,
    per method, the per-class counts of every scored sample (`_counts`)."""
    import jax
    import numpy as np

    from .. import bev as jbev
    from ..bev import bev_metadata

    score = _scores()
    rays = None
    per_sample = []
    pooled: dict = {m: [] for m in METHODS}
    with console.status(f"{kind}: top views ...") as status:
        for sid, cam, pose, maps, truth in items:
            status.update(f"{kind} sample {sid}: fusing {len(maps['names'])} cameras")
            cams = jbev.stack_cameras(maps["cameras"])
            poses = jbev.stack_poses(maps["cameras_to_vehicle"])
            if rays is None and "rays" in maps:
                rays = tuple(np.stack([np.asarray(maps["rays"][n][k]) for n in maps["names"]]) for k in (0, 1))
            if rays is None:
                rays = jax.jit(jbev.rig_rays)(cams)
            # fuse_cameras_dense / ipm_semantics compile their kernels once per shape themselves
            f = jbev.fuse_cameras_dense(cams, poses, maps["range_m"], maps["semantic"], cam, pose, valid=maps["valid"],
                                        rays=rays, height_tolerance_rad=_height_tolerance_rad(maps))
            i = jbev.ipm_semantics(cams, poses, maps["semantic"], cam, pose, valid=maps["valid"])
            meta = bev_metadata(cam, pose, sample=sid)
            written += _write_view(out / "fused", sid, meta, f.semantic, f.height_m, f.occupancy)
            written += _write_view(out / "ipm", sid, meta, i.semantic)
            preds = {"fused": np.asarray(f.semantic, np.int32), "ipm": np.asarray(i.semantic, np.int32)}
            row = {"sample": sid}
            for m in METHODS:
                row[f"coverage_{m}"] = float(np.mean(preds[m] >= 0))
            if truth is not None:
                written += _write_view(out / "truth", sid, meta, truth["semantic"], truth["height_m"], truth["occupancy"])
                t = np.asarray(truth["semantic"], np.int32)
                for m in METHODS:
                    counts = _counts(score(preds[m], t))
                    row[f"miou_{m}"] = _class_iou(*counts[0])[1]
                    row[f"miou_{m}_observed"] = _class_iou(*counts[1])[1]
                    pooled[m].append(counts)
            per_sample.append(row)
    return per_sample, pooled


def _pct(x) -> str:
    import math

    return f"{100 * x:.1f}" if x is not None and math.isfinite(x) else "-"


def _report(source: Path, kind: str, out: Path, per_sample: list, pooled: dict) -> None:
    """Print the scores (tables, and one result line per method through `say`) and write
    ``scores.json``. ``pooled``: per method the `_counts` of every scored sample."""
    import numpy as np
    from rich.table import Table

    from ..groundtruth import SYNWOODSCAPE_CLASSES
    from ..io import atomic_write_text

    table = Table(title=f"BEV mIoU vs the true top view ({kind}): all cells / observed cells (%)")
    for col in ("sample", "fused all", "fused obs.", "fused cover", "IPM all", "IPM obs.", "IPM cover"):
        table.add_column(col)
    for r in per_sample:
        table.add_row(r["sample"], *(_pct(r.get(k)) for m in METHODS
                                     for k in (f"miou_{m}", f"miou_{m}_observed", f"coverage_{m}")))
    results.print(table)
    rows = [{k: _json_number(v) if isinstance(v, float) else v for k, v in r.items()} for r in per_sample]
    scores = {"source": str(source), "kind": kind, "samples": rows,
              "miou_rule": "mean IoU over the classes present in the true top view, class 0 (unlabeled) ignored; "
                           "'miou': all cells (a cell the method did not observe is a miss), 'miou_observed': only "
                           "the cells the method observed (its own 'coverage')"}
    if all(pooled[m] for m in METHODS):
        per_class: dict = {}
        means: dict = {}
        coverage: dict = {}
        for m in METHODS:
            for part, name in ((0, m), (1, f"{m}_observed")):
                inter, union, counts = (np.sum([c[part][k] for c in pooled[m]], axis=0) for k in range(3))
                per_class[name], means[name] = _class_iou(inter, union, counts)
            cells = np.sum([c[0][2].sum() for c in pooled[m]])
            seen = np.sum([c[1][2].sum() for c in pooled[m]])
            coverage[m] = float(seen / cells) if cells > 0 else float("nan")
        cols = ("fused", "fused_observed", "ipm", "ipm_observed")
        cls_table = Table(title="per class, pooled over samples (IoU %): all cells / observed cells")
        for col in ("class", "fused all", "fused obs.", "IPM all", "IPM obs."):
            cls_table.add_column(col)
        for k, cname in enumerate(SYNWOODSCAPE_CLASSES):
            if any(np.isfinite(per_class[n][k]) for n in cols):
                cls_table.add_row(cname, *(_pct(per_class[n][k]) for n in cols))
        cls_table.add_row("mean (mIoU)", *(_pct(means[n]) for n in cols))
        results.print(cls_table)
        for m, label in (("fused", "fused mIoU"), ("ipm", "IPM mIoU")):
            say(f"{label}: {_pct(means[m])} % on all cells, {_pct(means[m + '_observed'])} % on the cells it observed "
                f"(coverage {_pct(coverage[m])} %)")
        scores["per_class_iou"] = {n: {SYNWOODSCAPE_CLASSES[k]: float(v) for k, v in enumerate(per_class[n])
                                       if np.isfinite(v)} for n in METHODS}
        scores["per_class_iou_observed"] = {n: {SYNWOODSCAPE_CLASSES[k]: float(v) for k, v in
                                                enumerate(per_class[f"{n}_observed"]) if np.isfinite(v)} for n in METHODS}
        scores["miou"] = {n: _json_number(means[n]) for n in METHODS}
        scores["miou_observed"] = {n: _json_number(means[f"{n}_observed"]) for n in METHODS}
        scores["coverage"] = {n: _json_number(coverage[n]) for n in METHODS}
    else:
        say("no true top view found: wrote the fused and IPM views only")
    atomic_write_text(out / "scores.json", json.dumps(scores, indent=1, allow_nan=False) + "\n")
    say(f"wrote {len(per_sample)} sample(s) to {out}")
