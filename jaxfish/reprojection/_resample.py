"""Resampling kernels applying a `Lut` to images, labels and depth (pure JAX, jit/vmap-safe).

Source arrays always carry the face axis: ``(*batch, F, Hs, Ws, C)`` for images and labels (``C``
may be omitted for labels) and ``(*batch, F, Hs, Ws)`` for depth; a single source camera has
``F = 1`` (``image[None]``). Leading ``*batch`` axes (frames) are kept; map over cameras with
`jax.vmap` over a LUT batch built by `jax.vmap(build_lut)` or `stack_luts`. Every kernel returns
``(values (*batch, H, W[, C]), valid (H, W))``; invalid pixels (outside the lens domain or not seen
by the source) hold ``fill`` (0 by default).

Rules (also in ``docs/reprojection.md``):

- **bilinear** (images): taps never blend across face borders. A cube rig's faces are padded with a
  one-pixel ring read from their neighbouring faces (`pad_faces`), so interpolation is continuous
  across seams; a single-camera source is clamped at its border (``cv2.BORDER_REPLICATE``).
  With supersampling: the mean of the valid samples. Integer images are rounded and clipped back
  to their dtype.
- **nearest** (labels, instance ids): the exact source value, never averaged. With supersampling:
  the majority among the valid samples, ties going to the sample nearest the pixel centre
  (``reduce="majority"``), or the centre sample (``reduce="centre"``).
- **depth**: each face's planar z-depth becomes the Euclidean range along the target ray
  (``range = z * |ray| / ray_z``, which is also the range along the fisheye ray since the centres
  coincide). Within one face, inverse depth ``1 / z`` is interpolated bilinearly -- exact for
  planar surfaces -- only when the four taps agree (``max / min <= 1 + rel_tol``); otherwise the
  nearest tap is used, so depth never blends across discontinuities (no flying points). Near a face
  border the taps stay inside the face and ``1 / z`` is extrapolated linearly for the last half
  pixel (exact for planes; the taps agree there). A tap at or beyond ``far_m`` (CARLA's 1000 m
  sky) forbids interpolation, and a far sample stays exactly ``far_m``. Supersampled LUTs use the
  sample nearest the pixel centre (exactly the centre for odd ``n``): depth is never averaged.
"""

from __future__ import annotations

from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Shaped

from .._constants import FAR_DEPTH_M
from ._lut import Lut, border_pixels, centre_sample, ring_positions, split_padded_index

DEPTH_AGREEMENT_REL_TOL = 0.05
"""Default ``rel_tol`` of `resample_depth`: inverse depth is interpolated only when the four taps
satisfy ``max / min <= 1 + rel_tol``; otherwise the nearest tap is used."""
_UNROLL_FRAMES = 8
"""Frame batches up to this size are unrolled (one kernel per frame in one program); larger ones loop."""


def _split_source(x: Array, lut: Lut, what: str, *, channels: bool | None) -> tuple[tuple[int, ...], bool]:
    """Batch shape of a source array and whether it has a trailing channel axis."""
    src = lut.source_shape
    if channels is not False and x.ndim >= 4 and tuple(x.shape[-4:-1]) == src:
        return tuple(x.shape[:-4]), True
    if channels is not True and x.ndim >= 3 and tuple(x.shape[-3:]) == src:
        return tuple(x.shape[:-3]), False
    want = f"(..., {src[0]}, {src[1]}, {src[2]}{', C' if channels else ''})"
    raise ValueError(f"{what}: source array of shape {x.shape} does not match the LUT's faces; expected {want}")


def _work_dtype(x: Array, lut: Lut):
    if jnp.issubdtype(x.dtype, jnp.floating) and x.dtype.itemsize >= 4:
        return x.dtype
    return lut.uv.dtype


def _to_output(values: Array, dtype) -> Array:
    if jnp.issubdtype(dtype, jnp.integer):
        info = jnp.iinfo(dtype)
        return jnp.clip(jnp.round(values), info.min, info.max).astype(dtype)
    if dtype == jnp.bool_:
        return values >= 0.5
    return values.astype(dtype)


