"""Label files: index and colour PNGs (palette metadata), 2D box CSV, 3D box pickle, displacements."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from jaxfish import ImageError
from jaxfish.dataset import synwoodscape_palette_dict
from jaxfish.dataset._sink import boxes_2d_rows
from jaxfish.io import (
    read_boxes_2d_csv,
    read_boxes_3d_pickle,
    read_displacements,
    read_image,
    read_label_png,
    read_palette,
    write_boxes_2d_csv,
    write_boxes_3d_pickle,
    write_color_png,
    write_depth_npy,
    write_displacements,
    write_label_png,
)


def test_label_png_round_trip(tmp_path):
    lab = np.random.default_rng(0).integers(0, 25, (6, 8))
    write_label_png(tmp_path / "l.png", lab)
    assert read_image(tmp_path / "l.png").dtype == np.uint8
    np.testing.assert_array_equal(read_label_png(tmp_path / "l.png"), lab)
    big = lab * 1000
    write_label_png(tmp_path / "i.png", big)
    np.testing.assert_array_equal(read_label_png(tmp_path / "i.png"), big)


@pytest.mark.parametrize("dtype", [np.uint8, np.int8, np.int32, np.uint16, np.int64, np.float32, np.float64, bool])
def test_label_png_pixels_are_the_clipped_integer_labels_in_the_narrowest_type(tmp_path, dtype):
    """Negative labels store 0, floats are truncated towards zero, uint8 below 256 else uint16."""
    rng = np.random.default_rng(2)
    lab = rng.integers(-5, 120, (5, 7)).astype(dtype) if dtype is not bool else rng.random((5, 7)) < 0.5
    if np.dtype(dtype).kind == "f":
        lab = lab + np.asarray(0.75, dtype)
    want = np.clip(np.asarray(lab).astype(np.int64), 0, None)
    stored = read_image(write_label_png(tmp_path / "l.png", lab))[..., 0]
    assert stored.dtype == np.uint8
    np.testing.assert_array_equal(stored, want)
    if np.dtype(dtype).itemsize > 1 and dtype is not bool:
        wide = np.asarray(want * 500, dtype)
        stored = read_image(write_label_png(tmp_path / "w.png", wide))[..., 0]
        assert stored.dtype == np.uint16
        np.testing.assert_array_equal(stored, np.asarray(wide).astype(np.int64))
        with pytest.raises(ImageError, match="labels above 65535"):
            write_label_png(tmp_path / "x.png", np.full((2, 2), 70000, np.int64))


def test_colour_png_carries_its_palette(tmp_path):
    rgb = np.random.default_rng(1).integers(0, 256, (4, 5, 3)).astype(np.uint8)
    pal = synwoodscape_palette_dict()
    write_color_png(tmp_path / "c.png", rgb, pal)
    np.testing.assert_array_equal(read_image(tmp_path / "c.png"), rgb)
    assert read_palette(tmp_path / "c.png") == pal
    assert len(pal["classes"]) == 25 and pal["colors"][24] == list(pal["colors"][24])
    write_color_png(tmp_path / "n.png", rgb)
    with pytest.raises(ImageError, match="palette"):
        read_palette(tmp_path / "n.png")


def test_box_csv_round_trip(tmp_path):
    rows = boxes_2d_rows(np.array([[1, 2, 30, 40], [0, 0, 0, 0], [5, 6, 7, 8]]), np.array([True, False, True]),
                         np.array([10, 4, 21]))
    assert rows == [("vehicle", 10, 1, 2, 30, 40), ("two_wheeler", 21, 5, 6, 7, 8)]
    write_boxes_2d_csv(tmp_path / "b.txt", rows)
    assert (tmp_path / "b.txt").read_text().splitlines()[0] == "vehicle,10,1,2,30,40"
    assert read_boxes_2d_csv(tmp_path / "b.txt") == rows
    write_boxes_2d_csv(tmp_path / "e.txt", [])
    assert (tmp_path / "e.txt").read_text() == "" and read_boxes_2d_csv(tmp_path / "e.txt") == []
    (tmp_path / "s.txt").write_text("car, 10, 1, 2, 3, 4\n")  # WoodScape files have spaces
    assert read_boxes_2d_csv(tmp_path / "s.txt") == [("car", 10, 1, 2, 3, 4)]
    (tmp_path / "x.txt").write_text("car,10,1\n")
    with pytest.raises(ImageError, match="x.txt:1"):
        read_boxes_2d_csv(tmp_path / "x.txt")


def test_box_pickle_and_displacements(tmp_path):
    corners = np.arange(24.0).reshape(8, 3)
    write_boxes_3d_pickle(tmp_path / "b.pkl", {7: corners})
    with open(tmp_path / "b.pkl", "rb") as fh:  # the release format, read without jaxfish
        raw = pickle.load(fh)
    assert list(raw) == [7] and raw[7].dtype == np.float64
    np.testing.assert_array_equal(raw[7], corners)
    np.testing.assert_array_equal(read_boxes_3d_pickle(tmp_path / "b.pkl")[7], corners)
    with pytest.raises(ImageError, match=r"b2\.pkl: box 7"):
        write_boxes_3d_pickle(tmp_path / "b2.pkl", {7: {"corners_world": corners}})
    assert not (tmp_path / "b2.pkl").exists()
    write_displacements(tmp_path / "d.txt", [3, 4], [10, 4], [0.75, 0.0], threshold_m=0.5)
    assert read_displacements(tmp_path / "d.txt") == {3: 0.75, 4: 0.0}
    assert (tmp_path / "d.txt").read_text().splitlines()[1] == "3 10 0.750000 1"
    write_depth_npy(tmp_path / "d.npy", np.full((2, 2), 1000.0))
    assert np.load(tmp_path / "d.npy").dtype == np.float32


def test_box_slots_share_one_size_across_actor_counts():
    from jaxfish import groundtruth as gt
    from jaxfish.pipeline import BOX_SLOT_QUANTUM, box_slots

    q = BOX_SLOT_QUANTUM
    assert [box_slots(n) for n in (0, 1, q, q + 1, 3 * q)] == [q, q, q, 2 * q, 3 * q]
    actor = {"id": 7, "category": "four_wheeler", "bounding_box": {"location": [0, 0, 0.7], "extent": [2, 1, 0.7]},
             "transform": {"location": [5, 0, 0], "rotation": [0, 0, 0]}}
    boxes = gt.boxes_from_actors([actor], "t", pad_to=box_slots(1))
    assert boxes.num_boxes == q and int(np.sum(np.asarray(boxes.active))) == 1


def test_a_label_png_that_is_a_jpeg_is_refused(tmp_path):
    import OpenImageIO as oiio

    path = tmp_path / "labels.png"
    out = oiio.ImageOutput.create("x.jpg")
    out.open(str(tmp_path / "x.jpg"), oiio.ImageSpec(8, 8, 1, oiio.UINT8))
    out.write_image(np.full((8, 8, 1), 7, np.uint8))
    out.close()
    (tmp_path / "x.jpg").rename(path)
    with pytest.raises(ImageError, match=r"labels\.png: expected a lossless PNG file, found JPEG data"):
        read_label_png(path)
