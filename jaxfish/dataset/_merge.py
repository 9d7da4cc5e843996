"""``jaxfish merge FOLDER``: finish a folder that N shard runs wrote (``docs/dataset.md``, "Shards").

A dataset's shards (``jaxfish build --shard I/N``) each leave a record ``.shards/{I}-of-{N}.json``
and no ``dataset.json``; `merge_shards` checks that every shard finished, that they all come from
one build (same N, frames, options, layout version and source) and that every sample they list is
complete, then ends the folder exactly as a whole build ends (`finish_dataset`), so that the folder
holds the bytes of one build. A capture's shards (``jaxfish synth --out CAPTURE --shard I/N``) are
finished the same way: `merge_shards` lists their frames in ``capture.json``.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any

from ._build import (
    MARKER_DIGESTS,
    file_digest,
    finish_dataset,
    marker_differences,
    marker_is_complete,
    read_marker,
    remove_stale_temporaries,
)
from ._layout import LAYOUT_VERSION, sample_id
from ._options import DONE_DIR, BuildOptions, DatasetError, sample_span
from ._shards import SHARDS_DIR, Shard, check_same_split, remove_shard_records, reopen_source, shard_records


@dataclasses.dataclass(frozen=True)
class MergeReport:
    """What `merge_shards` finished: the folder, its ``kind`` (``"dataset"`` or ``"capture"``),
    the number of shards and the samples (dataset: sample ids) or frames (capture) they made."""

    out_dir: Path
    kind: str
    shards: int
    items: tuple[str, ...]

    def summary(self) -> str:
        """One line: what was merged into which folder."""
        what = "sample(s)" if self.kind == "dataset" else "frame(s)"
        return f"merged {self.shards} shard(s), {len(self.items)} {what} -> {self.out_dir}"


_DATASET_FIELDS = ("kind", "requested", "layout_version", "options", "source", "origin", "rule")
_CAPTURE_FIELDS = ("kind", "requested", "settings", "rule")


def merge_shards(folder: str | os.PathLike, *, source=None, verify: bool = False) -> MergeReport:
    """Finish a folder that N shard runs wrote; returns a `MergeReport`.

    Checks, before writing anything, that ``folder/.shards`` holds the records of shards 0..N-1 of
    one split (one N; the same requested frames, options, layout version and source fingerprint) and
    that every sample each lists is complete (its ``.done`` marker present, of this layout version,
    with the build's options and the source's fingerprint, every file it lists present; with
    ``verify`` also each file's digest, by the algorithm its marker's field ``digest`` names);
    every other marker in the folder must match the build too, as a whole build requires. Then
    writes what the end of a whole build writes (`finish_dataset`: ``dataset.json``,
    ``calibration_data``, ...), removes the temporary files killed runs left and
    the shard records. A missing shard, a record of another split, a corrupt record or an
    incomplete sample raises `DatasetError` naming it, and nothing is written.

    ``source``: the source the shards were built from (a `FrameSource` or a capture directory);
    default: the one their records name (a capture's absolute path, or the embedded scene's
    settings). The folder is locked like a whole build's (no shard may run meanwhile). A capture
    folder whose shards ``jaxfish synth --shard`` wrote is finished by `merge_capture_shards`."""
    out = Path(folder)
    if not out.is_dir():
        raise DatasetError(f"{out}: not a folder")
    from ..io._folder import folder_lock

    with folder_lock(out, DatasetError, "build"):
        records = shard_records(out)
        if records and all(doc.get("kind") == "capture" for doc in records.values()):
            return merge_capture_shards(out, records)
        count, first = check_same_split(records, out, _DATASET_FIELDS, DatasetError, "build")
        if first.get("kind") != "dataset":
            raise DatasetError(f"{next(iter(records))}: field 'kind' is {first.get('kind')!r}, expected 'dataset' "
                               f"or 'capture'")
        where = str(next(iter(records)))
        _check_split(records, count, "dataset")
        if source is None:
            source = reopen_source(first.get("origin"), where)
        from ._sources import as_source

        source = as_source(source)
        if source.fingerprint() != first.get("source"):
            raise DatasetError(f"{getattr(source, 'where', source)}: the source differs from the one the shards were "
                               f"built from ({where}: field 'source'); merge with the capture they were built from")
        options = _options_of(first, where)
        if first.get("layout_version") != LAYOUT_VERSION:
            raise DatasetError(f"{where}: field 'layout_version' is {first.get('layout_version')!r}, this jaxfish writes "
                               f"{LAYOUT_VERSION}: build the shards again")
        frames = {int(s) for s in first["requested"]}
        _check_samples(out, first["requested"], options, source, frames, verify, records)
        finish_dataset(source, out, options)
        remove_stale_temporaries(out)
        remove_shard_records(out)
        return MergeReport(out, "dataset", count, tuple(first["requested"]))


def _check_split(records: dict[Path, dict[str, Any]], count: int, kind: str) -> None:
    """Every record's fields ``requested`` and ``samples`` are lists of ids (``kind`` "dataset":
    sample ids, `sample_id`; "capture": frame numbers), and ``samples`` is what the rule gives its
    shard of ``requested``; else `DatasetError` naming the record and the field."""
    is_id, what = (_is_sample_id, "sample ids such as \"00001\"") if kind == "dataset" else (_is_frame, "frame numbers")
    for path, doc in records.items():
        for field in ("requested", "samples"):
            value = doc.get(field)
            if field not in doc:
                raise DatasetError(f"{path}: field {field!r} missing: expected a list of {what}")
            if not isinstance(value, list) or not all(is_id(v) for v in value):
                raise DatasetError(f"{path}: field {field!r}: expected a list of {what}")
        requested, samples = doc["requested"], doc["samples"]
        expect = Shard(doc["shard"][0], count).select([int(v) for v in requested])
        if [int(v) for v in samples] != expect:
            raise DatasetError(f"{path}: field 'samples' is not shard {doc['shard'][0]}/{count} of field 'requested' "
                               f"(the shards' rule: the k-th sorted frame goes to shard k mod N)")


def _is_sample_id(value: Any) -> bool:
    """A sample id (``"00001"``, `sample_id`): a dataset shard's."""
    if not (isinstance(value, str) and value.isascii() and value.isdigit()):
        return False
    try:
        return sample_id(int(value)) == value
    except ValueError:  # more digits than int() converts
        return False


