"""Tight 2D boxes in each image: from instance masks (visible extent) and from densely sampled
box surfaces (full extent, occluded parts included)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ..cameras import AbstractCamera
from ..transforms import Pose
from ._boxes3d import Boxes3D

SURFACE_SAMPLES = 12
"""Default samples per edge of each box face for the surface boxes (``n x n`` per face)."""


class Boxes2D(eqx.Module):
    """2D boxes ``(B, 4)`` int32 ``x1, y1, x2, y2``: integer pixel (centre) coordinates of the
    extreme pixels, **inclusive** (a one-pixel object has ``x1 == x2``); `present` ``(B,)`` marks
    boxes with at least one pixel (others hold zeros); `pixels` ``(B,)`` counts the pixels (mask
    boxes) or the surface samples (surface boxes) inside the image."""

    xyxy: Int[Array, "B 4"]
    present: Bool[Array, " B"]
    pixels: Int[Array, " B"]


def boxes_from_instances(box_index: Int[ArrayLike, "H W"], num_boxes: int, *, min_pixels: int = 1) -> Boxes2D:
    """Tight boxes of the visible pixels of every instance (``box_index`` from
    `instance_segmentation`, -1 for none); a box needs ``min_pixels`` pixels to be present."""
    bi = jnp.asarray(box_index).astype(jnp.int32)
    h, w = bi.shape
    vv, uu = jnp.meshgrid(jnp.arange(h, dtype=jnp.int32), jnp.arange(w, dtype=jnp.int32), indexing="ij")
    seg = jnp.where(bi >= 0, bi, num_boxes).reshape(-1)
    n = num_boxes + 1
    x1 = jax.ops.segment_min(uu.reshape(-1), seg, n)[:num_boxes]
    x2 = jax.ops.segment_max(uu.reshape(-1), seg, n)[:num_boxes]
    y1 = jax.ops.segment_min(vv.reshape(-1), seg, n)[:num_boxes]
    y2 = jax.ops.segment_max(vv.reshape(-1), seg, n)[:num_boxes]
    cnt = jax.ops.segment_sum(jnp.ones(h * w, jnp.int32), seg, n)[:num_boxes]
    present = cnt >= max(int(min_pixels), 1)
    xyxy = jnp.where(present[:, None], jnp.stack([x1, y1, x2, y2], axis=-1), 0).astype(jnp.int32)
    return Boxes2D(xyxy=xyxy, present=present, pixels=cnt.astype(jnp.int32))


def box_surface_points(boxes: Boxes3D, samples: int = SURFACE_SAMPLES) -> Float[Array, "B P 3"]:
    """``6 * samples²`` points on the surface of every box (world frame): each face sampled on a
    regular grid that includes its edges and corners."""
    n = int(samples)
    g = np.linspace(-1.0, 1.0, n)
    a, b = np.meshgrid(g, g, indexing="ij")
    a, b = a.ravel(), b.ravel()
    one = np.ones_like(a)
    faces = [np.stack([s * one, a, b], -1) for s in (-1, 1)] + [np.stack([a, s * one, b], -1) for s in (-1, 1)] \
        + [np.stack([a, b, s * one], -1) for s in (-1, 1)]
    unit = jnp.asarray(np.concatenate(faces), boxes.half_extent.dtype)  # (P, 3)
    local = unit[None] * boxes.half_extent[:, None, :]
    rot = boxes.box_to_world.rotation_matrix
    return jnp.einsum("bij,bpj->bpi", rot, local) + boxes.box_to_world.translation[:, None, :]


def boxes_from_surfaces(
    boxes: Boxes3D, camera: AbstractCamera, world_to_camera: Pose, *, samples: int = SURFACE_SAMPLES
) -> Boxes2D:
    """Boxes of the full extent of every 3D box, occluded parts included: the box surfaces sampled
    densely (`box_surface_points`), projected with ``camera`` (every model, beyond 90 degrees
    included) and clipped to the image; samples the model cannot project are skipped. Integer
    coordinates are the pixels holding the extreme samples (``round``), inclusive."""
    pts = box_surface_points(boxes, samples)
    pc = world_to_camera.apply(pts)
    uv, ok = camera.project(pc)
    ok = ok & camera.contains(uv) & boxes.active[:, None]
    big = jnp.asarray(1e9, uv.dtype)
    lo = jnp.min(jnp.where(ok[..., None], uv, big), axis=1)
    hi = jnp.max(jnp.where(ok[..., None], uv, -big), axis=1)
    cnt = jnp.sum(ok.astype(jnp.int32), axis=1)
    present = cnt > 0
    w, h = camera.width, camera.height
    r = lambda x, m: jnp.clip(jnp.round(x), 0, m - 1).astype(jnp.int32)  # noqa: E731
    xyxy = jnp.stack([r(lo[:, 0], w), r(lo[:, 1], h), r(hi[:, 0], w), r(hi[:, 1], h)], axis=-1)
    return Boxes2D(xyxy=jnp.where(present[:, None], xyxy, 0), present=present, pixels=cnt)
