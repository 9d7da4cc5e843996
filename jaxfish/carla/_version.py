"""CARLA releases, their semantic tag tables and weather presets, and the lazy ``carla`` import."""

from __future__ import annotations

import difflib
import re
from collections.abc import Iterable

from .._errors import JaxfishError

SUPPORTED_CARLA_VERSIONS = ("0.9.10", "0.9.11", "0.9.12", "0.9.13", "0.9.14", "0.9.15", "0.9.16")
"""CARLA releases the capture program supports (the ``carla`` client package must match the server)."""
CARLA_WEATHER_PRESETS: tuple[str, ...] = (
    "Default", "ClearNoon", "CloudyNoon", "WetNoon", "WetCloudyNoon", "MidRainyNoon", "HardRainNoon",
    "SoftRainNoon", "ClearSunset", "CloudySunset", "WetSunset", "WetCloudySunset", "MidRainSunset",
    "HardRainSunset", "SoftRainSunset",
)
"""The 15 weather presets of ``carla.WeatherParameters`` in every supported release (0.9.10+)."""
CARLA_LATER_WEATHER_PRESETS: tuple[str, ...] = (
    "ClearNight", "CloudyNight", "WetNight", "WetCloudyNight", "SoftRainNight", "MidRainyNight",
    "HardRainNight", "DustStorm",
)
"""Presets that later releases add (night presets, dust storm): accepted by name, and then only when
the connected ``carla`` client has them (`validate_weather` with ``carla=``)."""
SYNWOODSCAPE_WEATHER_PRESETS: tuple[str, ...] = (
    "ClearNoon", "ClearSunset", "CloudyNoon", "CloudySunset", "Default", "WetCloudyNoon", "WetCloudySunset",
    "WetNoon", "WetSunset",
)
"""The nine presets SynWoodScape was captured with (the paper's list, Town10HD, CARLA 0.9.10.1)."""


class CarlaCaptureError(JaxfishError):
    """A CARLA capture input is unusable: an unknown weather preset or version, a sensor buffer of
    the wrong size, a missing sensor reading. The message names the sensor, file or field."""


# ---------------------------------------------------------------------------- versions and weather
def parse_carla_version(version: str) -> tuple[int, int, int]:
    """``"0.9.14"`` (also ``"0.9.14-12-gabc"``, ``"0.9.15.2"``) -> ``(0, 9, 14)``; rejects releases
    outside 0.9.10 - 0.9.16."""
    m = re.match(r"^\s*(\d+)\.(\d+)\.(\d+)", str(version))
    if not m:
        raise CarlaCaptureError(f"CARLA version {version!r} is not of the form 0.9.N")
    v = (int(m.group(1)), int(m.group(2)), int(m.group(3)))
    if not (0, 9, 10) <= v <= (0, 9, 16):
        raise CarlaCaptureError(f"CARLA version {version!r} is not supported (0.9.10 - 0.9.16)")
    return v


def carla_semantic_tags(version: str) -> str:
    """The tag table a CARLA release's semantic camera and lidar use, as ``capture.json``'s
    ``carla_semantic_tags``: ``"0.9.10"`` for 0.9.10-0.9.13 (23 tags), ``"0.9.14"`` for 0.9.14+
    (Cityscapes order)."""
    return "0.9.10" if parse_carla_version(version) < (0, 9, 14) else "0.9.14"


def has_instance_camera(version: str) -> bool:
    """Whether a CARLA release has ``sensor.camera.instance_segmentation`` (0.9.14+)."""
    return parse_carla_version(version) >= (0, 9, 14)


def validate_weather(names: Iterable[str], *, carla=None) -> tuple[str, ...]:
    """Check weather preset names (exact, case-sensitive ``carla.WeatherParameters`` attribute
    names) and return them in order without duplicates. With the ``carla`` module, a name must also
    exist in that client (night presets and ``DustStorm`` are not in every release)."""
    out: list[str] = []
    known = CARLA_WEATHER_PRESETS + CARLA_LATER_WEATHER_PRESETS
    for name in names:
        if name not in known:
            close = difflib.get_close_matches(str(name), known, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise CarlaCaptureError(f"weather preset {name!r} is unknown{hint}; presets: {', '.join(known)}")
        if carla is not None and getattr(carla.WeatherParameters, name, None) is None:
            raise CarlaCaptureError(f"weather preset {name!r} does not exist in this carla client")
        if name not in out:
            out.append(name)
    if not out:
        raise CarlaCaptureError("no weather preset given")
    return tuple(out)


def import_carla():
    """Import and return the ``carla`` client module, with an installation hint when it is missing."""
    try:
        import carla  # noqa: PLC0415 - the edge imports CARLA only when a capture runs
    except ImportError as e:
        raise CarlaCaptureError(
            "the CARLA client package is not installed: pip install 'jaxfish[carla]' (its version must match the "
            "server's, e.g. pip install carla==0.9.15)"
        ) from e
    return carla

