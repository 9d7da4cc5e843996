"""Hostile files a command reads back from a folder jaxfish wrote: corrupt shard records and
completion markers (``jaxfish merge``) and corrupt range and height maps of a built dataset
(``jaxfish bev``). Every case gets the error line naming the file and the field (or the dtype or
shape), exit status 2 and nothing written."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .cases_shards import write_shard_records
from .corpus import Case

NOT_MERGED = ("{tmp}/ds/dataset.json", "{tmp}/ds/calibration_data")


def _records(*names: str, edit=None, marker=None):
    """A folder ``{tmp}/ds`` whose shards left the records ``names``, of samples 00000 and 00001,
    that match the copy of the small capture (its fingerprint and path, the default options, this
    layout version) up to ``edit(doc)``; ``marker(doc)``: also a completion marker of sample 00000
    for this build (listing one present file), edited so."""
    def setup(tmp: Path) -> None:
        from jaxfish.dataset import BuildOptions, CaptureSource
        from jaxfish.dataset._layout import LAYOUT_VERSION

        fingerprint = CaptureSource(tmp / "capture").fingerprint()
        options = BuildOptions().to_dict()
        write_shard_records(tmp, names, edit=edit, fields={
            "layout_version": LAYOUT_VERSION, "options": dict(options), "source": fingerprint,
            "origin": {"capture": str(tmp / "capture")}})
        if marker is not None:
            (tmp / "ds" / "x.png").write_bytes(b"x")
            doc = {"sample": "00000", "layout_version": LAYOUT_VERSION, "options": dict(options),
                   "source": fingerprint, "files": {"x.png": "0" * 64}, "digest": "sha256"}
            (tmp / "ds" / ".done" / "00000.json").write_text(json.dumps(marker(doc) or doc))
    return setup


def _huge_shard_count(tmp: Path) -> None:
    d = tmp / "ds" / ".shards"
    d.mkdir(parents=True)
    (d / "0-of-2000000.json").write_text(json.dumps({"format": "jaxfish-shard", "shard": [0, 2000000]}))


def _renamed_samples(doc):
    doc["frames"] = doc.pop("samples")


def _dataset(npy: str | None = None, array=None):
    """A built dataset ``{tmp}/ds`` of one sample (00000): four 16 x 12 fisheyes' range maps and
    labels, their calibrations, an 8 x 8 BEV with its true labels and height map; the file ``npy``
    (relative) replaced by ``array``."""
    def setup(tmp: Path) -> None:
        import jax.numpy as jnp

        import jaxfish as jf
        from jaxfish.bev import bev_metadata
        from jaxfish.io import write_label_png

        root = tmp / "ds"
        for name, calib in jf.default_rig(width=16, height=12, dtype=jnp.float32).items():
            jf.save_calibration(calib, root / "calibration_data" / f"{name}.json")
            (root / "depth_maps" / "raw_data").mkdir(parents=True, exist_ok=True)
            np.save(root / "depth_maps" / "raw_data" / f"00000_{name}.npy", np.full((12, 16), 5.0, np.float32))
            write_label_png(root / "semantic_annotations" / "gtLabels" / f"00000_{name}.png", np.zeros((12, 16), int))
        cam = jf.Orthographic(0.5, width=8, height=8, dtype=jnp.float32)
        pose = jf.Pose(np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]), np.array([1.3, 0.0, 50.0]),
                       dtype=jnp.float32)
        (root / "calibration_data" / "BEV.json").write_text(json.dumps(bev_metadata(cam, pose)))
        write_label_png(root / "semantic_annotations" / "gtLabels" / "00000_BEV.png", np.zeros((8, 8), int))
        (root / "bev_height" / "raw_data").mkdir(parents=True)
        np.save(root / "bev_height" / "raw_data" / "00000_BEV.npy", np.zeros((8, 8), np.float32))
        if npy is not None:
            np.save(root / npy, array)
    return setup


FV = "depth_maps/raw_data/00000_FV.npy"
HEIGHT = "bev_height/raw_data/00000_BEV.npy"
BEV = "bev {tmp}/ds --out {tmp}/o"

def _record_from_dev_zero(tmp: Path) -> None:
    write_shard_records(tmp, ["0-of-2", "1-of-2"])
    (tmp / "ds" / ".shards" / "1-of-2.json").unlink()
    (tmp / "ds" / ".shards" / "1-of-2.json").symlink_to("/dev/zero")


def _marker_from_dev_zero(tmp: Path) -> None:
    _records("0-of-1", edit=lambda d: {**d, "requested": ["00000"], "samples": ["00000"]}, marker=lambda d: d)(tmp)
    (tmp / "ds" / ".done" / "00000.json").unlink()
    (tmp / "ds" / ".done" / "00000.json").symlink_to("/dev/zero")


CASES = [
    # jaxfish merge: shard records
    Case("records-merge-samples-renamed", "merge {tmp}/ds", setup=_records("0-of-1", edit=_renamed_samples),
         says=("0-of-1.json", "field 'samples' missing"), absent=NOT_MERGED),
    Case("records-merge-samples-as-numbers", "merge {tmp}/ds",
         setup=_records("0-of-2", "1-of-2", edit=lambda d: {**d, "samples": [int(s) for s in d["samples"]]}),
         says=("0-of-2.json", "field 'samples'", "sample ids"), absent=NOT_MERGED),
    Case("records-merge-sample-id-too-long", "merge {tmp}/ds",
         setup=_records("0-of-1", edit=lambda d: {**d, "requested": ["9" * 5000], "samples": ["9" * 5000]}),
         says=("0-of-1.json", "field 'requested'"), absent=NOT_MERGED),
    Case("records-merge-origin-nul", "merge {tmp}/ds",
         setup=_records("0-of-1", edit=lambda d: {**d, "origin": {"capture": "/tmp/\u0000x"}}),
         says=("0-of-1.json", "field 'origin.capture'", "NUL"), absent=NOT_MERGED),
    Case("records-merge-origin-not-a-capture", "merge {tmp}/ds",
         setup=_records("0-of-1", edit=lambda d: {**d, "origin": {"capture": "/nowhere/cap"}}),
         says=("0-of-1.json", "field 'origin.capture'", "--capture"), absent=NOT_MERGED),
    Case("records-merge-shard-count-huge", "merge {tmp}/ds", setup=_huge_shard_count,
         says=("0-of-2000000.json", "field 'shard'", "1000000"), absent=NOT_MERGED),
    Case("records-merge-kind-unhashable", "merge {tmp}/ds", setup=_records("0-of-1", edit=lambda d: {**d, "kind": [1]}),
         says=("0-of-1.json", "field 'kind'"), absent=NOT_MERGED),
    Case("records-merge-png-level-string", "merge {tmp}/ds",
         setup=_records("0-of-1", edit=lambda d: {**d, "options": {**d["options"], "png_level": "1"}}),
         says=("0-of-1.json", "field 'options'", "png_level"), absent=NOT_MERGED),
    # jaxfish merge: completion markers
    Case("records-merge-marker-files-list", "merge {tmp}/ds --verify",
         setup=_records("0-of-1", edit=lambda d: {**d, "requested": ["00000"], "samples": ["00000"]},
                        marker=lambda d: {**d, "files": ["x.png"]}),
         says=("00000.json", "field 'files'"), absent=NOT_MERGED),
    Case("records-merge-marker-files-outside", "merge {tmp}/ds",
         setup=_records("0-of-1", edit=lambda d: {**d, "requested": ["00000"], "samples": ["00000"]},
                        marker=lambda d: {**d, "files": {"/etc/hostname": "0"}}),
         says=("00000.json", "field 'files'", "/etc/hostname"), absent=NOT_MERGED),
    # jaxfish bev on a built dataset: range and height maps
    Case("records-bev-range-strings", BEV, setup=_dataset(FV, np.full((12, 16), "a")),
         says=("00000_FV.npy", "dtype <U1", "range map"), absent=("{tmp}/o",)),
    Case("records-bev-range-structured", BEV, setup=_dataset(FV, np.zeros((12, 16), [("a", "f4"), ("b", "f4")]),),
         says=("00000_FV.npy", "dtype [('a'", "range map"), absent=("{tmp}/o",)),
    Case("records-bev-range-shape", BEV, setup=_dataset(FV, np.zeros(5, np.float32)),
         says=("00000_FV.npy", "shape (5,)", "(12, 16)"), absent=("{tmp}/o",)),
    Case("records-bev-height-strings", BEV, setup=_dataset(HEIGHT, np.full((8, 8), "a")),
         says=("00000_BEV.npy", "dtype <U1", "height map"), absent=("{tmp}/o",)),
    Case("records-bev-height-shape", BEV, setup=_dataset(HEIGHT, np.zeros(5, np.float32)),
         says=("00000_BEV.npy", "shape (5,)", "(8, 8)"), absent=("{tmp}/o",)),
    Case("records-bev-height-complex", BEV, setup=_dataset(HEIGHT, np.zeros((8, 8), np.complex64)),
         says=("00000_BEV.npy", "dtype complex64"), absent=("{tmp}/o",)),
]

CASES += [
    Case("records-build-shard-count-huge", "build {capture} {tmp}/out --shard 0/1000001",
         says=("--shard", "N exceeds 1000000"), absent=("{tmp}/out",)),
    Case("records-build-shard-count-thousands-of-digits", "build {capture} {tmp}/out --shard 0/" + "9" * 5000,
         says=("--shard", "N exceeds 1000000"), absent=("{tmp}/out",)),
    Case("records-build-shard-index-thousands-of-digits", "build {capture} {tmp}/out --shard " + "9" * 5000 + "/2",
         says=("--shard", "0 <= I < N"), absent=("{tmp}/out",)),
    Case("records-build-slurm-array-huge", "build {capture} {tmp}/out",
         env=(("SLURM_ARRAY_TASK_ID", "0"), ("SLURM_ARRAY_TASK_COUNT", "2000000")),
         says=("SLURM", "more than 1000000 tasks"), absent=("{tmp}/out",)),
    Case("records-merge-record-is-a-device", "merge {tmp}/ds", setup=_record_from_dev_zero,
         says=("1-of-2.json", "character device"), absent=NOT_MERGED),
    Case("records-merge-marker-is-a-device", "merge {tmp}/ds", setup=_marker_from_dev_zero,
         says=("00000", "not complete"), absent=NOT_MERGED),
]
