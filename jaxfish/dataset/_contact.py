"""Contact sheets: one PNG per sample laid out like the SynWoodScape paper's overview figure.

Rows (top to bottom): RGB at t-1, RGB at t, depth, semantics, instances, motion, optical flow,
events; columns (left to right): front (FV), rear (RV), top view (BEV), left (MVL), right (MVR).
Every tile is read from the built dataset's files (so the sheet shows what a user gets), resized
with nearest-neighbour sampling to a common height; a missing modality (the BEV has no events) is a
grey tile. Below the tiles, a legend row: the optical-flow colour wheel (under the first column:
hue = flow direction, saturation = magnitude relative to the image's largest) and the depth scale
(under the other columns: `jaxfish.pipeline.depth_to_color`'s ramp on log range from 0.5 m, left,
to 100 m, right, with ticks). Row and column labels and the legend's tick labels are drawn with
OpenImageIO's text renderer when a font is available, else the sheet has none (the layout above is
fixed).
"""

from __future__ import annotations

import functools
import os
from pathlib import Path
from typing import NamedTuple

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
DEPTH_TICKS_M: tuple[float, ...] = (0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0)
"""Ranges (metres) marked on the contact sheet's depth scale."""


class LegendLayout(NamedTuple):
    """Where the contact sheet's legend row is drawn (pixels of the sheet): the flow colour wheel's
    centre ``(wheel_cx, wheel_cy)`` and radius, and the depth scale's box ``[bar_x0, bar_x1) x
    [bar_y0, bar_y1)`` (column ``x`` shows the range ``lo (hi / lo) ** ((x - bar_x0) / (bar_x1 -
    bar_x0 - 1))`` over `jaxfish.pipeline.DEPTH_COLOR_RANGE_M` ``(lo, hi)``)."""

    wheel_cx: int
    wheel_cy: int
    wheel_radius: int
    bar_x0: int
    bar_x1: int
    bar_y0: int
    bar_y1: int


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
    """Draw white text with its baseline at (x, y) (no-op without a usable font). The glyphs are
    rendered into a crop of the canvas around the text (a margin of two font sizes above the
    baseline, one below and at each end), not the whole canvas."""
    try:
        import OpenImageIO as oiio

        y0, y1 = max(0, int(y) - 2 * size), min(canvas.shape[0], int(y) + size)
        x0, x1 = max(0, int(x) - size), min(canvas.shape[1], int(x) + (len(text) + 1) * size)
        if y0 >= y1 or x0 >= x1:
            return
        crop = np.ascontiguousarray(canvas[y0:y1, x0:x1])
        buf = oiio.ImageBuf(crop)
        if oiio.ImageBufAlgo.render_text(buf, int(x) - x0, int(y) - y0, text, size, "", (1.0, 1.0, 1.0)):
            canvas[y0:y1, x0:x1] = buf.get_pixels(oiio.UINT8).reshape(crop.shape)
    except Exception:  # no font / renderer: the fixed layout is documented instead
        return


def flow_wheel_tile(radius: int) -> tuple[np.ndarray, np.ndarray]:
    """The flow colour wheel as a ``(2 radius + 1)``-pixel square uint8 RGB image and its disk mask:
    the pixel at offset ``(du, dv)`` from the centre has `jaxfish.flow_to_color`'s colour of the
    flow ``(du, dv) / radius`` with ``max_radius = 1`` (float32), i.e. of a flow in that image
    direction whose magnitude is that fraction of the image's largest."""
    import jax.numpy as jnp

    r = int(radius)
    off = np.arange(-r, r + 1, dtype=np.float32) / np.float32(max(r, 1))
    du, dv = np.meshgrid(off, off, indexing="xy")
    flow = jnp.asarray(np.stack([du, dv], axis=-1), jnp.float32)
    rgb = np.asarray(_wheel_colors()(flow))
    return rgb, du * du + dv * dv <= 1.0


@functools.cache
def _wheel_colors():
    """`jaxfish.flow_to_color` with ``max_radius = 1`` as one compiled program (kept: op by op it
    compiles each operation on its own)."""
    import jax

    from ..groundtruth import flow_to_color

    return jax.jit(functools.partial(flow_to_color, max_radius=1.0))