def _over_frames(fn, frames: Array):
    """``fn`` applied to each frame of ``(B, ...)``, one frame at a time (on CPU, XLA lowers a
    batched gather, and gathers inside a loop, more slowly than one unbatched gather per frame)."""
    b = frames.shape[0]
    if b <= _UNROLL_FRAMES:
        return jnp.stack([fn(frames[i]) for i in range(b)])
    return jax.lax.map(fn, frames)


def _ring_own_edge(size: int) -> np.ndarray:
    """Flat index (within one unpadded face) of the face pixel nearest each ring pixel."""
    xy = ring_positions(size) - 1
    x = np.clip(xy[:, 0], 0, size - 1)
    y = np.clip(xy[:, 1], 0, size - 1)
    return (y * size + x).astype(np.int32)


def _ring_values(flat: Array, lut: Lut, dtype) -> Array:
    """Values ``(F * R, C)`` of the one-pixel ring around every face of one frame ``flat``
    ``(F * S * S, C)`` (unpadded faces), in `ring_positions` order, in ``dtype``."""
    f, s = lut.num_faces, lut.source_width
    wdt = _work_dtype(flat, lut)
    idx = lut.ring_index  # (F, R), into the unpadded faces
    fx = lut.ring_frac[..., 0:1].astype(wdt)
    fy = lut.ring_frac[..., 1:2].astype(wdt)
    g = lambda i: flat.at[i].get(mode="promise_in_bounds").astype(wdt)  # noqa: E731
    t00, t01, t10, t11 = g(idx), g(idx + 1), g(idx + s), g(idx + s + 1)
    top = t00 + (t01 - t00) * fx
    bot = t10 + (t11 - t10) * fx
    val = top + (bot - top) * fy
    own = jnp.asarray(_ring_own_edge(s)) + (jnp.arange(f, dtype=jnp.int32) * (s * s))[:, None]
    own_val = flat.at[own].get(mode="promise_in_bounds")
    out = jnp.where(lut.ring_valid[..., None], _to_output(val, flat.dtype), own_val).astype(dtype)
    return out.reshape((-1, flat.shape[-1]))


def pad_faces(
    faces: Shaped[Array, "*batch F S S C"], lut: Lut
) -> Shaped[Array, "*batch F S+2 S+2 C"]:
    """Cube faces padded with a one-pixel border ring read from their neighbouring faces.

    Each ring pixel's ray is projected into the neighbouring face (dominant-axis rule) and read
    there bilinearly (clamped within that face). Ring pixels no face sees (towards the missing
    back face of a five-face rig, never inside a fisheye's image) replicate the face's own edge.
    """
    if lut.pad != 1:
        raise ValueError("pad_faces: the LUT's source is not a cube rig (pad = 0)")
    x = jnp.asarray(faces)
    batch, _ = _split_source(x, lut, "pad_faces", channels=True)
    f, s, c = lut.num_faces, lut.source_width, x.shape[-1]
    if x.size == 0:  # no channels or no frames: nothing to read (a reshape to -1 could not infer the batch)
        return jnp.zeros(batch + (f, s + 2, s + 2, c), x.dtype)
    xb = x.reshape((-1, f, s, s, c))
    flat = xb.reshape((xb.shape[0], f * s * s, c))
    ring_vals = jax.vmap(lambda fl: _ring_values(fl, lut, x.dtype))(flat)  # (B, F * R, C)
    pos = ring_positions(s)
    r = pos.shape[0]
    fi = jnp.asarray(np.repeat(np.arange(f), r))
    yi = jnp.asarray(np.tile(pos[:, 1], f))
    xi = jnp.asarray(np.tile(pos[:, 0], f))
    padded = jnp.pad(xb, ((0, 0), (0, 0), (1, 1), (1, 1), (0, 0)))
    padded = padded.at[:, fi, yi, xi].set(ring_vals.reshape((xb.shape[0], f * r, c)), mode="promise_in_bounds")
    return padded.reshape(batch + (f, s + 2, s + 2, c))


