"""Lookup tables (LUTs) from any target camera's pixels to any source camera's (or cube rig's) pixels.

A LUT answers, for every target pixel and every supersample inside it, "which source face and
which (fractional) source pixel does this ray hit?". It is built once per calibration (pure JAX,
jit- and vmap-able over cameras) and then applied to any number of frames by the resampling
kernels of `jaxfish.reprojection._resample`. The camera centres of source and target must
coincide (a LUT between two centres would depend on the scene depth); an optional rotation
``target_to_source`` relates their frames.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._numerics import positive_integer, resolve_dtype
from ..cameras import AbstractCamera, Pinhole
from ._cube import CubeRig

ROTATION_TOLERANCE = 1e-4
"""Largest deviation of a `build_lut` ``target_to_source`` from a rotation it accepts: of every
entry of ``Rᵀ R`` from the identity's and of ``det R`` from +1 (a rotation rounded to float32 is
~1e-7 off; a reflection's determinant is -1)."""


def _checked_rotation(target_to_source, dtype) -> Array:
    """``target_to_source`` as a ``(3, 3)`` array of ``dtype``, checked to be a finite rotation
    within `ROTATION_TOLERANCE`: ValueError when concrete, `eqx.error_if` (a runtime error) when
    traced (under `jax.jit` or `jax.vmap`)."""
    traced = isinstance(target_to_source, jax.core.Tracer)
    m = target_to_source if traced else np.asarray(target_to_source)
    if m.shape != (3, 3):
        raise ValueError(f"build_lut: target_to_source must be a 3x3 rotation matrix, got shape {m.shape}")
    if not traced:
        if m.dtype.kind not in "iuf":
            raise TypeError(f"build_lut: target_to_source must be a matrix of real numbers, got {m.dtype}")
        m = m.astype(np.float64)
        if not np.all(np.isfinite(m)):
            raise ValueError(f"build_lut: target_to_source must be finite, got {m.tolist()}")
        orth = float(np.max(np.abs(m.T @ m - np.eye(3))))
        det = float(np.linalg.det(m))
        if orth > ROTATION_TOLERANCE or abs(det - 1.0) > ROTATION_TOLERANCE:
            kind = "a reflection (det < 0)" if det < 0 else "not a rotation"
            raise ValueError(f"build_lut: target_to_source is {kind}: max |R^T R - I| = {orth:.3g}, det = {det:.6g} "
                             f"(a rotation has both within {ROTATION_TOLERANCE:g} of 0 and 1)")
        return jnp.asarray(m, dtype)
    r = jnp.asarray(target_to_source)
    if not jnp.issubdtype(r.dtype, jnp.floating):
        r = r.astype(dtype)
    orth = jnp.max(jnp.abs(r.T @ r - jnp.eye(3, dtype=r.dtype)))
    det = jnp.linalg.det(r)
    bad = ~jnp.all(jnp.isfinite(r)) | ~(orth <= ROTATION_TOLERANCE) | ~(jnp.abs(det - 1) <= ROTATION_TOLERANCE)
    r = eqx.error_if(r, bad, f"build_lut: target_to_source is not a finite rotation (max |R^T R - I| and "
                             f"|det R - 1| within {ROTATION_TOLERANCE:g})")
    return r.astype(dtype)


def supersample_offsets(n: int) -> np.ndarray:
    """Sub-pixel offsets ``(du, dv)`` of an ``n x n`` supersampling pattern, shape ``(n*n, 2)``.

    Sample ``k = iy * n + ix`` sits at ``((ix + 0.5) / n - 0.5, (iy + 0.5) / n - 0.5)`` pixels from
    the pixel centre: a regular grid covering the pixel's square footprint. ``n = 1`` is the pixel
    centre itself.
    """
    n = positive_integer(n, "supersample")
    o = (np.arange(n) + 0.5) / n - 0.5
    dv, du = np.meshgrid(o, o, indexing="ij")
    return np.stack([du.ravel(), dv.ravel()], axis=-1)


def centre_sample(n: int) -> int:
    """Index of the supersample nearest the pixel centre (exactly the centre for odd ``n``)."""
    return int(np.argmin(np.sum(supersample_offsets(n) ** 2, axis=-1)))