def depth_scale_tile(width: int, height: int) -> np.ndarray:
    """The depth scale as a ``(height, width, 3)`` uint8 image: column ``x`` is
    `jaxfish.pipeline.depth_to_color`'s colour of the range ``lo (hi / lo) ** (x / (width - 1))``
    over `jaxfish.pipeline.DEPTH_COLOR_RANGE_M` ``(lo, hi)`` (log scale, near left)."""
    from ..pipeline import DEPTH_COLOR_RANGE_M, depth_to_color

    lo, hi = DEPTH_COLOR_RANGE_M
    rng = lo * (hi / lo) ** (np.arange(width) / max(width - 1, 1))
    return np.broadcast_to(depth_to_color(rng.astype(np.float32)[None, :]), (height, width, 3)).copy()


def legend_layout(tile_height: int, tile_widths: list[int], labels: bool = True) -> LegendLayout:
    """The legend row's geometry of a contact sheet with tiles ``tile_height`` pixels high and
    columns ``tile_widths`` wide (see `LegendLayout`)."""
    th = int(tile_height)
    left = _LABEL_W if labels else 0
    top = _LABEL_H if labels else 0
    y0 = top + _GAP + len(CONTACT_ROWS) * (th + _GAP)
    x0s = np.cumsum([left + _GAP] + [w + _GAP for w in tile_widths[:-1]])
    radius = max(2, (min(th, tile_widths[0]) - 8) // 2)
    bar_x0 = int(x0s[1]) if len(tile_widths) > 1 else int(x0s[0]) + 2 * radius + 2 * _GAP
    bar_x1 = int(x0s[-1]) + tile_widths[-1] if len(tile_widths) > 1 else bar_x0 + 4 * th
    bar_y0 = y0 + th // 3
    return LegendLayout(int(x0s[0]) + tile_widths[0] // 2, y0 + th // 2, radius, bar_x0, bar_x1, bar_y0,
                        bar_y0 + max(2, th // 4))


def _draw_legend(canvas: np.ndarray, g: LegendLayout, labels: bool) -> None:
    """Draw the flow wheel and the depth scale (with ticks, and their labels when ``labels``)."""
    from ..pipeline import DEPTH_COLOR_RANGE_M

    wheel, disk = flow_wheel_tile(g.wheel_radius)
    r = g.wheel_radius
    patch = canvas[g.wheel_cy - r: g.wheel_cy + r + 1, g.wheel_cx - r: g.wheel_cx + r + 1]
    patch[disk] = wheel[disk]
    width = g.bar_x1 - g.bar_x0
    canvas[g.bar_y0:g.bar_y1, g.bar_x0:g.bar_x1] = depth_scale_tile(width, g.bar_y1 - g.bar_y0)
    lo, hi = DEPTH_COLOR_RANGE_M
    for d in DEPTH_TICKS_M:
        x = g.bar_x0 + int(round((width - 1) * np.log(d / lo) / np.log(hi / lo)))
        canvas[g.bar_y1:g.bar_y1 + 6, x] = 255
        if labels:
            last = d == DEPTH_TICKS_M[-1]
            _text(canvas, x - (36 if last else 8), g.bar_y1 + 22, f"{d:g}" + (" m" if last else ""), 13)
    if labels:
        _text(canvas, g.bar_x0, g.bar_y0 - 8, "depth: range along the ray (log scale); sky and no ray: black")
        _text(canvas, 6, g.wheel_cy - 4, "flow wheel,")
        _text(canvas, 6, g.wheel_cy + 14, "depth")


def contact_sheet(dataset_dir: str | os.PathLike, sample: str, *, tile_height: int = 160,
                  labels: bool = True, legend: bool = True) -> np.ndarray:
    """The contact sheet of ``sample`` of a built dataset as an ``(H, W, 3)`` uint8 image (layout:
    `CONTACT_ROWS` x `CONTACT_COLUMNS`, tiles ``tile_height`` pixels high, widths following each
    column's aspect ratio; with ``legend``, one more row of the same height below: the flow colour
    wheel and the depth scale, placed as `legend_layout` says)."""
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
    height = top + (len(CONTACT_ROWS) + int(legend)) * (th + _GAP) + _GAP
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
    if legend:
        _draw_legend(canvas, legend_layout(th, widths, labels), labels)
    return canvas


def write_contact_sheet(dataset_dir: str | os.PathLike, sample: str, path: str | os.PathLike, *,
                        tile_height: int = 160, labels: bool = True, legend: bool = True) -> Path:
    """Write `contact_sheet` of ``sample`` as a PNG at ``path`` (atomic)."""
    from ..io import write_image

    return write_image(path, contact_sheet(dataset_dir, sample, tile_height=tile_height, labels=labels, legend=legend))
