"""Label files: index PNGs (``gtLabels``), colour PNGs (``rgbLabels``) carrying their palette as
metadata, 2D box CSV (WoodScape format), 3D box pickle, depth ``.npy`` and the per-actor
displacement text file."""

from __future__ import annotations

import math
import os
import pickle
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .._errors import ImageError
from ._atomic import atomic_write_bytes, atomic_write_text
from ._exr import exr_z_bytes
from ._images import PNG_LEVEL, metadata_text, read_image, read_image_metadata, write_image
from ._json import write_json
from ._npz import write_npy

PALETTE_ATTRIBUTE = "jaxfish:palette"
"""Metadata key of the palette JSON in colour label PNGs."""


def write_label_png(path: str | os.PathLike, labels: np.ndarray, *, png_level: int = PNG_LEVEL) -> Path:
    """Index PNG of a label map (uint8 if every label fits, else uint16); negative labels -> 0."""
    a = np.asarray(labels)
    if a.ndim != 2:
        raise ImageError(f"{path}: labels must be (H, W), got {a.shape}")
    if a.dtype == np.uint8:  # as written
        return write_image(path, a, png_level=png_level)
    if a.dtype.kind not in "iub":
        a = a.astype(np.int64)  # truncated towards zero
    low, high = int(a.min(initial=0)), int(a.max(initial=0))
    if high > 65535:
        raise ImageError(f"{path}: labels above 65535 do not fit a PNG")
    if low < 0:
        a = np.maximum(a, 0)
    return write_image(path, a.astype(np.uint8 if high < 256 else np.uint16), png_level=png_level)


_CHANNEL_KINDS = {2: "grey + alpha", 3: "RGB colour", 4: "RGBA colour"}


def read_label_png(path: str | os.PathLike) -> np.ndarray:
    """Read an index PNG as ``(H, W)`` int32: the grey samples of a one-channel PNG, or the palette
    indices of a palette PNG (never its colours). A file that is not a PNG by content (a JPEG
    renamed ``.png``: wrong labels) or that has more than one channel (a colour rendering such as
    ``rgbLabels``) raises `ImageError` naming it."""
    a = read_image(path, lossless=True)
    if a.shape[-1] != 1:
        raise ImageError(f"{path}: expected an index PNG (one grey channel or palette indices), got "
                         f"{a.shape[-1]} channels ({_CHANNEL_KINDS.get(a.shape[-1], 'colour')}): labels are "
                         "not read from colours (gtLabels holds the index PNGs, rgbLabels their colour renderings)")
    return a[..., 0].astype(np.int32)


def write_color_png(path: str | os.PathLike, rgb: np.ndarray, palette: Mapping[str, Any] | None = None, *,
                    png_level: int = PNG_LEVEL) -> Path:
    """RGB uint8 PNG with ``palette`` (JSON-able, e.g. ``{"classes": [...], "colors": [...]}``)
    stored as the PNG text attribute `PALETTE_ATTRIBUTE` (atomic)."""
    path = Path(path)
    a = np.ascontiguousarray(np.asarray(rgb, np.uint8))
    if a.ndim != 3 or a.shape[-1] != 3:
        raise ImageError(f"{path}: colour labels must be (H, W, 3) uint8, got {a.shape}")
    return write_image(path, a, metadata=None if palette is None else {PALETTE_ATTRIBUTE: palette}, png_level=png_level)


def read_palette(path: str | os.PathLike) -> dict[str, Any]:
    """The palette stored in a colour PNG by `write_color_png`."""
    return read_image_metadata(path, PALETTE_ATTRIBUTE)


def write_boxes_2d_csv(path: str | os.PathLike, rows: Sequence[tuple[str, int, int, int, int, int]]) -> Path:
    """WoodScape 2D box file: one line ``class_name,class_id,x1,y1,x2,y2`` per box (integer pixel
    coordinates of the extreme pixels, pixel-centre convention, inclusive); empty file if none."""
    lines = []
    for r in rows:
        name, cid, x1, y1, x2, y2 = r
        if "," in str(name):
            raise ImageError(f"{path}: class name {name!r} contains a comma")
        lines.append(f"{name},{int(cid)},{int(x1)},{int(y1)},{int(x2)},{int(y2)}")
    return atomic_write_text(path, "".join(line + "\n" for line in lines))


def read_boxes_2d_csv(path: str | os.PathLike) -> list[tuple[str, int, int, int, int, int]]:
    """Read a WoodScape 2D box file (spaces after commas tolerated)."""
    path = Path(path)
    if not path.is_file():
        raise ImageError(f"{path}: file missing")
    out = []
    for i, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        parts = [p.strip() for p in line.split(",")]
        if len(parts) != 6:
            raise ImageError(f"{path}:{i}: expected 6 fields class_name,class_id,x1,y1,x2,y2, got {len(parts)}")
        try:
            out.append((parts[0], *(int(float(p)) for p in parts[1:])))
        except ValueError as e:
            raise ImageError(f"{path}:{i}: non-numeric field ({e})") from e
    return out  # type: ignore[return-value]