class Lut(eqx.Module):
    """A lookup table from a target camera's pixels to a source's faces (an immutable pytree).

    Per target pixel ``(H, W)`` and per supersample ``N = n * n`` (see `supersample_offsets`):

    - `face` ``(H, W, N)`` int32: source face index (0 for a single-image source);
    - `uv` ``(H, W, N, 2)``: source pixel coordinates within that face (pixel-centre convention);
    - `valid` ``(H, W, N)``: the target pixel has a ray, and the source sees it inside its image;
    - `z_to_range` ``(H, W, N)``: ``|ray| / ray_z`` in the source (face) frame, the factor turning
      a planar z-depth of that face into the Euclidean range along the ray (1 for non-pinhole sources);
    - `tap_index` ``(H, W, N)`` int32 and `tap_frac` ``(H, W, N, 2)``: the bilinear taps, as the flat
      index of the top-left tap into the source faces ``(F, Hs + 2 pad, Ws + 2 pad)`` and the
      fractional position ``(fx, fy)`` in ``[0, 1]`` from it;
    - `nearest_index` ``(H, W, N)`` int32: flat index of the nearest source pixel in the *unpadded*
      faces ``(F, Hs, Ws)``;
    - `ring_index` / `ring_frac` / `ring_valid` ``(F, 4 (Ws + 1))`` (cube sources only, else empty):
      where each face's one-pixel border ring is read from its neighbouring faces (see
      `pad_faces`);
    - `border_pixel` ``(K,)`` int32 and `border_fits` ``()`` bool (cube sources; optional): the flat
      indices of the target pixels whose bilinear footprint reaches a face's border ring (padded
      with ``H * W``; `K` a static capacity) and whether they all fit. `resample_bilinear` reads
      every other pixel straight from the unpadded faces. ``None`` (hand-built LUTs): computed per call.

    Static fields: `num_faces`, `source_width`, `source_height`, `pad` (1 for a cube rig: the
    bilinear kernel reads faces padded with a one-pixel border from their neighbours; 0 for a
    single camera: taps are clamped inside the image, like ``cv2.BORDER_REPLICATE``),
    `supersample` (``n``). Invalid entries hold in-bounds placeholder indices, never garbage.
    Batch LUTs of several cameras by building them under `jax.vmap` (leading axes on every array).
    """

    face: Int[Array, "*cams H W N"]
    uv: Float[Array, "*cams H W N 2"]
    valid: Bool[Array, "*cams H W N"]
    z_to_range: Float[Array, "*cams H W N"]
    tap_index: Int[Array, "*cams H W N"]
    tap_frac: Float[Array, "*cams H W N 2"]
    nearest_index: Int[Array, "*cams H W N"]
    ring_index: Int[Array, "*cams F R"]
    ring_frac: Float[Array, "*cams F R 2"]
    ring_valid: Bool[Array, "*cams F R"]
    num_faces: int = eqx.field(static=True)
    source_width: int = eqx.field(static=True)
    source_height: int = eqx.field(static=True)
    pad: int = eqx.field(static=True)
    supersample: int = eqx.field(static=True)
    border_pixel: Int[Array, "*cams K"] | None = None
    border_fits: Bool[Array, "*cams"] | None = None

    @property
    def target_shape(self) -> tuple[int, int]:
        """``(H, W)`` of the target image."""
        return tuple(self.valid.shape[-3:-1])  # type: ignore[return-value]

    @property
    def source_shape(self) -> tuple[int, int, int]:
        """``(F, Hs, Ws)``: faces and face size the LUT reads from."""
        return (self.num_faces, self.source_height, self.source_width)

    @property
    def pixel_valid(self) -> Bool[Array, "*cams H W"]:
        """Per target pixel: at least one of its supersamples is valid."""
        return jnp.any(self.valid, axis=-1)


def _ring_pixels(size: int) -> np.ndarray:
    """Pixel coordinates ``(u, v)`` of the one-pixel ring just outside an ``S x S`` face,
    clockwise from the top-left corner ``(-1, -1)``: shape ``(4 (S + 1), 2)``."""
    s = size
    top = [(u, -1) for u in range(-1, s)]
    right = [(s, v) for v in range(-1, s)]
    bottom = [(u, s) for u in range(s, -1, -1)]
    left = [(-1, v) for v in range(s, -1, -1)]
    return np.asarray(top + right + bottom + left, dtype=np.float64)


