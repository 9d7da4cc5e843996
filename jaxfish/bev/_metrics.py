"""Semantic segmentation scores: per-class IoU and mIoU."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float, Int


class IouScores(eqx.Module):
    """Per-class `intersection` and `union` (pixel counts), `iou` = intersection / union (0 where
    the class is absent), `present` (the class occurs in the truth or the prediction) and
    `mean_iou` over the present classes (NaN if none)."""

    intersection: Int[Array, " C"]
    union: Int[Array, " C"]
    iou: Float[Array, " C"]
    present: Bool[Array, " C"]
    mean_iou: Float[Array, ""]


def semantic_iou(
    prediction: Int[ArrayLike, "*shape"],
    truth: Int[ArrayLike, "*shape"],
    *,
    num_classes: int = 25,
    valid: Bool[ArrayLike, "*shape"] | None = None,
) -> IouScores:
    """IoU of every class ``0..num_classes-1`` and their mean (mIoU) over the evaluated pixels:
    those with a truth label in range and ``valid``. A prediction outside the range (e.g.
    `UNOBSERVED` = -1) counts as a miss for the true class. Classes absent from both prediction
    and truth are ignored by the mean. Any shape (batches are pooled); pure, jittable."""
    p = jnp.asarray(prediction)
    t = jnp.asarray(truth)
    if p.shape != t.shape:
        raise ValueError(f"semantic_iou: prediction {p.shape} and truth {t.shape} differ in shape")
    if not (jnp.issubdtype(p.dtype, jnp.integer) and jnp.issubdtype(t.dtype, jnp.integer)):
        raise ValueError(f"semantic_iou: labels must be integer, got {p.dtype} and {t.dtype}")
    c = int(num_classes)
    if c < 1:
        raise ValueError(f"semantic_iou: num_classes must be positive, got {num_classes}")
    p = p.astype(jnp.int32).reshape(-1)
    t = t.astype(jnp.int32).reshape(-1)
    keep = (t >= 0) & (t < c)
    if valid is not None:
        v = jnp.asarray(valid, bool)
        if v.shape != jnp.shape(prediction):
            raise ValueError(f"semantic_iou: valid {v.shape} does not match the labels {jnp.shape(prediction)}")
        keep = keep & v.reshape(-1)
    pc = jnp.where((p >= 0) & (p < c), p, c)  # c = "no class"
    idx = jnp.where(keep, t * (c + 1) + pc, c * (c + 1))
    conf = jnp.bincount(idx, length=c * (c + 1) + 1)[: c * (c + 1)].reshape(c, c + 1)
    inter = jnp.diagonal(conf[:, :c])
    union = conf.sum(axis=1) + conf[:, :c].sum(axis=0) - inter
    present = union > 0
    iou = jnp.where(present, inter.astype(jnp.float32) / jnp.maximum(union, 1).astype(jnp.float32), 0.0)
    n = present.sum()
    mean = jnp.where(n > 0, jnp.where(present, iou, 0.0).sum() / jnp.maximum(n, 1).astype(jnp.float32), jnp.nan)
    return IouScores(intersection=inter.astype(jnp.int32), union=union.astype(jnp.int32), iou=iou, present=present,
                     mean_iou=mean)
