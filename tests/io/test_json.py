"""The strict JSON writer: no NaN or infinity ever reaches a file."""

from __future__ import annotations

import json
import math
import re

import pytest

from jaxfish import JaxfishError
from jaxfish.io._json import non_finite_field, to_json_text, write_json


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