def _bilinear_taps(face, uv, *, width: int, height: int, pad: int):
    """Flat top-left tap index and fractions of bilinear taps that never leave their face.

    With ``pad = 1`` coordinates address faces padded by one pixel (stride ``W + 2``); with
    ``pad = 0`` they are clamped to the image (``cv2.BORDER_REPLICATE``).
    """
    sw, sh = width + 2 * pad, height + 2 * pad
    dtype = uv.dtype
    u = jnp.clip(uv[..., 0] + pad, 0.0, sw - 1.0)
    v = jnp.clip(uv[..., 1] + pad, 0.0, sh - 1.0)
    x0 = jnp.clip(jnp.floor(u), 0, max(sw - 2, 0)).astype(jnp.int32)
    y0 = jnp.clip(jnp.floor(v), 0, max(sh - 2, 0)).astype(jnp.int32)
    fx = jnp.clip(u - x0.astype(dtype), 0.0, 1.0)
    fy = jnp.clip(v - y0.astype(dtype), 0.0, 1.0)
    index = (face.astype(jnp.int32) * sh + y0) * sw + x0
    return index, jnp.stack([fx, fy], axis=-1)


def _nearest_index(face, uv, *, width: int, height: int):
    x = jnp.clip(jnp.floor(uv[..., 0] + 0.5), 0, width - 1).astype(jnp.int32)
    y = jnp.clip(jnp.floor(uv[..., 1] + 0.5), 0, height - 1).astype(jnp.int32)
    return (face.astype(jnp.int32) * height + y) * width + x


def _project_source(source: AbstractCamera, rays: Array):
    """(face, uv, valid, z_to_range) of source-frame rays."""
    dtype = rays.dtype
    if isinstance(source, CubeRig):
        face, uv, valid = source.project_faces(rays)
        face = face.astype(jnp.int32)
        rots = source.face_to_camera.rotation_matrix.astype(dtype)
        axis_z = rots[:, :, 2][face]  # each sample's face optical axis, rig frame
        # Multiply-adds on coordinate planes: a sum over the minor axis of 3 is a reduction that
        # XLA:CPU hands to a library kernel several times slower than the loop.
        ray_z = axis_z[..., 0] * rays[..., 0] + axis_z[..., 1] * rays[..., 1] + axis_z[..., 2] * rays[..., 2]
    else:
        uv, valid = source.project(rays)
        valid = valid & source.contains(uv)
        face = jnp.zeros(rays.shape[:-1], jnp.int32)
        ray_z = rays[..., 2]
    if isinstance(source, (CubeRig, Pinhole)):
        norm = jnp.linalg.norm(rays, axis=-1)
        ok = valid & (ray_z > 0)
        z_to_range = jnp.where(ok, norm / jnp.where(ok, ray_z, 1.0), 1.0)
    else:
        z_to_range = jnp.ones(rays.shape[:-1], dtype)
    uv = jnp.where(valid[..., None], uv, 0.0)
    face = jnp.where(valid, face, 0).astype(jnp.int32)
    return face, uv, valid, z_to_range


