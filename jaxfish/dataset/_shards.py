"""Shards: one build (or one ``jaxfish synth``) split into N independent runs that write into the
same folder, on one machine or many (``docs/dataset.md``, "Shards").

The rule: the requested frames, sorted ascending without repeats, are numbered k = 0, 1, ...; frame
number k goes to shard ``k mod N``. Every shard records what it made, last and atomically, in
``.shards/{I}-of-{N}.json`` (`SHARDS_DIR`); ``jaxfish merge`` checks those records and finishes the
folder as one run would have.
"""

from __future__ import annotations

import dataclasses
import itertools
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from .._errors import JaxfishError
from ._options import DatasetError

SHARDS_DIR = ".shards"
"""Folder of the shard records (``{I}-of-{N}.json``) and the shard lock files; removed by the merge."""

SHARD_FORMAT = "jaxfish-shard"
"""``format`` of a shard record."""

MAX_SHARDS = 1_000_000
"""The most shards (N) a record may name: a record of a larger split is refused as corrupt."""

SHARD_RULE = "the requested frames, sorted ascending without repeats, are numbered k = 0, 1, ...; frame k goes to shard k mod N"
"""The assignment of frames to shards, in words (also in every shard record)."""


@dataclasses.dataclass(frozen=True)
class Shard:
    """Shard ``index`` of ``count`` (0 <= index < count): a deterministic 1/count of a run's frames
    (`SHARD_RULE`). ``str(shard)`` is ``"I/N"``; `name` (``"I-of-N"``) names its record and lock."""

    index: int
    count: int

    def __post_init__(self) -> None:
        for field in ("index", "count"):
            v = getattr(self, field)
            if isinstance(v, bool) or not isinstance(v, int):
                raise DatasetError(f"shard: {field} must be an integer, got {v!r}")
        if self.count < 1:
            raise DatasetError(f"shard: the number of shards must be at least 1, got {self.count}")
        if self.count > MAX_SHARDS:
            raise DatasetError(f"shard: the number of shards must be at most {MAX_SHARDS}, got {self.count}")
        if not 0 <= self.index < self.count:
            raise DatasetError(f"shard: index {self.index} is not in 0..{self.count - 1} (shard I/N needs 0 <= I < N)")

    def __str__(self) -> str:
        return f"{self.index}/{self.count}"

    @property
    def name(self) -> str:
        """``"I-of-N"``: the stem of the shard's record and lock file."""
        return f"{self.index}-of-{self.count}"

    def select(self, frames: Sequence[int]) -> list[int]:
        """This shard's frames of the requested ``frames`` (`SHARD_RULE`), ascending."""
        ordered = sorted({int(f) for f in frames})
        return ordered[self.index::self.count]

    def record_path(self, folder: str | os.PathLike) -> Path:
        """``folder/.shards/{I}-of-{N}.json``."""
        return Path(folder) / SHARDS_DIR / f"{self.name}.json"


def as_shard(shard: Shard | tuple[int, int] | None) -> Shard | None:
    """A `Shard` of ``(index, count)`` (or itself; None stays None); a bad value raises `DatasetError`."""
    if shard is None or isinstance(shard, Shard):
        return shard
    if not isinstance(shard, (tuple, list)) or len(shard) != 2:
        raise DatasetError(f"shard must be (index, count), e.g. (0, 4), got {shard!r}")
    return Shard(*shard)


def parse_shard(text: str, *, where: str = "--shard") -> Shard:
    """``"I/N"`` -> ``Shard(I, N)``; anything else raises `DatasetError` naming ``where``."""
    parts = str(text).strip().split("/")
    if len(parts) != 2 or not all(p.strip().isdigit() and p.strip().isascii() for p in parts):
        raise DatasetError(f"{where}: cannot read {text!r}: give I/N with integers 0 <= I < N, e.g. 0/4")
    if len(parts[1].strip()) > 12:  # digits beyond what int() reads are no shard count either
        raise DatasetError(f"{where}: {text!r}: N exceeds {MAX_SHARDS}, the most shards of one split")
    index, count = (int(p) if len(p.strip()) <= 12 else MAX_SHARDS + 1 for p in parts)
    if count < 1 or index >= count:
        raise DatasetError(f"{where}: {text!r} is not a shard: I/N needs N >= 1 and 0 <= I < N (e.g. 0/{max(count, 1)})")
    if count > MAX_SHARDS:
        raise DatasetError(f"{where}: {text!r}: N exceeds {MAX_SHARDS}, the most shards of one split")
    return Shard(index, count)


