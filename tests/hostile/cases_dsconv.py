"""Hostile inputs of ``jaxfish convert``'s fit domain and error gate, and of the double sphere's
domain edges (library calls)."""

from __future__ import annotations

from .corpus import Case, edit_json


def _folded_double_sphere(tmp):
    """A double sphere lens that folds at 60.97 degrees inside a wide image: a point at 62 degrees
    must be invalid, the pixel of one at 60.9 valid and finite."""
    import math

    import jax.numpy as jnp

    import jaxfish as jf

    cam = jf.DoubleSphere(300.0, 300.0, 640.0, 480.0, -0.9, 0.7, width=1280, height=960, dtype=jnp.float64)
    t = jnp.radians(jnp.asarray([60.9, 62.0]))
    uv, valid = cam.project(jnp.stack([jnp.sin(t), 0 * t, jnp.cos(t)], -1))
    return math.degrees(float(cam.theta_max())), valid.tolist(), bool(jnp.all(jnp.isfinite(uv)))


def _ds_model(obj):
    obj["intrinsic"] = {"model": "double_sphere", "width": 1280, "height": 966, "fx": 300.0, "fy": 300.0,
                        "cx": 640.0, "cy": 483.0, "xi": -0.9, "alpha": 0.7}


CASES = [
    # The default domain (the image's valid pixels) cannot hold the unified model to 2 px: nothing written.
    Case("dsconv-ucm-over-2px", "convert {calib} --to ucm -o {tmp}/ucm.json -r {tmp}/rep.json",
         says=("FV.json", "maximum error", "exceeds --max-error 2 px", "deg", "px from the principal point",
               "not written"), absent=("{tmp}/ucm.json", "{tmp}/rep.json")),
    # The whole lens (190 degrees) for a model whose domain ends before: rays outside it, refused.
    Case("dsconv-eucm-whole-lens", "convert {calib} --to eucm --fov lens -o {tmp}/e.json",
         says=("FV.json", "the source's whole lens", "not written"), absent=("{tmp}/e.json",)),
    Case("dsconv-max-error-nan", "convert {calib} --to ds --max-error nan -o {tmp}/d.json",
         says=("--max-error must be a positive finite number",), absent=("{tmp}/d.json",)),
    Case("dsconv-max-error-negative", "convert {calib} --to ds --max-error -1 -o {tmp}/d.json",
         says=("--max-error must be",), absent=("{tmp}/d.json",)),
    Case("dsconv-fov-unknown", "convert {calib} --to ds --fov sensor -o {tmp}/d.json",
         says=("--fov must be 'image' or 'lens'",), absent=("{tmp}/d.json",)),
    # A double sphere source that folds at 60.97 deg inside its image: the fitted domain is its valid
    # pixels (up to the fold); Kannala-Brandt follows the fold with a stationary point and leaves rays
    # outside its own domain: refused, naming them.
    Case("dsconv-folded-source-to-kb", "convert {calib} --to kb -o {tmp}/kb.json",
         setup=lambda tmp: edit_json(tmp / "FV.json", _ds_model),
         says=("FV.json", "image's valid pixels", "outside the kannala_brandt model's domain", "not written"),
         absent=("{tmp}/kb.json",)),
    Case("dsconv-folded-domain", call=_folded_double_sphere, raises=None,
         check=lambda r: abs(r[0] - 60.9714) < 1e-3 and r[1] == [True, False] and r[2]),
]
