"""No NaN or infinity reaches a file: non-finite or absurd numbers in every input are refused
where they are read (naming the file and field), and every JSON writer refuses them."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .corpus import Case, edit_json


def _set(rel: str, *keys: str | int, value: object):
    """A setup that sets ``obj[k1][k2]... = value`` in the capture's JSON file ``rel``."""
    def setup(tmp: Path) -> None:
        def edit(obj):
            target = obj
            for k in keys[:-1]:
                target = target[k]
            target[keys[-1]] = value
        edit_json(tmp / "capture" / rel, edit)
    return setup


def _calib(key: str, value: float, rel: str = "FV.json"):
    """A setup that sets ``intrinsic.key`` of ``{tmp}/rel`` (the FV calibration copy)."""
    def setup(tmp: Path) -> None:
        edit_json(tmp / rel, lambda d: d["intrinsic"].__setitem__(key, value))
    return setup


def _capture_calib(key: str, value: float, **more: float):
    def setup(tmp: Path) -> None:
        edit_json(tmp / "capture" / "calibration" / "FV.json", lambda d: d["intrinsic"].update({key: value, **more}))
    return setup


def _kb_calib(key: str, value: float):
    """A Kannala-Brandt calibration at ``{tmp}/kb.json`` with ``intrinsic.key = value``."""
    def setup(tmp: Path) -> None:
        intr = {"model": "kannala_brandt", "fx": 330.0, "fy": 330.0, "cx": 640.0, "cy": 480.0, "k1": 0.01,
                "k2": 0.0, "k3": 0.0, "k4": 0.0, "width": 1280, "height": 966, key: value}
        doc = {"name": "FV", "intrinsic": intr,
               "extrinsic": {"quaternion": [0.0, 0.0, 0.0, 1.0], "translation": [0.0, 0.0, 0.0]}}
        (tmp / "kb.json").write_text(json.dumps(doc))
    return setup


def _height(value: float):
    """A setup that puts ``value`` into one pixel of frame 0's BEV height EXR."""
    def setup(tmp: Path) -> None:
        from jaxfish.io import read_image, write_image

        path = tmp / "capture" / "frames" / "000000" / "bev" / "height_curr.exr"
        h = np.array(read_image(path), np.float32)
        h[3, 5] = value
        write_image(path, h)
    return setup


def _lidar_nan(tmp: Path) -> None:
    path = tmp / "capture" / "frames" / "000000" / "lidar.npy"
    a = np.load(path)
    a[7, 2] = np.nan
    np.save(path, a)


def _duplicates(tmp: Path) -> None:
    """20 copies of one correspondence (camera frame: no pose to fit)."""
    views = [{"points": [[0.1, 0.2, 1.0]] * 20, "pixels": [[700.0, 500.0]] * 20}]
    (tmp / "dup.json").write_text(json.dumps({"frame": "camera", "views": views}))


def _collinear(tmp: Path) -> None:
    """20 distinct correspondences, all on the optical axis: they cannot fix the distortion."""
    views = [{"points": [[0.0, 0.0, 1.0 + i] for i in range(20)], "pixels": [[639.5, 482.5]] * 20}]
    (tmp / "axis.json").write_text(json.dumps({"frame": "camera", "views": views}))


def _corr(points: list, pixels: list):
    def setup(tmp: Path) -> None:
        (tmp / "c.json").write_text(json.dumps({"frame": "camera", "views": [{"points": points, "pixels": pixels}]}))
    return setup


_PTS = [[0.1 * i, 0.2, 1.0] for i in range(20)]
_PIX = [[700.0 + i, 500.0] for i in range(20)]


def _write_json_nan(tmp: Path):
    from jaxfish.io._json import write_json

    return write_json(tmp / "out.json", {"a": [1.0, {"b": float("nan")}]})


def _save_calibration_inf(tmp: Path):
    import equinox as eqx
    import jax.numpy as jnp

    import jaxfish as jf

    calib = jf.load_calibration(tmp / "FV.json")
    bad = eqx.tree_at(lambda c: c.camera.cx_offset, calib, jnp.asarray(jnp.inf, calib.camera.cx_offset.dtype))
    return jf.save_calibration(bad, tmp / "out.json")