SLURM_VARIABLES = ("SLURM_ARRAY_TASK_ID", "SLURM_ARRAY_TASK_COUNT", "SLURM_ARRAY_TASK_MIN", "SLURM_ARRAY_TASK_MAX",
                   "SLURM_ARRAY_TASK_STEP")
"""The SLURM job-array variables `slurm_shard` reads."""


def slurm_shard(environ: Mapping[str, str] | None = None) -> Shard | None:
    """The shard of a SLURM job-array task, or None outside a job array (``SLURM_ARRAY_TASK_ID``
    or ``SLURM_ARRAY_TASK_COUNT`` unset or empty).

    SLURM numbers the tasks of ``sbatch --array=MIN-MAX[:STEP]`` MIN, MIN + STEP, ..., MAX and
    sets ``SLURM_ARRAY_TASK_COUNT`` to their number; the task with id ``SLURM_ARRAY_TASK_ID`` is
    shard ``(ID - MIN) / STEP`` of COUNT, with MIN = ``SLURM_ARRAY_TASK_MIN`` (0 when unset) and
    STEP = ``SLURM_ARRAY_TASK_STEP`` (1 when unset): ``--array=0-3``, ``--array=1-4`` and
    ``--array=10-16:2`` each give shards 0/4 .. 3/4. An array that is not such a range
    (``--array=1,2,9``: MIN + (COUNT - 1) STEP differs from ``SLURM_ARRAY_TASK_MAX``) or a value
    that is not an integer raises `DatasetError` naming the variable: pass ``--shard I/N`` then."""
    env = os.environ if environ is None else environ
    if not env.get("SLURM_ARRAY_TASK_ID", "").strip() or not env.get("SLURM_ARRAY_TASK_COUNT", "").strip():
        return None

    def read(name: str, default: int | None, low: int) -> int | None:
        text = env.get(name, "").strip()
        if not text:
            return default
        if not (text.isascii() and text.isdigit()) or int(text) < low:
            raise DatasetError(f"environment variable {name}={env.get(name)!r}: not an integer >= {low}; "
                               f"pass --shard I/N to choose the shard yourself")
        return int(text)

    task = read("SLURM_ARRAY_TASK_ID", None, 0)
    count = read("SLURM_ARRAY_TASK_COUNT", None, 1)
    low = read("SLURM_ARRAY_TASK_MIN", 0, 0)
    step = read("SLURM_ARRAY_TASK_STEP", 1, 1)
    high = read("SLURM_ARRAY_TASK_MAX", None, 0)
    assert task is not None and count is not None and low is not None and step is not None
    shown = f"SLURM_ARRAY_TASK_ID={task}, SLURM_ARRAY_TASK_MIN={low}, SLURM_ARRAY_TASK_STEP={step}, " \
            f"SLURM_ARRAY_TASK_COUNT={count}" + (f", SLURM_ARRAY_TASK_MAX={high}" if high is not None else "")
    if high is not None and low + (count - 1) * step != high:
        raise DatasetError(f"the SLURM job array is not a range MIN-MAX[:STEP] of SLURM_ARRAY_TASK_COUNT tasks "
                           f"({shown}); submit it as --array=0-{count - 1} or pass --shard I/N")
    if count > MAX_SHARDS:
        raise DatasetError(f"the SLURM job array has more than {MAX_SHARDS} tasks ({shown}), the most shards of one "
                           f"split")
    if task < low or (task - low) % step or (task - low) // step >= count:
        raise DatasetError(f"the SLURM array task is not one of MIN, MIN + STEP, ... ({shown}); "
                           f"pass --shard I/N")
    return Shard((task - low) // step, count)


# -------------------------------------------------------------------------------------- records
def read_record(path: Path, error: type[Exception] = DatasetError) -> dict[str, Any]:
    """A shard record's content; a missing, unreadable or malformed record, or one whose field
    ``shard`` [I, N] is not 0 <= I < N <= `MAX_SHARDS` or not the file's name, raises ``error``
    naming the file (and the field)."""
    import json

    from ..io._json import regular_file

    try:
        doc = json.loads(regular_file(path, error, "shard record").read_text())  # not a FIFO or a device
    except error:
        raise
    except (OSError, ValueError) as e:
        raise error(f"{path}: not a readable shard record ({type(e).__name__}: {e})") from None
    if not isinstance(doc, dict) or doc.get("format") != SHARD_FORMAT:
        raise error(f"{path}: field 'format': not a jaxfish shard record (expected {SHARD_FORMAT!r})")
    shard = doc.get("shard")
    if (not isinstance(shard, list) or len(shard) != 2 or
            not all(isinstance(v, int) and not isinstance(v, bool) for v in shard) or not 0 <= shard[0] < shard[1]):
        raise error(f"{path}: field 'shard': expected [I, N] with 0 <= I < N, got {shard!r}")
    if shard[1] > MAX_SHARDS:
        raise error(f"{path}: field 'shard' is {shard!r}: N exceeds {MAX_SHARDS}, the most shards of one split")
    if path.stem != f"{shard[0]}-of-{shard[1]}":
        raise error(f"{path}: field 'shard' is {shard!r}, but the file is named for shard {path.stem}")
    return doc


def shard_records(folder: Path, error: type[Exception] = DatasetError) -> dict[Path, dict[str, Any]]:
    """Every shard record of ``folder`` (``.shards/*.json``), read and checked (`read_record`)."""
    d = folder / SHARDS_DIR
    return {p: read_record(p, error) for p in sorted(d.glob("*.json"))} if d.is_dir() else {}


def remove_shard_records(folder: str | os.PathLike) -> None:
    """Remove ``folder/.shards`` (records and lock files); call it holding the folder's exclusive lock."""
    d = Path(folder) / SHARDS_DIR
    if not d.is_dir():
        return
    for p in d.iterdir():
        if p.is_file() or p.is_symlink():
            p.unlink(missing_ok=True)
    try:
        d.rmdir()
    except OSError:  # something else in there: not ours, kept
        pass


def check_same_split(records: dict[Path, dict[str, Any]], folder: Path, fields: Sequence[str],
                     error: type[Exception], what: str) -> tuple[int, dict[str, Any]]:
    """Check that the records are the N shards of one run: one count N, every index 0..N-1 present,
    the same ``fields``; returns N and the first record. Raises ``error`` naming the missing shard,
    the other count or the field that differs."""
    if not records:
        raise error(f"{folder}: no shard record in {SHARDS_DIR}/: nothing to merge (a {what} without --shard "
                    f"finishes the folder itself)")
    counts: dict[int, list[str]] = {}
    for path, doc in records.items():
        counts.setdefault(doc["shard"][1], []).append(path.name)
    if len(counts) > 1:
        listed = "; ".join(f"of {n}: {', '.join(names)}" for n, names in sorted(counts.items()))
        raise error(f"{folder}: shard records of different splits in {SHARDS_DIR}/ ({listed}); keep the records of "
                    f"one split (delete the others) and run the missing shards")
    (count,) = counts
    have = {doc["shard"][0] for doc in records.values()}
    if len(have) < count:  # the first missing indices only: N may be far larger than the records held
        missing = list(itertools.islice((i for i in range(count) if i not in have), 5))
        shown = ", ".join(f"{i}/{count}" for i in missing) + (" ..." if count - len(have) > 5 else "")
        raise error(f"{folder}: shard(s) {shown} missing: no {SHARDS_DIR}/{missing[0]}-of-{count}.json (the shard has "
                    f"not finished, or some of its samples failed): run the {what} with --shard {missing[0]}/{count}")
    first_path, first = next(iter(records.items()))
    for path, doc in records.items():
        for field in fields:
            if doc.get(field) != first.get(field):
                raise error(f"{path}: field {field!r} differs from {first_path.name}'s: the shards come from different "
                            f"{what}s (other capture, options or frames); run every shard with the same arguments")
    return count, first


# ------------------------------------------------------------------------- reopening the source
def source_origin(source) -> dict[str, Any] | None:
    """How `reopen_source` finds ``source`` again (in a dataset shard record): ``{"capture":
    absolute path}`` of a `CaptureSource`, ``{"embedded": {seed, frames, config, calibrations}}``
    of an `EmbeddedSource`; None for any other source (merge it with ``merge_shards(...,
    source=...)``)."""
    from ._sources import CaptureSource, EmbeddedSource

    if isinstance(source, CaptureSource):
        return {"capture": str(Path(source.root).resolve())}
    if isinstance(source, EmbeddedSource):
        import json

        from ..io._calibration_json import calibration_to_dict

        rig = source.render_rig
        return {"embedded": json.loads(json.dumps({
            "seed": source.seed, "frames": len(source.frames), "config": dataclasses.asdict(source.config),
            "calibrations": {n: calibration_to_dict(c) for n, c in rig.items()},
            "leaves": {n: _leaves(c) for n, c in rig.items()}}))}
    return None


def reopen_source(origin: Any, where: str):
    """The source a dataset shard record's ``origin`` (`source_origin`) names; a record without one,
    or whose source cannot be opened, raises `DatasetError` naming ``where`` (the record) and the
    field."""
    from ._sources import CaptureSource, EmbeddedSource

    if isinstance(origin, dict) and isinstance(origin.get("capture"), str):
        path = origin["capture"]
        try:
            if "\0" in path:
                raise DatasetError("not a path (it holds a NUL character)")
            return CaptureSource(path)
        except (ValueError, OSError) as e:  # JaxfishError is a ValueError
            raise DatasetError(f"{where}: field 'origin.capture' ({path!r}): cannot open the capture it names ({e}); "
                               f"give the capture (jaxfish merge DATASET --capture CAPTURE_DIR)") from None
    if isinstance(origin, dict) and isinstance(origin.get("embedded"), dict):
        from ..io._calibration_json import calibration_from_dict
        from ..scene import CaptureConfig

        spec = origin["embedded"]
        try:
            config = CaptureConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in spec["config"].items()})
            rig = {n: _with_leaves(calibration_from_dict(d, source=f"{where}: field 'origin.embedded.calibrations.{n}'"),
                                   spec["leaves"][n], f"{where}: field 'origin.embedded.leaves.{n}'")
                   for n, d in spec["calibrations"].items()}
            return EmbeddedSource(rig, frames=spec["frames"], seed=spec["seed"], config=config)
        except (KeyError, TypeError, AttributeError, ValueError) as e:
            if isinstance(e, JaxfishError) and str(e).startswith(where):  # names the record and the field itself
                raise
            if isinstance(e, JaxfishError):
                raise DatasetError(f"{where}: field 'origin.embedded': {e}") from None
            raise DatasetError(f"{where}: field 'origin.embedded' is malformed ({type(e).__name__}: {e})") from None
    raise DatasetError(f"{where}: field 'origin' names no capture (the shards were built from a source jaxfish cannot "
                       f"reopen): give the capture (jaxfish merge DATASET --capture CAPTURE_DIR, "
                       f"merge_shards(..., source=...))")