def build_lut(
    source: AbstractCamera,
    target: AbstractCamera,
    *,
    target_to_source: Float[ArrayLike, "3 3"] | None = None,
    supersample: int = 1,
    dtype=jnp.float32,
) -> Lut:
    """The LUT taking ``target``'s pixels to ``source``'s (a `CubeRig` or any single camera).

    Every target pixel (and each of its ``supersample x supersample`` sub-pixel samples) is
    unprojected to a ray in the target's OpenCV frame, rotated by ``target_to_source`` (a 3x3
    rotation from the target frame to the source frame; identity by default), and projected into
    the source: a cube rig picks the face by the dominant-axis rule. Both cameras must share their
    centre. Pure JAX: call it under `jax.jit` (cameras as arguments) and `jax.vmap` /
    `eqx.filter_vmap` over a batch of cameras. Examples: cube rig -> fisheye (SynWoodScape),
    fisheye -> `Pinhole` (rectification), fisheye -> `Equirectangular` / `Cylindrical`,
    pinhole -> fisheye.

    ``dtype`` is the precision of the ray computation and of the stored coordinates (float32 by
    default: 1024-px faces keep ~1e-4 px).

    Refused: a ``target_to_source`` that is not a finite 3x3 rotation within `ROTATION_TOLERANCE`
    (a reflection, a scaled or non-finite matrix: ValueError; under `jax.jit` or `jax.vmap`, where
    it is traced, an `eqx.error_if` runtime error), a ``supersample`` that is not an integer >= 1
    (TypeError, ValueError) and a ``dtype`` other than float32 or float64 (TypeError).
    """
    dtype = resolve_dtype(dtype)  # TypeError unless float32 or float64
    n = positive_integer(supersample, "supersample")
    r = None if target_to_source is None else _checked_rotation(target_to_source, dtype)
    offsets = jnp.asarray(supersample_offsets(n), dtype)  # (N, 2)
    grid = target.pixel_grid(dtype)  # (H, W, 2)
    uv_t = grid[:, :, None, :] + offsets  # (H, W, N, 2)
    rays, valid_t = target.unproject(uv_t)
    rays = rays.astype(dtype)
    if r is not None:
        rays = jnp.einsum("ij,...j->...i", r, rays)
    face, uv, valid_s, z_to_range = _project_source(source, rays)
    valid = valid_t & valid_s
    if isinstance(source, CubeRig):
        return _assemble(face, uv, valid, z_to_range, rig=source, width=source.width, height=source.height, n=n)
    return _assemble(face, uv, valid, z_to_range, rig=None, width=source.width, height=source.height, n=n)



compiled_build_lut = jax.jit(build_lut, static_argnames=("supersample", "dtype"))
"""`build_lut` compiled (once per camera types, image sizes and static arguments): the same
arguments, the same `Lut`."""

def lut_from_map(
    uv: Float[ArrayLike, "H W N 2"],
    *,
    source_width: int,
    source_height: int,
    valid: Bool[ArrayLike, "H W N"] | None = None,
    z_to_range: Float[ArrayLike, "H W N"] | None = None,
) -> Lut:
    """A single-source LUT from an explicit coordinate map (like the maps of ``cv2.remap``).

    ``uv`` holds source pixel coordinates (pixel-centre convention) per target pixel and sample;
    ``valid`` defaults to "inside the source image" and ``z_to_range`` to 1. Taps are clamped
    inside the source image (``cv2.BORDER_REPLICATE``); ``supersample`` is ``sqrt(N)`` and the
    samples are assumed in the `supersample_offsets` order.
    """
    uv = jnp.asarray(uv)
    if uv.ndim != 4 or uv.shape[-1] != 2:
        raise ValueError(f"lut_from_map: uv must have shape (H, W, N, 2), got {uv.shape}")
    n = int(round(uv.shape[2] ** 0.5))
    if n * n != uv.shape[2]:
        raise ValueError(f"lut_from_map: the sample axis must be a square number, got {uv.shape[2]}")
    inside = (
        (uv[..., 0] >= -0.5) & (uv[..., 0] <= source_width - 0.5) & (uv[..., 1] >= -0.5) & (uv[..., 1] <= source_height - 0.5)
    )
    valid = inside if valid is None else jnp.asarray(valid, bool) & inside
    z = jnp.ones(uv.shape[:-1], uv.dtype) if z_to_range is None else jnp.asarray(z_to_range, uv.dtype)
    face = jnp.zeros(uv.shape[:-1], jnp.int32)
    uv = jnp.where(valid[..., None], uv, jnp.zeros_like(uv))
    return _assemble(face, uv, valid, z, rig=None, width=int(source_width), height=int(source_height), n=n)