def resample_bilinear(
    images: Shaped[Array, "*batch F Hs Ws C"], lut: Lut, *, fill: float = 0
) -> tuple[Shaped[Array, "*batch H W C"], Bool[Array, "H W"]]:
    """Bilinear resampling of images through ``lut`` (see the module rules); dtype preserved.

    For a cube rig the result equals reading `pad_faces` output, without the padded copy: taps
    inside a face read the faces directly, and the few pixels whose footprint reaches a face's
    border ring (counted per call; a static capacity, `pad_faces` beyond it) are recomputed from
    the ring values and written back."""
    x = jnp.asarray(images)
    batch, _ = _split_source(x, lut, "resample_bilinear", channels=True)
    f, c = lut.num_faces, x.shape[-1]
    if x.size == 0:  # no channels or no frames: an empty result of the right shape
        valid_px = jnp.any(lut.valid, axis=-1)
        return jnp.zeros(batch + valid_px.shape + (c,), x.dtype), valid_px
    sw = lut.source_width + 2 * lut.pad
    sh = lut.source_height + 2 * lut.pad
    frames = x.reshape((-1,) + lut.source_shape + (c,))
    wdt = _work_dtype(x, lut)
    idx = lut.tap_index
    frac = lut.tap_frac.astype(wdt)
    n = lut.valid.shape[-1]
    valid_px = jnp.any(lut.valid, axis=-1)
    w = None
    if n > 1:
        w = lut.valid.astype(wdt)
        w = w / jnp.maximum(jnp.sum(w, axis=-1, keepdims=True), 1)

    def blend(taps, fr, wt):  # taps (..., N, C), fractions (..., N, 2), weights (..., N) -> (..., C)
        t00, t01, t10, t11 = taps
        fx, fy = fr[..., 0:1], fr[..., 1:2]
        top = t00 + (t01 - t00) * fx
        bot = t10 + (t11 - t10) * fx
        val = top + (bot - top) * fy
        return val[..., 0, :] if n == 1 else jnp.einsum("...nc,...n->...c", val, wt)

    def finish(val):
        val = jnp.where(valid_px[..., None], val, jnp.asarray(fill, wdt))
        return _to_output(val, x.dtype)

    def padded(frame):
        fl = pad_faces(frame, lut).reshape((f * sh * sw, c))
        g = lambda i: fl.at[i].get(mode="promise_in_bounds").astype(wdt)  # noqa: E731
        return finish(blend((g(idx), g(idx + 1), g(idx + sw), g(idx + sw + 1)), frac, w))

    if not lut.pad:

        def plain(frame):
            fl = frame.reshape((f * sh * sw, c))
            g = lambda i: fl.at[i].get(mode="promise_in_bounds").astype(wdt)  # noqa: E731
            return finish(blend((g(idx), g(idx + 1), g(idx + sw), g(idx + sw + 1)), frac, w))

        out = _over_frames(plain, frames)
        return out.reshape(batch + out.shape[1:]), valid_px

    # Cube rig: the top-left tap in unpadded coordinates, clamped so all four taps stay in the face.
    s = lut.source_width
    face, xp, yp = split_padded_index(idx, s)
    fi = (face * s + jnp.clip(yp - 1, 0, s - 2)) * s + jnp.clip(xp - 1, 0, s - 2)
    if lut.border_pixel is None:
        border = border_pixels(idx, lut.valid, width=s, num_faces=f)
        pix, fits = border["border_pixel"], border["border_fits"]
    else:
        pix, fits = lut.border_pixel, lut.border_fits
    hw = valid_px.size
    pix_safe = jnp.minimum(pix, hw - 1)
    b_idx = idx.reshape((hw, n))[pix_safe]
    b_frac = frac.reshape((hw, n, 2))[pix_safe]
    b_w = None if w is None else w.reshape((hw, n))[pix_safe]
    bf, bx, by = split_padded_index(b_idx, s)
    r = 4 * (s + 1)
    b_taps = []
    for dy, dx in ((0, 0), (0, 1), (1, 0), (1, 1)):
        tx, ty = bx + dx, by + dy  # padded coordinates of this tap
        t_in = (tx >= 1) & (tx <= s) & (ty >= 1) & (ty <= s)
        t_face = (bf * s + jnp.clip(ty - 1, 0, s - 1)) * s + jnp.clip(tx - 1, 0, s - 1)
        # ring order (`ring_positions`): top (y = 0), right (x = S + 1), bottom (y = S + 1), left (x = 0)
        ring = jnp.where(ty == 0, tx, jnp.where(tx == s + 1, (s + 1) + ty,
                                                jnp.where(ty == s + 1, 2 * (s + 1) + (s + 1 - tx), 3 * (s + 1) + (s + 1 - ty))))
        b_taps.append((t_in, t_face, bf * r + jnp.clip(ring, 0, r - 1)))

    def fast(frame):
        fl = frame.reshape((-1, c))
        g = lambda i: fl.at[i].get(mode="promise_in_bounds").astype(wdt)  # noqa: E731
        out = finish(blend((g(fi), g(fi + 1), g(fi + s), g(fi + s + 1)), frac, w))
        ring_vals = _ring_values(fl, lut, x.dtype)
        taps = tuple(jnp.where(t_in[..., None], g(t_face), ring_vals.at[t_ring].get(mode="promise_in_bounds").astype(wdt))
                     for t_in, t_face, t_ring in b_taps)
        val = blend(taps, b_frac, b_w)  # (K, C)
        val = _to_output(jnp.where(valid_px.reshape(-1)[pix_safe][:, None], val, jnp.asarray(fill, wdt)), x.dtype)
        flat_out = out.reshape((hw, c)).at[pix].set(val, mode="drop")
        return flat_out.reshape(out.shape)

    def one(frame):
        return jax.lax.cond(fits, fast, padded, frame)

    out = _over_frames(one, frames)
    return out.reshape(batch + out.shape[1:]), valid_px


