"""Event files: CARLA dtype and tonic arrays round trip with their time unit; colour rendering."""

from __future__ import annotations

import numpy as np
import pytest

from jaxfish import ImageError
from jaxfish.io import (
    DVS_EVENT_DTYPE,
    TONIC_EVENT_DTYPE,
    carla_events,
    carla_to_tonic,
    read_events_npy,
    read_events_tonic,
    read_image,
    write_events_npy,
    write_events_tonic,
    write_image,
)


def _events(n=50):
    rng = np.random.default_rng(0)
    return carla_events(rng.integers(0, 32, n), rng.integers(0, 24, n), np.sort(rng.integers(10**9, 10**9 + 10**8, n)),
                        rng.random(n) < 0.5)


def test_carla_dtype_round_trip(tmp_path):
    ev = _events()
    assert ev.dtype == DVS_EVENT_DTYPE and ev.dtype.itemsize == 13
    write_events_npy(tmp_path / "e.npy", ev)
    back = read_events_npy(tmp_path / "e.npy")
    assert back.dtype == DVS_EVENT_DTYPE
    np.testing.assert_array_equal(back, ev)


def test_tonic_round_trip_states_microseconds(tmp_path):
    ev = _events()
    write_events_tonic(tmp_path / "e.npz", ev, width=32, height=24)
    ton, unit, size = read_events_tonic(tmp_path / "e.npz")
    assert unit == "us" and size == (32, 24, 2)
    assert ton.dtype == TONIC_EVENT_DTYPE and ton.dtype.names == ("x", "y", "t", "p")
    np.testing.assert_array_equal(ton["t"], ev["t"] // 1000)
    np.testing.assert_array_equal(ton["p"], ev["pol"].astype(np.int64))
    np.testing.assert_array_equal(ton["x"], ev["x"])
    np.testing.assert_array_equal(carla_to_tonic(ev), ton)


def test_tonic_file_is_the_npz_of_the_converted_events_chunk_by_chunk(tmp_path, monkeypatch):
    import jaxfish.io._events as events_module
    from jaxfish.io import write_npz

    ev = _events(1000)
    monkeypatch.setattr(events_module, "TONIC_CHUNK_EVENTS", 64)  # several chunks, the last one short
    a = write_events_tonic(tmp_path / "a.npz", ev, width=32, height=24).read_bytes()
    b = write_npz(tmp_path / "b.npz", events=carla_to_tonic(ev), time_unit=np.asarray("us"),
                  sensor_size=np.asarray([32, 24, 2], np.int64)).read_bytes()
    assert a == b
    empty = write_events_tonic(tmp_path / "e.npz", ev[:0], width=32, height=24)
    assert read_events_tonic(empty)[0].shape == (0,)


def test_tonic_records_are_narrow_and_take_tonic_arithmetic():
    ev = _events()
    ton = carla_to_tonic(ev)
    assert TONIC_EVENT_DTYPE.itemsize == 13 and [ton.dtype[k].kind for k in "xytp"] == ["i"] * 4
    assert ton.dtype["x"].itemsize == ton.dtype["y"].itemsize == 2 and ton.dtype["p"].itemsize == 1
    flipped = ton["p"] * np.int8(-1)  # tonic's polarity flip needs a signed polarity
    assert set(flipped.tolist()) <= {0, -1} and (flipped == -1).sum() == ev["pol"].sum()


def test_tonic_refuses_coordinates_int16_cannot_hold(tmp_path):
    big = carla_events([0, 40000], [0, 1], [5, 6], [True, False])
    with pytest.raises(ImageError, match="big.npz.*'x'.*0..32767"):
        write_events_tonic(tmp_path / "big.npz", big, width=32768, height=2)
    with pytest.raises(ImageError, match="wide.npz.*'sensor_size'"):
        write_events_tonic(tmp_path / "wide.npz", big[:1], width=40000, height=2)
    with pytest.raises(ImageError, match="carla_to_tonic.*'x'"):
        carla_to_tonic(big)
    assert not list(tmp_path.iterdir())
    edge = carla_events([32767], [32767], [5], [True])
    write_events_tonic(tmp_path / "edge.npz", edge, width=32768, height=32768)
    assert read_events_tonic(tmp_path / "edge.npz")[0][["x", "y"]].tolist() == [(32767, 32767)]


def test_tonic_conversion_of_other_field_types():
    ev = np.zeros(3, [("t", "<f8"), ("x", "<i4"), ("y", "<u2"), ("pol", "<i1")])  # CARLA's fields, other types
    ev["t"], ev["x"], ev["y"], ev["pol"] = [1999.9, 2000.0, 123456.7], [1, 2, 3], [4, 5, 6], [1, 0, 1]
    ton = carla_to_tonic(ev)
    ev["x"][0] = -1
    with pytest.raises(ImageError, match="'x'"):
        carla_to_tonic(ev)
    assert ton.dtype == TONIC_EVENT_DTYPE
    assert ton["t"].tolist() == [1, 2, 123] and ton["p"].tolist() == [1, 0, 1] and ton["x"].tolist() == [1, 2, 3]


def test_wrong_dtype_and_missing_files(tmp_path):
    np.save(tmp_path / "bad.npy", np.zeros(3))
    with pytest.raises(ImageError, match="bad.npy"):
        read_events_npy(tmp_path / "bad.npy")
    with pytest.raises(ImageError, match="missing"):
        read_events_tonic(tmp_path / "none.npz")
    (tmp_path / "corrupt.npy").write_bytes(b"garbage")
    with pytest.raises(ImageError, match="corrupt.npy.*not a readable"):
        read_events_npy(tmp_path / "corrupt.npy")
    for plain in (np.zeros((3, 2)), np.array([[1.7, -3.0, 2e30]]), np.zeros(3)):  # a cast would invent events
        with pytest.raises(ImageError, match="out.npy.*DVS fields"):
            write_events_npy(tmp_path / "out.npy", plain)
        with pytest.raises(ImageError, match="DVS fields"):
            carla_to_tonic(plain)
    assert not (tmp_path / "out.npy").exists()


def test_colour_rendering(tmp_path):
    ev = carla_events([1, 2], [0, 3], [5, 6], [True, False])
    from jaxfish.pipeline import events_color

    write_image(tmp_path / "c.png", events_color(ev, width=4, height=5))
    img = read_image(tmp_path / "c.png")
    assert img[0, 1].tolist() == [0, 0, 255] and img[3, 2].tolist() == [255, 0, 0] and img[1, 1].tolist() == [255] * 3