def _assemble(face, uv, valid, z_to_range, *, rig: CubeRig | None, width: int, height: int, n: int) -> Lut:
    dtype = uv.dtype
    sw, sh = width, height
    if rig is not None:
        num_faces, pad = len(rig.faces), 1
    else:
        num_faces, pad = 1, 0
    if sw < 2 or sh < 2:
        raise ValueError(f"build_lut: the source must be at least 2x2 pixels, got {sw}x{sh}")
    tap_index, tap_frac = _bilinear_taps(face, uv, width=sw, height=sh, pad=pad)
    nearest = _nearest_index(face, uv, width=sw, height=sh)
    tap_index = jnp.where(valid, tap_index, 0)
    nearest = jnp.where(valid, nearest, 0)
    if rig is not None:
        ring_index, ring_frac, ring_valid = _ring_lut(rig, dtype)
    else:
        ring_index = jnp.zeros((1, 0), jnp.int32)
        ring_frac = jnp.zeros((1, 0, 2), dtype)
        ring_valid = jnp.zeros((1, 0), bool)
    return Lut(
        face=face,
        uv=uv.astype(dtype),
        valid=valid,
        z_to_range=z_to_range.astype(dtype),
        tap_index=tap_index,
        tap_frac=tap_frac.astype(dtype),
        nearest_index=nearest,
        ring_index=ring_index,
        ring_frac=ring_frac,
        ring_valid=ring_valid,
        num_faces=num_faces,
        source_width=sw,
        source_height=sh,
        pad=pad,
        supersample=n,
        **(border_pixels(tap_index, valid, width=sw, num_faces=num_faces) if pad else {}),
    )


def border_capacity(height: int, width: int, n: int, num_faces: int, face_size: int) -> int:
    """Static capacity of `Lut.border_pixel`: four one-pixel bands per face side, four target
    samples per face pixel (faces much coarser than the target may exceed it: `resample_bilinear`
    then pads the faces instead)."""
    return int(min(height * width, max(1024, 16 * num_faces * (face_size + 2) * n)))


def split_padded_index(index, size: int):
    """Face, x and y (padded-face coordinates in ``[0, S + 1]``) of flat indices into faces padded
    by one pixel (`Lut.tap_index` of a cube rig)."""
    sw = size + 2
    face = index // (sw * sw)
    rem = index - face * (sw * sw)
    y = rem // sw
    return face, rem - y * sw, y


def border_pixels(tap_index, valid, *, width: int, num_faces: int) -> dict:
    """``{"border_pixel", "border_fits"}`` of a cube LUT (see `Lut`)."""
    h, w, n = valid.shape[-3:]
    _, xp, yp = split_padded_index(tap_index, width)
    inner = (xp >= 1) & (xp <= width - 1) & (yp >= 1) & (yp <= width - 1)
    border = jnp.any(valid & ~inner, axis=-1).reshape(-1)
    cap = border_capacity(h, w, n, num_faces, width)
    pix = jnp.nonzero(border, size=cap, fill_value=h * w)[0].astype(jnp.int32)
    return {"border_pixel": pix, "border_fits": jnp.sum(border) <= cap}


def _ring_lut(rig: CubeRig, dtype):
    """Where each face's one-pixel border ring lies in the *other* faces (bilinear taps into the
    unpadded faces, clamped within the neighbour). A ring pixel no face sees (towards the missing
    back face of a five-face rig) is marked invalid: `pad_faces` replicates the face's own edge."""
    s = rig.width
    ring = jnp.asarray(_ring_pixels(s), dtype)  # (R, 2)
    f = len(rig.faces)
    face_ids = jnp.broadcast_to(jnp.arange(f, dtype=jnp.int32)[:, None], (f, ring.shape[0]))
    rays, _ = rig.unproject_faces(face_ids, jnp.broadcast_to(ring, (f,) + ring.shape))
    face, uv, valid = rig.project_faces(rays)
    face = face.astype(jnp.int32)
    valid = valid & (face != face_ids)
    uv = jnp.where(valid[..., None], uv, 0.0)
    face = jnp.where(valid, face, 0)
    index, frac = _bilinear_taps(face, uv, width=s, height=s, pad=0)
    return jnp.where(valid, index, 0), frac.astype(dtype), valid


def ring_positions(size: int) -> np.ndarray:
    """Padded-face coordinates ``(x, y)`` (integers in ``[0, S + 1]``) of the ring pixels, in the
    order `Lut.ring_index` uses: shape ``(4 (S + 1), 2)``."""
    return (_ring_pixels(size) + 1).astype(np.int64)


def stack_luts(luts: list[Lut]) -> Lut:
    """Stack LUTs built separately (same shapes and static fields) along a new leading camera axis."""
    return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *luts)