def _majority(values: Array, valid: Array, n_side: int) -> Array:
    """Per pixel, the most frequent value among valid samples ``(..., N)``; ties go to the sample
    nearest the pixel centre."""
    n = values.shape[-1]
    order = np.argsort(np.sum(_offsets_sq(n_side), axis=-1), kind="stable")
    rank = np.empty(n, np.int64)
    rank[order] = np.arange(n)
    eq = (values[..., :, None] == values[..., None, :]) & valid[..., None, :]
    counts = jnp.sum(eq, axis=-1, dtype=jnp.int32)
    score = jnp.where(valid, counts * n + jnp.asarray(n - 1 - rank, jnp.int32), -1)
    k = jnp.argmax(score, axis=-1)
    return jnp.take_along_axis(values, k[..., None], axis=-1)[..., 0]


def _offsets_sq(n_side: int) -> np.ndarray:
    from ._lut import supersample_offsets

    return supersample_offsets(n_side) ** 2


def resample_nearest(
    labels: Shaped[Array, "*batch F Hs Ws *C"],
    lut: Lut,
    *,
    fill: int | float = 0,
    reduce: Literal["majority", "centre"] = "majority",
) -> tuple[Shaped[Array, "*batch H W *C"], Bool[Array, "H W"]]:
    """Nearest-neighbour resampling (labels, instance ids, any dtype): values are copied exactly.

    Accepts ``(*batch, F, Hs, Ws)`` or ``(*batch, F, Hs, Ws, C)``. With a supersampled LUT,
    ``reduce="majority"`` takes the most frequent valid sample (per channel for multi-channel
    arrays), ``"centre"`` the sample nearest the pixel centre.
    """
    if reduce not in ("majority", "centre"):
        raise ValueError(f"resample_nearest: reduce must be 'majority' or 'centre', got {reduce!r}")
    x = jnp.asarray(labels)
    batch, has_c = _split_source(x, lut, "resample_nearest", channels=None)
    if not has_c:
        x = x[..., None]
    f, c = lut.num_faces, x.shape[-1]
    n = lut.valid.shape[-1]
    valid_px = jnp.any(lut.valid, axis=-1)
    if x.size == 0:  # no channels or no frames: an empty result of the right shape
        out = jnp.zeros(batch + valid_px.shape + (c,), x.dtype)
        return (out if has_c else out[..., 0]), (valid_px if reduce == "majority" or n == 1 else
                                                  lut.valid[..., centre_sample(lut.supersample)])
    flat = x.reshape((-1, f * lut.source_height * lut.source_width, c))
    idx = lut.nearest_index
    valid = lut.valid
    if n > 1 and reduce == "centre":
        k = centre_sample(lut.supersample)
        idx, valid = idx[..., k : k + 1], valid[..., k : k + 1]
        valid_px = valid[..., 0]
        n = 1

    def one(fl):
        val = fl.at[idx].get(mode="promise_in_bounds")  # (H, W, N, C)
        if n == 1:
            val = val[:, :, 0, :]
        else:
            val = jnp.moveaxis(val, -1, -2)  # (H, W, C, N)
            val = _majority(val, valid[:, :, None, :], lut.supersample)
        return jnp.where(valid_px[..., None], val, jnp.asarray(fill, x.dtype))

    out = _over_frames(one, flat)
    out = out.reshape(batch + out.shape[1:])
    return (out if has_c else out[..., 0]), valid_px