def _is_frame(value: Any) -> bool:
    """A frame number (an integer >= 0): a capture shard's."""
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


def _options_of(record: dict[str, Any], where: str) -> BuildOptions:
    opts = record.get("options")
    if not isinstance(opts, dict):
        raise DatasetError(f"{where}: field 'options': expected an object")
    try:
        return BuildOptions(**{k: opts[k] for k in ("backward_flow", "bev", "motion_threshold_m", "png_level")})
    except (KeyError, TypeError, ValueError) as e:  # ValueError: BuildOptions' DatasetError (a JaxfishError)
        raise DatasetError(f"{where}: field 'options' is malformed ({type(e).__name__}: {e})") from None


def _check_samples(out: Path, requested: list[str], options: BuildOptions, source, frames: set[int], verify: bool,
                   records: dict[Path, dict[str, Any]]) -> None:
    """Every requested sample complete and made by this build; every other marker too."""
    owner = {s: path.name for path, doc in records.items() for s in doc["samples"]}
    wanted, capture = options.to_dict(), source.fingerprint()
    incomplete: list[str] = []
    docs: dict[str, Any] = {}  # the requested samples' markers, parsed once
    for sid in requested:
        marker = out / DONE_DIR / f"{sid}.json"
        doc = docs[sid] = read_marker(marker)  # None: missing or unreadable, not complete
        if isinstance(doc, dict) and doc.get("layout_version") == LAYOUT_VERSION and "files" in doc:
            _marker_files(marker, doc)
        if doc is None or not marker_is_complete(out, doc):
            incomplete.append(sid)
    if incomplete:
        raise DatasetError(f"{out}: sample(s) {sample_span(incomplete)} listed by {owner[incomplete[0]]} are not "
                           f"complete (no valid {DONE_DIR}/{incomplete[0]}.json, or a file it lists is missing): run "
                           f"that shard's build again")
    done = out / DONE_DIR
    for marker in sorted(done.glob("*.json")) if done.is_dir() else []:
        doc = docs[marker.stem] if marker.stem in docs else read_marker(marker)
        if doc is None:
            if marker.stem in owner:  # pragma: no cover - read a moment ago
                raise DatasetError(f"{marker}: not a readable completion marker")
            continue
        if not isinstance(doc, dict) or doc.get("layout_version") != LAYOUT_VERSION:
            continue  # another layout version: rebuilt by the next build, not listed
        diffs = marker_differences(doc, wanted, capture, source, frames)
        if diffs:
            raise DatasetError(f"{marker}: sample {marker.stem} was made from another capture or with other options "
                               f"than the shards ({'; '.join(diffs)}): rebuild it (jaxfish build --rebuild ...)")
        if verify and marker.stem in owner:
            algorithm = doc.get("digest", "sha256")  # a marker without the field records SHA-256
            if not isinstance(algorithm, str) or algorithm not in MARKER_DIGESTS:
                raise DatasetError(f"{marker}: field 'digest' is {algorithm!r}, not one of "
                                   f"{', '.join(sorted(MARKER_DIGESTS))}: rebuild sample {marker.stem}")
            for rel, digest in _marker_files(marker, doc).items():
                if file_digest(out / rel, algorithm) != digest:
                    raise DatasetError(f"{out / rel}: its {algorithm} digest differs from {marker}'s field 'files': "
                                       f"the file changed after its sample was built; rebuild sample {marker.stem}")