def _leaves(calibration) -> list[dict[str, Any]]:
    """A calibration's array leaves, exactly (dtype, shape, values): its JSON (a quaternion of a
    float32 rotation) does not give the same floats back, and the scene renders with these."""
    import jax
    import numpy as np

    return [{"dtype": str(np.asarray(x).dtype), "shape": list(np.shape(x)),
             "values": np.asarray(x).ravel().tolist()} for x in jax.tree_util.tree_leaves(calibration)]


def _with_leaves(template, leaves: Any, where: str):
    """``template`` (a calibration read from its JSON) with the exact array leaves `_leaves` recorded."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    structure = jax.tree_util.tree_structure(template)
    if not isinstance(leaves, list) or len(leaves) != structure.num_leaves:
        raise DatasetError(f"{where}: expected {structure.num_leaves} arrays")
    arrays = []
    for leaf in leaves:
        dtype = np.dtype(leaf["dtype"])
        if dtype.kind not in "fiu" or dtype.itemsize > 8:
            raise DatasetError(f"{where}: dtype {leaf['dtype']!r} is not a float or integer type")
        arrays.append(jnp.asarray(np.asarray(leaf["values"], dtype=dtype).reshape(leaf["shape"])))
    return jax.tree_util.tree_unflatten(structure, arrays)
