"""Hostile shard arguments (``--shard``, the SLURM job-array variables) and merges of folders that
are not the complete split of one run (the shards themselves: tests/dataset/test_shards.py)."""

from __future__ import annotations

import json
from pathlib import Path

from .corpus import Case


def _slurm(task: str, count: str, low: str | None = None, step: str | None = None,
           high: str | None = None) -> tuple[tuple[str, str], ...]:
    names = ("SLURM_ARRAY_TASK_ID", "SLURM_ARRAY_TASK_COUNT", "SLURM_ARRAY_TASK_MIN", "SLURM_ARRAY_TASK_STEP",
             "SLURM_ARRAY_TASK_MAX")
    return tuple((n, v) for n, v in zip(names, (task, count, low or "", step or "", high or ""), strict=True))


def write_shard_records(tmp: Path, names, *, fields=None, edit=None) -> None:
    """Make ``{tmp}/ds`` look like a dataset whose shards left the records ``names`` (``"I-of-N"``),
    of samples 00000 and 00001: the record fields, updated with ``fields``, then edited by
    ``edit(doc)`` (its result, when not None, is written)."""
    d = tmp / "ds" / ".shards"
    d.mkdir(parents=True)
    (tmp / "ds" / ".done").mkdir()
    for name in names:
        i, n = (int(v) for v in name.split("-of-"))
        doc = {"format": "jaxfish-shard", "kind": "dataset", "shard": [i, n], "requested": ["00000", "00001"],
               "samples": ["00000", "00001"][i::n], "options": {}, "source": {}, "origin": None, **(fields or {})}
        edited = edit(doc) if edit else None
        (d / f"{name}.json").write_text(json.dumps(doc if edited is None else edited))


def _fake_shard_records(*names: str, edit=None):
    """A setup making ``{tmp}/ds`` with the shard records ``names`` (`write_shard_records`)."""
    return lambda tmp: write_shard_records(tmp, names, edit=edit)