def _marker_files(marker: Path, doc: dict[str, Any]) -> dict[str, str]:
    """A completion marker's field ``files``: {path relative to the dataset folder, inside it:
    digest}; anything else raises `DatasetError` naming the marker and the field."""
    files = doc.get("files")
    if not isinstance(files, dict):
        raise DatasetError(f"{marker}: field 'files': expected an object {{relative file path: digest}}, got "
                           f"{type(files).__name__}: rebuild sample {marker.stem}")
    for rel, digest in files.items():
        parts = Path(rel).parts
        if not rel or "\0" in rel or Path(rel).is_absolute() or ".." in parts or not isinstance(digest, str):
            raise DatasetError(f"{marker}: field 'files': entry {rel!r}: {digest!r} is not a file path inside the "
                               f"dataset folder and its digest: rebuild sample {marker.stem}")
    return files


# ------------------------------------------------------------------------------------ captures
def merge_capture_shards(root: Path, records: dict[Path, dict[str, Any]]) -> MergeReport:
    """Finish a capture whose frames ``jaxfish synth --shard I/N`` runs rendered: check the
    records (as `merge_shards`) and that every frame folder they list is still what its shard
    wrote (`frame_fingerprint`), then list the frames in ``capture.json`` (the bytes one
    ``jaxfish synth`` writes) and remove the shard records. Call it holding the folder's lock."""
    from ..io import CaptureError, list_capture_frames
    from ._fingerprint import frame_fingerprint

    count, first = check_same_split(records, root, _CAPTURE_FIELDS, DatasetError, "synth")
    _check_split(records, count, "capture")
    header = root / "capture.json"
    if not header.is_file():
        raise DatasetError(f"{header}: missing (every shard writes it): run the shards again")
    for path, doc in records.items():
        prints = doc.get("frame_fingerprints")
        if not isinstance(prints, dict):
            raise DatasetError(f"{path}: field 'frame_fingerprints': expected an object")
        for f in doc["samples"]:
            if prints.get(str(f)) != frame_fingerprint(root, int(f)):
                raise DatasetError(f"{root / 'frames' / f'{int(f):06d}'}: differs from what shard {path.stem} wrote "
                                   f"({path}: field 'frame_fingerprints'): run that shard again")
    frames = sorted(int(f) for f in first["requested"])
    try:
        list_capture_frames(root, frames)
    except CaptureError as e:
        raise DatasetError(str(e)) from None
    from ..io._folder import remove_temporaries

    remove_temporaries(root)
    remove_shard_records(root)
    return MergeReport(root, "capture", count, tuple(sample_id(f) for f in frames))


__all__ = ["SHARDS_DIR", "MergeReport", "merge_shards", "merge_capture_shards"]
