"""COLMAP ``images.txt``: two lines per image, the second its 2D points (maybe empty); an image
line whose points line is missing is refused naming the file and line, never swallowed."""

from __future__ import annotations

import numpy as np
import pytest

import jaxfish as jf
from jaxfish.io import read_calibration_file

CAMERAS = "1 PINHOLE 640 480 500 500 320 240\n2 PINHOLE 640 480 500 500 320 240\n"
FRONT = "1 1 0 0 0 0 0 1 1 front.png"
REAR = "2 1 0 0 0 0 0 2 2 rear.png"


def _read(tmp_path, images: str):
    (tmp_path / "cameras.txt").write_text(CAMERAS)
    (tmp_path / "images.txt").write_text(images)
    return [(c.name, np.asarray(c.camera_to_vehicle.translation).tolist()) for c in read_calibration_file(tmp_path)]


@pytest.mark.parametrize("images", [
    f"{FRONT}\n{REAR}\n",  # no points lines
    f"{FRONT}\n1.5 2.5 -1 3\n{REAR}\n\n",  # not triples
    f"{FRONT}\n1.5 abc -1\n{REAR}\n\n",  # not numbers
])
def test_an_image_line_without_its_points_line_is_refused(tmp_path, images):
    with pytest.raises(jf.CalibrationError, match=r"images\.txt: field 'line 2': expected the POINTS2D line "
                                                  r"of the image on line 1"):
        _read(tmp_path, images)


@pytest.mark.parametrize("images", [
    f"{FRONT}\n\n{REAR}\n\n",  # empty points lines
    f"{FRONT}\n1.5 2.5 -1 7 8 12\n{REAR}\n3 4 -1\n",  # points
    f"# header\n\n{FRONT}\n\n\n# between\n{REAR}\n",  # comments and blank lines between images, the last ends the file
    f"{FRONT}\n# a comment line is a points line, as for COLMAP\n{REAR}\n\n",
])
def test_two_lines_per_image_are_read(tmp_path, images):
    assert _read(tmp_path, images) == [("front", [0.0, 0.0, -1.0]), ("rear", [0.0, 0.0, -2.0])]


def test_pycolmap_reads_the_accepted_layouts_alike(tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    for i, images in enumerate((f"{FRONT}\n\n{REAR}\n\n", f"{FRONT}\n# c\n{REAR}\n1 2 -1\n")):
        d = tmp_path / str(i)
        d.mkdir()
        (d / "points3D.txt").write_text("")
        ours = _read(d, images)
        rec = pycolmap.Reconstruction(str(d))
        assert sorted(im.name.rsplit(".", 1)[0] for im in rec.images.values()) == [n for n, _ in ours]
