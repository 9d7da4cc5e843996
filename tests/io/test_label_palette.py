"""Label PNGs stored as palettes (colour type 3) read as their indices, never their colours; label
PNGs with colour channels are refused by `read_label_png`."""

from __future__ import annotations

import shutil
import struct
import zlib

import numpy as np
import pytest
from PIL import Image

from jaxfish import ImageError
from jaxfish.io import _png, read_image, read_label_png, write_image
from tests.conftest import SHARED
from tests.hostile.cases_png import assemble

ADAM7 = ((0, 0, 8, 8), (0, 4, 8, 8), (4, 0, 8, 4), (0, 2, 4, 4), (2, 0, 4, 2), (0, 1, 2, 2), (1, 0, 2, 1))


def _paeth(a: int, b: int, c: int) -> int:
    p = a + b - c
    pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
    return a if pa <= pb and pa <= pc else b if pb <= pc else c


def _filtered(rows: list[bytes], first_filter: int) -> bytes:
    """``rows`` (packed, one byte per filter unit) with filter types cycling from ``first_filter``."""
    out, prev = b"", bytes(len(rows[0]))
    for i, row in enumerate(rows):
        kind = (first_filter + i) % 5
        line = bytearray([kind])
        for j, x in enumerate(row):
            a, b, c = (row[j - 1] if j else 0), prev[j], (prev[j - 1] if j else 0)
            pred = (0, a, b, (a + b) // 2, _paeth(a, b, c))[kind]
            line.append((x - pred) % 256)
        out += bytes(line)
        prev = row
    return out


def _packed(indices: np.ndarray, bits: int) -> list[bytes]:
    per = 8 // bits
    rows = []
    for r in indices:
        padded = np.zeros(-(-len(r) // per) * per, np.uint8)
        padded[:len(r)] = r
        groups = padded.reshape(-1, per).astype(np.int64) << (bits * np.arange(per - 1, -1, -1))
        rows.append(groups.sum(axis=1).astype(np.uint8).tobytes())
    return rows


def palette_png(indices: np.ndarray, bits: int, *, interlace: bool = False, first_filter: int = 0,
                transparency: bool = False) -> bytes:
    """A palette PNG of ``indices`` at ``bits`` bits per index, each colour far from its index."""
    h, w = indices.shape
    if interlace:
        raw = b"".join(_filtered(_packed(indices[y0::dy, x0::dx], bits), first_filter)
                       for y0, x0, dy, dx in ADAM7 if indices[y0::dy, x0::dx].size)
    else:
        raw = _filtered(_packed(indices, bits), first_filter)
    n = 1 << bits
    plte = bytes(c for i in range(n) for c in ((200 + 7 * i) % 256, (3 * i) % 256, 50))
    parts = [(b"IHDR", struct.pack(">IIBBBBB", w, h, bits, 3, 0, 0, int(interlace))), (b"PLTE", plte)]
    if transparency:
        parts.append((b"tRNS", bytes([0] + [255] * (n - 1))))
    return assemble(parts + [(b"IDAT", zlib.compress(raw)), (b"IEND", b"")])


@pytest.mark.parametrize("bits", [1, 2, 4, 8])
@pytest.mark.parametrize("interlace,first_filter,transparency", [(False, 0, False), (False, 1, True), (True, 3, False)])
def test_palette_label_png_reads_as_its_indices(tmp_path, bits, interlace, first_filter, transparency):
    ids = (np.arange(11 * 13).reshape(11, 13) * 5 % (1 << bits)).astype(np.uint8)
    path = tmp_path / "labels.png"
    path.write_bytes(palette_png(ids, bits, interlace=interlace, first_filter=first_filter, transparency=transparency))
    assert np.array_equal(np.asarray(Image.open(path)), ids)  # Pillow reads the same indices
    got = read_label_png(path)
    assert got.dtype == np.int32 and np.array_equal(got, ids)
    lossless = read_image(path, lossless=True)
    assert lossless.shape == (11, 13, 1) and lossless.dtype == np.uint8 and np.array_equal(lossless[..., 0], ids)
    colours = read_image(path)  # without lossless: the colours, as before
    assert colours.shape[-1] in (3, 4) and np.array_equal(colours[..., 0], (200 + 7 * ids.astype(int)) % 256)


def test_pillow_palette_label_png(tmp_path):
    ids = (np.arange(48).reshape(6, 8) % 25).astype(np.uint8)
    im = Image.fromarray(ids, mode="P")
    im.putpalette([c for i in range(256) for c in ((200 + 7 * i) % 256, 3 * i % 256, 50)])
    im.save(tmp_path / "p.png")
    assert np.array_equal(read_label_png(tmp_path / "p.png"), ids)


def test_low_bit_palette_without_pyspng_is_refused(tmp_path, monkeypatch):
    path = tmp_path / "labels.png"
    path.write_bytes(palette_png(np.zeros((3, 4), np.uint8), 4))
    monkeypatch.setattr(_png, "_pyspng", None)
    with pytest.raises(ImageError, match=r"labels\.png: .*4-bit palette PNG needs pyspng"):
        read_label_png(path)


@pytest.mark.parametrize("channels,kind", [(2, "grey \\+ alpha"), (3, "RGB colour"), (4, "RGBA colour")])
def test_label_png_with_colour_channels_is_refused(tmp_path, channels, kind):
    path = write_image(tmp_path / "colour.png", np.zeros((4, 5, channels), np.uint8))
    with pytest.raises(ImageError, match=rf"colour\.png: expected an index PNG .* {channels} channels \({kind}\)"):
        read_label_png(path)


def test_dataset_semantics_of_a_palette_png_are_its_indices(tmp_path):
    import jaxfish.dataset as jd

    for d in ("rgb_images", "semantic_annotations/gtLabels", "calibration_data"):
        (tmp_path / d).mkdir(parents=True)
    shutil.copy(SHARED / "calibration" / "synwoodscape" / "FV.json", tmp_path / "calibration_data" / "FV.json")
    write_image(tmp_path / "rgb_images" / "00000_FV.png", np.zeros((6, 8, 3), np.uint8))
    ids = (np.arange(48).reshape(6, 8) % 25).astype(np.uint8)
    (tmp_path / "semantic_annotations" / "gtLabels" / "00000_FV.png").write_bytes(palette_png(ids, 8))
    sample = jd.open(tmp_path, fields={"rgb", "semantics"}, cameras=["FV"])[0]
    assert np.array_equal(np.asarray(sample.cameras["FV"].semantics), ids)


def test_dataset_labels_in_colour_channels_are_refused_unless_grey(tmp_path):
    """The dataset reader takes grey labels stored as RGB (all channels equal) and refuses
    colours, naming the file."""
    import jaxfish.dataset as jd

    for d in ("rgb_images", "semantic_annotations/gtLabels", "calibration_data"):
        (tmp_path / d).mkdir(parents=True)
    shutil.copy(SHARED / "calibration" / "synwoodscape" / "FV.json", tmp_path / "calibration_data" / "FV.json")
    write_image(tmp_path / "rgb_images" / "00000_FV.png", np.zeros((6, 8, 3), np.uint8))
    ids = (np.arange(48).reshape(6, 8) % 25).astype(np.uint8)
    labels = tmp_path / "semantic_annotations" / "gtLabels" / "00000_FV.png"
    write_image(labels, np.repeat(ids[..., None], 3, axis=-1))
    sample = jd.open(tmp_path, fields={"rgb", "semantics"}, cameras=["FV"])[0]
    assert np.array_equal(np.asarray(sample.cameras["FV"].semantics), ids)
    write_image(labels, np.stack([ids, ids + 1, ids], axis=-1))
    with pytest.raises(jd.DatasetReadError, match=r"00000_FV\.png: expected labels .* 3 channels of different colours"):
        jd.open(tmp_path, fields={"rgb", "semantics"}, cameras=["FV"])[0]