def write_boxes_3d_pickle(path: str | os.PathLike, boxes: Mapping[int, Any]) -> Path:
    """3D boxes in SynWoodScape's released format: a pickle ``{actor_id (int): (8, 3) float64 corners
    in CARLA world coordinates}`` (order `jaxfish.groundtruth.CORNER_SIGNS`), every actor, no class
    (the class and vehicle-frame corners go to `write_boxes_3d_ext_json`)."""
    clean = {}
    for k, v in sorted(boxes.items()):
        try:
            a = np.asarray(v, np.float64)
        except (TypeError, ValueError) as e:
            raise ImageError(f"{path}: box {k}: corners must be an (8, 3) array of numbers ({e})") from e
        if a.shape != (8, 3):
            raise ImageError(f"{path}: box {k}: corners must be (8, 3), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ImageError(f"{path}: not written: box {k}: corners are not finite numbers")
        clean[int(k)] = a
    return atomic_write_bytes(path, pickle.dumps(clean, protocol=4))


def write_boxes_3d_ext_json(path: str | os.PathLike, boxes: Mapping[int, Mapping[str, Any]]) -> Path:
    """jaxfish's extra 3D box file (JSON): ``{"frames": ..., "boxes": [{"actor_id", "class_id",
    "class_name", "corners_world" (8 x 3, CARLA world), "corners_vehicle" (8 x 3, ISO 8855 vehicle
    frame at t)}, ...]}`` in actor-id order."""
    rows = []
    for k, v in sorted(boxes.items()):
        rows.append({"actor_id": int(k), "class_id": int(v["class_id"]), "class_name": str(v["class_name"]),
                     "corners_world": np.round(np.asarray(v["corners_world"], np.float64), 6).tolist(),
                     "corners_vehicle": np.round(np.asarray(v["corners_vehicle"], np.float64), 6).tolist()})
    doc = {"frames": {"corners_world": "CARLA world (x forward, y right, z up; left-handed), metres",
                      "corners_vehicle": "ISO 8855 ego vehicle frame at t (x forward, y left, z up), metres"},
           "corner_order": "index = 4 ix + 2 iy + iz over the signs (-, +) of the box axes (CARLA get_local_vertices)",
           "boxes": rows}
    return write_json(path, doc, indent=1, error=ImageError)


def read_boxes_3d_pickle(path: str | os.PathLike) -> dict[int, Any]:
    """Read a 3D box pickle ``{actor_id: (8, 3) corners}`` (trusted files only: pickle runs code)."""
    path = Path(path)
    if not path.is_file():
        raise ImageError(f"{path}: file missing")
    with open(path, "rb") as fh:
        return pickle.load(fh)


def write_displacements(path: str | os.PathLike, actor_id: Sequence[int], class_id: Sequence[int],
                        displacement_m: Sequence[float], *, threshold_m: float) -> Path:
    """Text file of every actor's displacement between t-1 and t: a header line, then
    ``actor_id class_id displacement_m moving`` per actor (moving = displacement > threshold)."""
    lines = [f"# actor_id class_id displacement_m moving(threshold_m={threshold_m:g})"]
    for a, c, d in zip(actor_id, class_id, displacement_m, strict=True):
        if not math.isfinite(float(d)):
            raise ImageError(f"{path}: not written: the displacement of actor {int(a)} is not a finite number ({float(d)})")
        lines.append(f"{int(a)} {int(c)} {float(d):.6f} {int(float(d) > threshold_m)}")
    return atomic_write_text(path, "\n".join(lines) + "\n")


def read_displacements(path: str | os.PathLike) -> dict[int, float]:
    """Read `write_displacements`' file: ``{actor_id: displacement_m}``."""
    path = Path(path)
    if not path.is_file():
        raise ImageError(f"{path}: file missing")
    out = {}
    for i, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip() or line.startswith("#"):
            continue
        parts = line.split()
        if len(parts) != 4:
            raise ImageError(f"{path}:{i}: expected 4 fields, got {len(parts)}")
        out[int(parts[0])] = float(parts[2])
    return out


def write_depth_npy(path: str | os.PathLike, depth_m: np.ndarray) -> Path:
    """Depth map as float32 ``.npy`` (metres; range or z-depth as documented by the caller; sky 1000)."""
    return write_npy(path, np.asarray(depth_m, np.float32))


DEPTH_ATTRIBUTE = "jaxfish:depth"
"""Metadata key of the definition JSON in the depth EXRs written by `write_depth_exr`."""


def write_depth_exr(path: str | os.PathLike, depth_m: np.ndarray, definition: Mapping[str, Any] | None = None) -> Path:
    """Depth map as a one-channel float32 OpenEXR (channel ``Z``, uncompressed: faster to write
    than zip, for larger files; figures in docs/performance.md), with ``definition`` (JSON-able: what the values are) stored as
    the text attribute `DEPTH_ATTRIBUTE`; atomic. Encoded with NumPy: the bytes `write_image`
    (OpenImageIO) writes for the same map and definition. Read it back with `read_depth_exr`."""
    path = Path(path)
    d = np.asarray(depth_m, np.float32)
    if d.ndim != 2:
        raise ImageError(f"{path}: depth must be (H, W), got {d.shape}")
    if path.suffix.lower() != ".exr" or 0 in d.shape:  # write_image names the fault
        return write_image(path, d, channel_names=("Z",), exr_compression="none",
                           metadata=None if definition is None else {DEPTH_ATTRIBUTE: dict(definition)})
    text = None if definition is None else metadata_text(path, {DEPTH_ATTRIBUTE: dict(definition)})
    return atomic_write_bytes(path, exr_z_bytes(d, text))


def read_depth_exr(path: str | os.PathLike) -> np.ndarray:
    """A depth EXR written by `write_depth_exr` as ``(H, W)`` float32 metres."""
    a = read_image(path)
    if a.shape[-1] != 1 or a.dtype != np.float32:
        raise ImageError(f"{path}: expected a one-channel float32 depth EXR, got {a.dtype} {a.shape}")
    return a[..., 0]
