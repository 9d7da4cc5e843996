"""The one JSON reader of every input file (what it refuses, naming the file and the field) and the
strict JSON writer (no NaN or infinity ever reaches a file)."""

from __future__ import annotations

import json
import math
import os
import re

import pytest

from jaxfish import JaxfishError
from jaxfish.io._json import non_finite_field, read_json, regular_file, to_json_text, write_json


def test_an_integer_beyond_the_int_string_limit_names_the_file_and_field(tmp_path):
    path = tmp_path / "a.json"
    path.write_text('{"frames": [0, 1], "actors": [{"id": 3}, {"id": ' + "9" * 5000 + "}]}")
    with pytest.raises(JaxfishError) as e:
        read_json(path, JaxfishError)
    assert str(e.value) == (f"{path}: field 'actors[1].id': expected a finite number, got an integer of 5000 digits "
                            "(beyond the float range)")


@pytest.mark.parametrize("literal, shown", [("1" + "0" * 400, "an integer of 401 digits"),
                                            ("-" + "9" * 309, "an integer of 309 digits"),
                                            ("1e400", "1e400"), ("-2.5E+999", "-2.5E+999")])
def test_numbers_beyond_the_float_range_name_the_field(tmp_path, literal, shown):
    path = tmp_path / "q.json"
    path.write_text('{"extrinsic": {"quaternion": [0, 0, 0, ' + literal + "]}}")
    with pytest.raises(JaxfishError, match=r"q\.json: field 'extrinsic\.quaternion\[3\]': .*" + re.escape(shown)):
        read_json(path, JaxfishError)
    path.write_text(literal)
    with pytest.raises(JaxfishError, match="field '<root>'"):
        read_json(path, JaxfishError)


def test_numbers_within_the_float_range_are_kept_exactly(tmp_path):
    path = tmp_path / "ok.json"
    big = 2**70
    path.write_text(f'{{"id": {big}, "x": 1e308, "y": -1e-400, "n": [{"9" * 308}]}}')
    data = read_json(path, JaxfishError)
    assert data["id"] == big and isinstance(data["id"], int) and data["x"] == 1e308 and data["n"] == [int("9" * 308)]


def test_paths_that_are_not_regular_files_are_refused_before_reading(tmp_path):
    (tmp_path / "dir.json").mkdir()
    with pytest.raises(JaxfishError, match=r"dir\.json: is a directory"):
        read_json(tmp_path / "dir.json", JaxfishError)
    os.mkfifo(tmp_path / "pipe.json")  # reading it would block forever
    with pytest.raises(JaxfishError, match=r"pipe\.json: is a FIFO \(named pipe\), expected a regular file"):
        read_json(tmp_path / "pipe.json", JaxfishError)
    os.symlink(tmp_path / "b.json", tmp_path / "a.json")
    os.symlink(tmp_path / "a.json", tmp_path / "b.json")
    with pytest.raises(JaxfishError, match=r"a\.json: cannot read the file \(Too many levels of symbolic links\)"):
        read_json(tmp_path / "a.json", JaxfishError)
    os.symlink(tmp_path / "gone.json", tmp_path / "dangling.json")
    with pytest.raises(FileNotFoundError, match=r"dangling\.json: file not found \(a broken symbolic link\)"):
        read_json(tmp_path / "dangling.json", JaxfishError)
    with pytest.raises(FileNotFoundError, match=r"nope\.json: calibration file not found$"):
        regular_file(tmp_path / "nope.json", JaxfishError, "calibration file")
    real = tmp_path / "real.json"
    real.write_text("{}")
    os.symlink(real, tmp_path / "link.json")
    assert read_json(tmp_path / "link.json", JaxfishError, obj=True) == {}



@pytest.mark.parametrize(("data", "field"), [
    ({"a": [1.0, {"b": math.nan}]}, "a[1].b"),
    ({"x": 1, "y": (2.0, -math.inf)}, "y[1]"),
    (math.inf, "<root>"),
    ([{"k": 1e308 * 10}], "[0].k"),
])
def test_a_non_finite_number_names_the_file_and_field_and_writes_nothing(tmp_path, data, field):
    assert non_finite_field(data) == field
    path = tmp_path / "out.json"
    with pytest.raises(JaxfishError, match=re.escape(f"out.json: not written: field '{field}' is not a finite number")) as info:
        write_json(path, data)
    assert path.name in str(info.value)
    assert not list(tmp_path.iterdir())  # nothing, not even a temporary file


def test_finite_data_round_trip_strictly(tmp_path):
    data = {"a": [1.0, 2, {"b": -0.0}], "s": "NaN", "big": 10**400, "t": True, "n": None}
    assert non_finite_field(data) is None
    path = write_json(tmp_path / "ok.json", data, indent=1)
    assert json.loads(path.read_text()) == data
    assert to_json_text(path, data).endswith("}\n")


def test_the_error_type_is_the_callers(tmp_path):
    from jaxfish import CalibrationError

    with pytest.raises(CalibrationError):
        write_json(tmp_path / "c.json", {"k1": math.nan}, error=CalibrationError)
