"""Label files: index PNGs (``gtLabels``), colour PNGs (``rgbLabels``) carrying their palette as
metadata, 2D box CSV (WoodScape format), 3D box pickle, depth ``.npy`` and the per-actor
displacement text file."""

from __future__ import annotations

import json
import os
import pickle
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import OpenImageIO as oiio

from .._errors import ImageError
from ._atomic import atomic_path, atomic_write_bytes, atomic_write_text
from ._images import read_image, write_image

#: Metadata key of the palette JSON in colour label PNGs.
PALETTE_ATTRIBUTE = "jaxfish:palette"


def write_label_png(path: str | os.PathLike, labels: np.ndarray) -> Path:
    """Index PNG of a label map (uint8 if every label fits, else uint16); negative labels -> 0."""
    a = np.asarray(labels)
    if a.ndim != 2:
        raise ImageError(f"{path}: labels must be (H, W), got {a.shape}")
    a = np.clip(a.astype(np.int64), 0, None)
    dtype = np.uint8 if a.max(initial=0) < 256 else np.uint16
    if a.max(initial=0) > 65535:
        raise ImageError(f"{path}: labels above 65535 do not fit a PNG")
    return write_image(path, a.astype(dtype))


def read_label_png(path: str | os.PathLike) -> np.ndarray:
    """Read an index PNG as ``(H, W)`` int32."""
    return read_image(path)[..., 0].astype(np.int32)


def write_color_png(path: str | os.PathLike, rgb: np.ndarray, palette: Mapping[str, Any] | None = None) -> Path:
    """RGB uint8 PNG with ``palette`` (JSON-able, e.g. ``{"classes": [...], "colors": [...]}``)
    stored as the PNG text attribute `PALETTE_ATTRIBUTE` (atomic)."""
    path = Path(path)
    a = np.ascontiguousarray(np.asarray(rgb, np.uint8))
    if a.ndim != 3 or a.shape[-1] != 3:
        raise ImageError(f"{path}: colour labels must be (H, W, 3) uint8, got {a.shape}")
    if palette is None:
        return write_image(path, a)
    h, w, c = a.shape
    with atomic_path(path) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None:
            raise ImageError(f"{path}: cannot create writer ({oiio.geterror()})")
        spec = oiio.ImageSpec(w, h, c, oiio.UINT8)
        spec.attribute(PALETTE_ATTRIBUTE, json.dumps(palette))
        if not out.open(str(tmp), spec) or not out.write_image(a):
            err = out.geterror()
            out.close()
            raise ImageError(f"{path}: cannot write ({err})")
        out.close()
    return path


def read_palette(path: str | os.PathLike) -> dict[str, Any]:
    """The palette stored in a colour PNG by `write_color_png`."""
    path = Path(path)
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise ImageError(f"{path}: cannot open ({oiio.geterror()})")
    try:
        value = inp.spec().get_string_attribute(PALETTE_ATTRIBUTE, "")
    finally:
        inp.close()
    if not value:
        raise ImageError(f"{path}: no '{PALETTE_ATTRIBUTE}' metadata")
    return json.loads(value)


def synwoodscape_palette_dict() -> dict[str, Any]:
    """The SynWoodScape palette as metadata: ``{"classes": names, "colors": [[r, g, b], ...]}``
    (also the content of a ``seg_annotation_info.json``)."""
    from ..groundtruth import SYNWOODSCAPE_CLASSES, SYNWOODSCAPE_PALETTE

    return {"classes": list(SYNWOODSCAPE_CLASSES), "colors": SYNWOODSCAPE_PALETTE.astype(int).tolist()}


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


def boxes_2d_rows(xyxy: np.ndarray, present: np.ndarray, class_id: np.ndarray) -> list[tuple[str, int, int, int, int, int]]:
    """CSV rows of the present boxes (`jaxfish.groundtruth.Boxes2D` arrays and box classes)."""
    from ..groundtruth import SYNWOODSCAPE_CLASSES

    rows = []
    for b, c, p in zip(np.asarray(xyxy), np.asarray(class_id), np.asarray(present), strict=True):
        if p and 0 <= int(c) < len(SYNWOODSCAPE_CLASSES):
            rows.append((SYNWOODSCAPE_CLASSES[int(c)], int(c), *(int(v) for v in b)))
    return rows  # type: ignore[return-value]


def write_boxes_3d_pickle(path: str | os.PathLike, boxes: Mapping[int, Mapping[str, Any]]) -> Path:
    """3D boxes as a pickle ``{actor_id: {"corners_world": (8, 3), "corners_vehicle": (8, 3),
    "class_id": int, "class_name": str}}``: corners in CARLA world and ISO 8855 vehicle frames
    (order `jaxfish.groundtruth.CORNER_SIGNS`). SynWoodScape's pickle has world corners only and
    no class; this one adds both."""
    clean = {int(k): {kk: (np.asarray(vv, np.float64) if kk.startswith("corners") else vv) for kk, vv in v.items()}
             for k, v in boxes.items()}
    return atomic_write_bytes(path, pickle.dumps(clean, protocol=4))


def read_boxes_3d_pickle(path: str | os.PathLike) -> dict[int, dict[str, Any]]:
    """Read a 3D box pickle (trusted files only: pickle runs code)."""
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
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.save(fh, np.asarray(depth_m, np.float32), allow_pickle=False)
    return path