CASES = [
    Case("shards-index-past-count", "build {capture} {tmp}/out --shard 3/2", says=("--shard", "'3/2'", "0 <= I < N"),
         absent=("{tmp}/out",)),
    Case("shards-zero-of-zero", "build {capture} {tmp}/out --shard 0/0", says=("--shard", "N >= 1"),
         absent=("{tmp}/out",)),
    Case("shards-letters", "build {capture} {tmp}/out --shard a/b", says=("--shard", "cannot read 'a/b'"),
         absent=("{tmp}/out",)),
    Case("shards-negative", "build {capture} {tmp}/out --shard -1/2", says=("--shard", "cannot read"),
         absent=("{tmp}/out",)),
    Case("shards-three-parts", "build {capture} {tmp}/out --shard 1/2/3", says=("--shard", "cannot read"),
         absent=("{tmp}/out",)),
    Case("shards-empty", "build {capture} {tmp}/out --shard ''", says=("--shard", "cannot read"),
         absent=("{tmp}/out",)),
    Case("shards-unicode-digits", "build {capture} {tmp}/out --shard ١/٢", says=("--shard", "cannot read"),
         absent=("{tmp}/out",)),
    Case("shards-huge", "build {capture} {tmp}/out --shard 99999999999999999999/2", says=("--shard", "0 <= I < N"),
         absent=("{tmp}/out",)),
    Case("shards-synth-past-count", "synth --out {tmp}/cap --frames 2 --face-size 8 --shard 2/2",
         says=("--shard", "'2/2'"), absent=("{tmp}/cap",)),
    Case("shards-synth-build-letters", "synth --build {tmp}/ds --frames 2 --face-size 8 --shard x/2",
         says=("--shard",), absent=("{tmp}/ds",)),
    Case("shards-slurm-id-garbage", "build {capture} {tmp}/out", env=_slurm("seven", "4"),
         says=("SLURM_ARRAY_TASK_ID='seven'", "--shard I/N"), absent=("{tmp}/out",)),
    Case("shards-slurm-count-zero", "build {capture} {tmp}/out", env=_slurm("0", "0"),
         says=("SLURM_ARRAY_TASK_COUNT", "integer >= 1"), absent=("{tmp}/out",)),
    Case("shards-slurm-id-past-count", "build {capture} {tmp}/out", env=_slurm("4", "4"),
         says=("not one of MIN, MIN + STEP",), absent=("{tmp}/out",)),
    Case("shards-slurm-id-below-min", "build {capture} {tmp}/out", env=_slurm("0", "4", "1", "1", "4"),
         says=("SLURM_ARRAY_TASK_MIN=1",), absent=("{tmp}/out",)),
    Case("shards-slurm-off-step", "build {capture} {tmp}/out", env=_slurm("11", "4", "10", "2", "16"),
         says=("SLURM_ARRAY_TASK_STEP=2",), absent=("{tmp}/out",)),
    Case("shards-slurm-irregular-array", "build {capture} {tmp}/out", env=_slurm("2", "3", "1", "1", "9"),
         says=("not a range", "--array=0-2"), absent=("{tmp}/out",)),
    Case("shards-slurm-step-zero", "build {capture} {tmp}/out", env=_slurm("1", "2", "1", "0"),
         says=("SLURM_ARRAY_TASK_STEP",), absent=("{tmp}/out",)),
    Case("shards-slurm-negative-min", "synth --out {tmp}/cap --frames 2 --face-size 8", env=_slurm("1", "2", "-1"),
         says=("SLURM_ARRAY_TASK_MIN",), absent=("{tmp}/cap",)),
    Case("shards-slurm-garbage-but-shard-given", "build {capture} {tmp}/out --shard 3/2",
         env=_slurm("seven", "x"), says=("--shard", "'3/2'")),
    Case("shards-merge-missing-folder", "merge {tmp}/nowhere", says=("not a folder",)),
    Case("shards-merge-no-records", "merge {tmp}/ds", setup=lambda tmp: (tmp / "ds" / ".done").mkdir(parents=True),
         says=("no shard record", ".shards"), absent=("{tmp}/ds/dataset.json",)),
    Case("shards-merge-missing-shard", "merge {tmp}/ds", setup=_fake_shard_records("0-of-3", "2-of-3"),
         says=("shard(s) 1/3 missing", "--shard 1/3"), absent=("{tmp}/ds/dataset.json",)),
    Case("shards-merge-two-splits", "merge {tmp}/ds", setup=_fake_shard_records("0-of-2", "1-of-2", "0-of-3"),
         says=("different splits", "of 3: 0-of-3.json"), absent=("{tmp}/ds/dataset.json",)),
    Case("shards-merge-record-not-json", "merge {tmp}/ds",
         setup=lambda tmp: (_fake_shard_records("0-of-1")(tmp), (tmp / "ds/.shards/0-of-1.json").write_text("[1,")),
         says=("0-of-1.json", "not a readable shard record"), absent=("{tmp}/ds/dataset.json",)),
    Case("shards-merge-record-wrong-shard-field", "merge {tmp}/ds",
         setup=_fake_shard_records("0-of-1", edit=lambda d: {**d, "shard": [0, 0]}),
         says=("0-of-1.json", "field 'shard'"), absent=("{tmp}/ds/dataset.json",)),
    Case("shards-merge-record-not-a-shard", "merge {tmp}/ds",
         setup=_fake_shard_records("0-of-1", edit=lambda d: {**d, "format": "other"}),
         says=("0-of-1.json", "field 'format'"), absent=("{tmp}/ds/dataset.json",)),
    Case("shards-merge-record-no-origin", "merge {tmp}/ds", setup=_fake_shard_records("0-of-2", "1-of-2"),
         says=("field 'origin'", "--capture"), absent=("{tmp}/ds/dataset.json",)),
    Case("shards-merge-record-bad-samples", "merge {tmp}/ds",
         setup=_fake_shard_records("0-of-1", edit=lambda d: {**d, "samples": "00000"}),
         says=("0-of-1.json", "field 'samples'"), absent=("{tmp}/ds/dataset.json",)),
    Case("shards-merge-capture-not-found", "merge {tmp}/ds --capture {tmp}/nowhere",
         setup=_fake_shard_records("0-of-1"), says=("--capture",), absent=("{tmp}/ds/dataset.json",)),
]

CASES += [
    Case("shards-merge-record-path-in-samples", "merge {tmp}/ds",
         setup=_fake_shard_records("0-of-1", edit=lambda d: {**d, "requested": ["../../etc/x"], "samples": ["../../etc/x"]}),
         says=("0-of-1.json", "field 'requested'"), absent=("{tmp}/ds/dataset.json",)),
]