def resample_depth(
    depth: Float[Array, "*batch F Hs Ws"],
    lut: Lut,
    *,
    planar: bool = True,
    far_m: float = FAR_DEPTH_M,
    rel_tol: float = DEPTH_AGREEMENT_REL_TOL,
    fill: float = 0.0,
) -> tuple[Float[Array, "*batch H W"], Bool[Array, "H W"]]:
    """Depth resampling: source depth (metres) -> Euclidean range along each target ray (metres).

    ``planar=True`` (CARLA depth cameras, cube faces): the source holds planar z-depth along its
    (face's) optical axis; ``planar=False``: the source already holds range. See the module rules
    for interpolation, discontinuities, faces borders and the far value.
    """
    x = jnp.asarray(depth)
    batch, _ = _split_source(x, lut, "resample_depth", channels=False)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        raise ValueError(f"resample_depth: depth must be floating point metres, got {x.dtype}")
    f, s_h, s_w = lut.source_shape
    k = centre_sample(lut.supersample)
    if x.size == 0:  # no frames: an empty result of the right shape
        out_dtype = x.dtype if x.dtype.itemsize >= 4 else jnp.promote_types(x.dtype, jnp.float32)
        return jnp.zeros(batch + lut.valid.shape[:-1], out_dtype), lut.valid[..., k]
    flat = x.reshape((-1, f * s_h * s_w))
    uv = lut.uv[..., k, :]
    face = lut.face[..., k]
    valid = lut.valid[..., k]
    scale = lut.z_to_range[..., k] if planar else jnp.ones_like(lut.z_to_range[..., k])
    wdt = jnp.promote_types(x.dtype, jnp.float32)
    uv = uv.astype(wdt)
    x0 = jnp.clip(jnp.floor(uv[..., 0]), 0, s_w - 2).astype(jnp.int32)
    y0 = jnp.clip(jnp.floor(uv[..., 1]), 0, s_h - 2).astype(jnp.int32)
    fx = uv[..., 0] - x0.astype(wdt)  # in [-0.5, 1.5]: linear extrapolation at face borders
    fy = uv[..., 1] - y0.astype(wdt)
    i00 = (face * s_h + y0) * s_w + x0
    i00 = jnp.where(valid, i00, 0)
    far = jnp.asarray(far_m, wdt)
    one_plus = jnp.asarray(1.0 + rel_tol, wdt)
    scale = scale.astype(wdt)

    def one(fl):
        g = lambda i: fl.at[i].get(mode="promise_in_bounds").astype(wdt)  # noqa: E731
        t00, t01, t10, t11 = g(i00), g(i00 + 1), g(i00 + s_w), g(i00 + s_w + 1)
        lo = jnp.minimum(jnp.minimum(t00, t01), jnp.minimum(t10, t11))
        hi = jnp.maximum(jnp.maximum(t00, t01), jnp.maximum(t10, t11))
        smooth = (lo > 0) & (hi < far) & (hi <= lo * one_plus)
        safe = lambda t: 1.0 / jnp.where(smooth, t, 1.0)  # noqa: E731
        i_top = safe(t00) + (safe(t01) - safe(t00)) * fx
        i_bot = safe(t10) + (safe(t11) - safe(t10)) * fx
        inv = i_top + (i_bot - i_top) * fy
        inv_ok = smooth & (inv > 0)
        z_interp = 1.0 / jnp.where(inv_ok, inv, 1.0)
        # nearest of the four taps (fractions reach [-0.5, 1.5] near face borders)
        z_near = jnp.where(fy >= 0.5, jnp.where(fx >= 0.5, t11, t10), jnp.where(fx >= 0.5, t01, t00))
        z = jnp.where(inv_ok, z_interp, z_near)
        rng = jnp.where(z >= far, far, z * scale)
        return jnp.where(valid, rng, jnp.asarray(fill, wdt)).astype(x.dtype if x.dtype.itemsize >= 4 else wdt)

    out = _over_frames(one, flat)
    return out.reshape(batch + out.shape[1:]), valid
