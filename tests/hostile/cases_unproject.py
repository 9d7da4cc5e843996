"""Hostile inputs of the WoodScape unprojection (issue #18 part 4, helper unproject): pixels and
lenses that must give invalid, finite rays (never NaN, never a silent ray), through the library."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .corpus import FV_CALIBRATION, Case


def _unproject(k, uv, **kw):
    def call(_tmp: Path):
        import jax.numpy as jnp

        import jaxfish as jf

        cam = jf.load_calibration(FV_CALIBRATION).camera if k is None else jf.WoodScapeFisheye(
            np.asarray(k, float), width=kw.get("width", 1280), height=kw.get("height", 966))
        if isinstance(uv, str):
            pixels = cam.pixel_grid(jnp.float32 if uv == "grid32" else None)
        else:
            pixels = jnp.asarray(uv)
        rays, valid = cam.unproject(pixels)
        return np.asarray(rays), np.asarray(valid)
    return call


def _all_invalid_and_finite(out) -> bool:
    rays, valid = out
    return not valid.any() and bool(np.isfinite(rays).all())


def _stationary_lens_ok(out) -> bool:
    rays, valid = out
    unit = np.abs(np.linalg.norm(rays[valid], axis=-1) - 1) < 1e-12
    return 0 < valid.mean() < 1 and bool(np.isfinite(rays).all()) and bool(unit.all())


CASES = [
    Case("unproject-nonfinite-and-huge-pixels", call=_unproject(None, [[np.nan, 3.0], [np.inf, 5.0], [1e30, -1e30],
                                                                        [-np.inf, np.nan]]),
         raises=None, check=_all_invalid_and_finite),
    Case("unproject-lens-k1-subnormal", call=_unproject([1e-310, 0.0, 0.0, 0.0], "grid", width=64, height=48),
         raises=None, check=_all_invalid_and_finite),
    Case("unproject-lens-k1-negative", call=_unproject([-300.0, 10.0, 0.0, 0.0], "grid", width=64, height=48),
         raises=None, check=_all_invalid_and_finite),
    Case("unproject-lens-k1-zero-float32", call=_unproject([0.0, 0.0, 0.0, 0.0], "grid32", width=64, height=48),
         raises=None, check=_all_invalid_and_finite),
    Case("unproject-lens-stationary-point-full-frame", call=_unproject([300.0, -60.0, -10.0, 0.0], "grid"),
         raises=None, check=_stationary_lens_ok),
    Case("unproject-empty-batch", call=_unproject(None, np.zeros((0, 2))), raises=None,
         check=lambda out: out[0].shape == (0, 3) and out[1].shape == (0,)),
]
