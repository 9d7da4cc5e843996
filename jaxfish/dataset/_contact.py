"""Contact sheets: one PNG per sample laid out like the SynWoodScape paper's overview figure.

Rows (top to bottom): RGB at t-1, RGB at t, depth, semantics, instances, motion, optical flow,
events; columns (left to right): front (FV), rear (RV), top view (BEV), left (MVL), right (MVR).
Every tile is read from the built dataset's files (so the sheet shows what a user gets), resized
with nearest-neighbour sampling to a common height; a missing modality (the BEV has no events) is a
grey tile. Row and column labels are drawn with OpenImageIO's text renderer when a font is
available, else the sheet has none (the layout above is fixed).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ._layout import BEV_CAMERA

CONTACT_ROWS: tuple[tuple[str, str], ...] = (
    ("RGB t-1", "previous_images/{sample}_{camera}_prev.png"),
    ("RGB t", "rgb_images/{sample}_{camera}.png"),
    ("depth", "depth_maps/colormap/{sample}_{camera}.png"),
    ("semantics", "semantic_annotations/rgbLabels/{sample}_{camera}.png"),
    ("instances", "instance_annotations/rgbLabels/{sample}_{camera}.png"),
    ("motion", "motion_annotations/rgbLabels/{sample}_{camera}.png"),
    ("flow", "optical_flow/color_coded/{sample}_{camera}.png"),
    ("events", "dvs_signals/color_coded/{sample}_{camera}.png"),
)
"""Contact-sheet rows: (label, dataset file pattern with ``{sample}`` and ``{camera}``)."""
CONTACT_COLUMNS: tuple[tuple[str, str], ...] = (
    ("front (FV)", "FV"), ("rear (RV)", "RV"), ("top view (BEV)", BEV_CAMERA), ("left (MVL)", "MVL"),
    ("right (MVR)", "MVR"),
)
"""Contact-sheet columns: (label, camera name in file names)."""
_GAP = 4
_LABEL_W = 96
_LABEL_H = 22
_BG = 32
_MISSING = 96


def _resize_nearest(img: np.ndarray, h: int, w: int) -> np.ndarray:
    ys = np.minimum(((np.arange(h) + 0.5) * img.shape[0] / h).astype(np.int64), img.shape[0] - 1)
    xs = np.minimum(((np.arange(w) + 0.5) * img.shape[1] / w).astype(np.int64), img.shape[1] - 1)
    return img[ys][:, xs]


def _as_rgb(a: np.ndarray) -> np.ndarray:
    if a.ndim == 2:
        a = a[..., None]
    if a.dtype != np.uint8:
        a = (a.astype(np.float64) * 255.0 / max(float(np.iinfo(a.dtype).max), 1.0)).astype(np.uint8) \
            if np.issubdtype(a.dtype, np.integer) else np.clip(a * 255.0, 0, 255).astype(np.uint8)
    if a.shape[-1] == 1:
        a = np.repeat(a, 3, -1)
    return a[..., :3]


def _text(canvas: np.ndarray, x: int, y: int, text: str, size: int = 14) -> None:
    """Draw white text with its baseline at (x, y) (no-op without a usable font)."""
    try:
        import OpenImageIO as oiio

        buf = oiio.ImageBuf(np.ascontiguousarray(canvas))
        if oiio.ImageBufAlgo.render_text(buf, int(x), int(y), text, size, "", (1.0, 1.0, 1.0)):
            canvas[...] = buf.get_pixels(oiio.UINT8).reshape(canvas.shape)
    except Exception:  # no font / renderer: the fixed layout is documented instead
        return


def contact_sheet(dataset_dir: str | os.PathLike, sample: str, *, tile_height: int = 160,
                  labels: bool = True) -> np.ndarray:
    """The contact sheet of ``sample`` of a built dataset as an ``(H, W, 3)`` uint8 image (layout:
    `CONTACT_ROWS` x `CONTACT_COLUMNS`, tiles ``tile_height`` pixels high, widths following each
    column's aspect ratio)."""
    from ..io import read_image

    root = Path(dataset_dir)
    tiles: dict[tuple[int, int], np.ndarray] = {}
    col_aspect = []
    for j, (_, cam) in enumerate(CONTACT_COLUMNS):
        aspect = None
        for i, (_, pattern) in enumerate(CONTACT_ROWS):
            p = root / pattern.format(sample=sample, camera=cam)
            if p.is_file():
                img = _as_rgb(read_image(p))
                tiles[(i, j)] = img
                aspect = aspect or img.shape[1] / img.shape[0]
        col_aspect.append(aspect or 4.0 / 3.0)
    th = int(tile_height)
    widths = [max(1, round(th * a)) for a in col_aspect]
    left = _LABEL_W if labels else 0
    top = _LABEL_H if labels else 0
    height = top + len(CONTACT_ROWS) * (th + _GAP) + _GAP
    width = left + sum(w + _GAP for w in widths) + _GAP
    canvas = np.full((height, width, 3), _BG, np.uint8)
    x0s = np.cumsum([left + _GAP] + [w + _GAP for w in widths[:-1]])
    for i in range(len(CONTACT_ROWS)):
        y0 = top + _GAP + i * (th + _GAP)
        for j, w in enumerate(widths):
            x0 = int(x0s[j])
            img = tiles.get((i, j))
            canvas[y0:y0 + th, x0:x0 + w] = _MISSING if img is None else _resize_nearest(img, th, w)
    if labels:
        for j, (name, _) in enumerate(CONTACT_COLUMNS):
            _text(canvas, int(x0s[j]) + 4, _LABEL_H - 6, name)
        for i, (name, _) in enumerate(CONTACT_ROWS):
            _text(canvas, 6, top + _GAP + i * (th + _GAP) + th // 2 + 5, name)
    return canvas


def write_contact_sheet(dataset_dir: str | os.PathLike, sample: str, path: str | os.PathLike, *,
                        tile_height: int = 160, labels: bool = True) -> Path:
    """Write `contact_sheet` of ``sample`` as a PNG at ``path`` (atomic)."""
    from ..io import write_image

    return write_image(path, contact_sheet(dataset_dir, sample, tile_height=tile_height, labels=labels))