BUILD = "build {capture} {tmp}/out --frames 0"
ACTORS = "frames/000000/actors.json"
CASES = [
    # the inputs of issue #21 item 5
    Case("finite-capture-dt-nan", BUILD, setup=_set("capture.json", "dt_s", value=float("nan")),
         says=("capture.json", "'dt_s'"), absent=("{tmp}/out",)),
    Case("finite-actor-extent-huge", BUILD, setup=_set(ACTORS, "actors", 1, "bounding_box", "extent", 0, value=1e300),
         exit=1, says=("actors.json", "actors[1]", "bounding_box.extent"), absent=("{tmp}/out/distances_traveled",
                                                                                  "{tmp}/out/box_3d_annotations")),
    Case("finite-bev-height-nan", BUILD, setup=_height(float("nan")), exit=1,
         says=("height_curr.exr", "not finite", "(u=5, v=3)"), absent=("{tmp}/out/bev_height",)),
    Case("finite-convert-aspect-tiny", "convert {calib} --to kb --out {tmp}/kb.json --report {tmp}/r.json",
         setup=_calib("aspect_ratio", 1e-300), says=("FV.json", "intrinsic.aspect_ratio"),
         absent=("{tmp}/kb.json", "{tmp}/r.json")),
    Case("finite-convert-k1-huge", "convert {calib} --to kb --out {tmp}/kb.json --report {tmp}/r.json",
         setup=_calib("k1", 1e308), says=("FV.json", "intrinsic.k1"), absent=("{tmp}/kb.json", "{tmp}/r.json")),
    Case("finite-capture-calibration-k1-huge", BUILD, setup=_capture_calib("k1", 1e300),
         says=("calibration/FV.json", "intrinsic.k1"), absent=("{tmp}/out/dataset.json",)),
    Case("finite-refit-duplicates", "refit {tmp}/dup.json -c {calib} -o {tmp}/fit.json -r {tmp}/r.json",
         setup=_duplicates, exit=1, says=("dup.json", "degenerate", "1 distinct", "not estimable"),
         absent=("{tmp}/fit.json", "{tmp}/r.json")),
    # more fields with NaN, 1e308, -inf
    Case("finite-capture-calibration-blind", BUILD, setup=_capture_calib("k1", 1e-3, k2=-1e7), exit=1,
         says=("calibration/FV.json", "every pixel invalid"), absent=("{tmp}/out/rgb_images",)),
    Case("finite-capture-dt-negative", BUILD, setup=_set("capture.json", "dt_s", value=-0.1),
         says=("capture.json", "'dt_s'"), absent=("{tmp}/out",)),
    Case("finite-capture-dt-inf", BUILD, setup=_set("capture.json", "dt_s", value=float("inf")),
         says=("capture.json", "'dt_s'"), absent=("{tmp}/out",)),
    Case("finite-actor-location-huge", BUILD, setup=_set(ACTORS, "actors", 2, "transform", "location", 1, value=1e308),
         exit=1, says=("actors.json", "actors[2]", "transform.location"), absent=("{tmp}/out/distances_traveled",)),
    Case("finite-actor-box-location-neg-inf", BUILD,
         setup=_set(ACTORS, "actors", 1, "bounding_box", "location", 2, value=float("-inf")),
         exit=1, says=("actors.json", "actors[1]", "bounding_box.location"), absent=("{tmp}/out/box_3d_annotations",)),
    Case("finite-actor-rotation-huge", BUILD, setup=_set(ACTORS, "actors", 1, "transform_prev", "rotation", 1, value=1e300),
         exit=1, says=("actors.json", "actors[1]", "transform_prev.rotation"), absent=("{tmp}/out/distances_traveled",)),
    Case("finite-ego-location-huge", BUILD, setup=_set("frames/000000/ego.json", "transform", "location", 0, value=1e300),
         exit=1, says=("ego.json", "transform.location"), absent=("{tmp}/out/vehicle_data",)),
    Case("finite-ego-velocity-nan", BUILD, setup=_set("frames/000000/ego.json", "velocity", 0, value=float("nan")),
         exit=1, says=("ego.json", "velocity"), absent=("{tmp}/out/vehicle_data",)),
    Case("finite-bev-height-neg-inf", BUILD, setup=_height(float("-inf")), exit=1,
         says=("height_curr.exr", "not finite"), absent=("{tmp}/out/bev_height",)),
    Case("finite-lidar-nan", BUILD, setup=_lidar_nan, exit=1, says=("lidar.npy", "not finite"),
         absent=("{tmp}/out/lidar_data",)),
    Case("finite-convert-k2-neg-inf", "convert {calib} --to kb --out {tmp}/kb.json", setup=_calib("k2", float("-inf")),
         says=("FV.json", "intrinsic.k2"), absent=("{tmp}/kb.json",)),
    Case("finite-convert-aspect-huge", "convert {calib} --to kb --out {tmp}/kb.json", setup=_calib("aspect_ratio", 1e308),
         says=("FV.json", "intrinsic.aspect_ratio"), absent=("{tmp}/kb.json",)),
    Case("finite-convert-k1-tiny", "convert {calib} --to kb --out {tmp}/kb.json", setup=_calib("k1", 1e-300),
         says=("FV.json", "intrinsic.k1"), absent=("{tmp}/kb.json",)),
    Case("finite-convert-kb-fx-huge", "convert {tmp}/kb.json --to woodscape --out {tmp}/ws.json",
         setup=_kb_calib("fx", 1e308), says=("kb.json", "intrinsic.fx"), absent=("{tmp}/ws.json",)),
    Case("finite-convert-kb-fy-tiny", "convert {tmp}/kb.json --to woodscape --out {tmp}/ws.json",
         setup=_kb_calib("fy", 1e-300), says=("kb.json", "intrinsic.fy"), absent=("{tmp}/ws.json",)),
    Case("finite-convert-kb-k4-nan", "convert {tmp}/kb.json --to woodscape --out {tmp}/ws.json",
         setup=_kb_calib("k4", float("nan")), says=("kb.json", "intrinsic.k4"), absent=("{tmp}/ws.json",)),
    Case("finite-refit-on-axis", "refit {tmp}/axis.json -c {calib} -o {tmp}/fit.json -r {tmp}/r.json",
         setup=_collinear, exit=1, says=("axis.json", "degenerate"), absent=("{tmp}/fit.json", "{tmp}/r.json")),
    Case("finite-convert-theta-max-nan", "convert {calib} --to kb --out {tmp}/kb.json --theta-max-deg nan",
         says=("--theta-max-deg",), absent=("{tmp}/kb.json",)),
    Case("finite-convert-theta-max-neg-inf", "convert {calib} --to kb --out {tmp}/kb.json --theta-max-deg -inf",
         says=("--theta-max-deg",), absent=("{tmp}/kb.json",)),
    Case("finite-refit-loss-scale-nan", "refit {tmp}/dup.json -c {calib} -o {tmp}/fit.json --loss-scale nan",
         setup=_duplicates, says=("--loss-scale",), absent=("{tmp}/fit.json",)),
    Case("finite-refit-loss-scale-inf", "refit {tmp}/dup.json -c {calib} -o {tmp}/fit.json --loss-scale inf",
         setup=_duplicates, says=("--loss-scale",), absent=("{tmp}/fit.json",)),
    Case("finite-refit-pixel-huge", "refit {tmp}/c.json -c {calib} -o {tmp}/fit.json",
         setup=_corr(_PTS, _PIX[:19] + [[1e308, 1.0]]), says=("c.json", "views[0].pixels", "at most"),
         absent=("{tmp}/fit.json",)),
    Case("finite-refit-point-huge", "refit {tmp}/c.json -c {calib} -o {tmp}/fit.json",
         setup=_corr(_PTS[:19] + [[1e300, 0.0, 1.0]], _PIX), says=("c.json", "views[0].points", "at most"),
         absent=("{tmp}/fit.json",)),
    Case("finite-sensors-bev-cx-nan", BUILD, setup=_set("sensors.json", "bev", "cx", value=float("nan")),
         says=("sensors.json", "bev.cx"), absent=("{tmp}/out",)),
    Case("finite-sensors-bev-scale-huge", BUILD, setup=_set("sensors.json", "bev", "metres_per_pixel", value=1e308),
         says=("sensors.json", "bev.metres_per_pixel"), absent=("{tmp}/out",)),
    Case("finite-sensors-bev-scale-tiny", BUILD, setup=_set("sensors.json", "bev", "metres_per_pixel", value=1e-300),
         says=("sensors.json", "bev.metres_per_pixel"), absent=("{tmp}/out",)),
    # the writers
    Case("finite-write-json-nan", call=_write_json_nan, says=("out.json", "field 'a[1].b'", "nan"),
         absent=("{tmp}/out.json",)),
    Case("finite-save-calibration-inf", call=_save_calibration_inf, raises="CalibrationError",
         says=("out.json", "field 'intrinsic.cx_offset'"), absent=("{tmp}/out.json",)),
]
