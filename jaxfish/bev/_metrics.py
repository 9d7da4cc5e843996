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
    return _iou_scores(inter, union)


def _iou_scores(inter, union) -> IouScores:
    inter = jnp.asarray(inter).astype(jnp.int32)
    union = jnp.asarray(union).astype(jnp.int32)
    present = union > 0
    iou = jnp.where(present, inter.astype(jnp.float32) / jnp.maximum(union, 1).astype(jnp.float32), 0.0)
    n = present.sum()
    mean = jnp.where(n > 0, jnp.where(present, iou, 0.0).sum() / jnp.maximum(n, 1).astype(jnp.float32), jnp.nan)
    return IouScores(intersection=inter, union=union, iou=iou, present=present, mean_iou=mean)


VOID_CLASS = 0
"""SynWoodScape class 0 (``unlabeled``): never scored by `bev_scores`."""


class BevScores(eqx.Module):
    """A top view scored against the truth two ways (`bev_scores`): over **all** cells (`all_cells`,
    a cell the method did not observe counts as a miss for its true class) and over the cells it
    **observed** only (`observed_cells`), with the `coverage` (observed fraction of the scored
    cells). `truth_count` / `observed_truth_count` count the true cells of each class among all /
    the observed scored cells; `miou_all` and `miou_observed` average the IoU over the classes
    present in that truth, the void class excluded (NaN when no class is scored). `cells` and
    `observed_count` are the numbers of scored and observed scored cells. Sum the count fields of
    several samples and call `pool_bev_scores` for pooled scores."""

    all_cells: IouScores
    observed_cells: IouScores
    truth_count: Int[Array, " C"]
    observed_truth_count: Int[Array, " C"]
    cells: Int[Array, ""]
    observed_count: Int[Array, ""]
    coverage: Float[Array, ""]
    miou_all: Float[Array, ""]
    miou_observed: Float[Array, ""]


def truth_class_miou(
    intersection: Int[ArrayLike, " C"], union: Int[ArrayLike, " C"], truth_count: Int[ArrayLike, " C"], *,
    void_class: int | None = VOID_CLASS,
) -> tuple[Float[Array, " C"], Float[Array, ""]]:
    """Per-class IoU (NaN where not scored) and their mean, scoring the classes present in the truth
    (``truth_count > 0``) except ``void_class``: a class only a prediction has lowers the IoU of the
    true classes it covers but is not averaged itself. The mean is NaN when no class is scored."""
    inter = jnp.asarray(intersection, jnp.float32)
    union = jnp.asarray(union, jnp.float32)
    scored = jnp.asarray(truth_count) > 0
    if void_class is not None and 0 <= int(void_class) < scored.shape[0]:
        scored = scored.at[int(void_class)].set(False)
    iou = jnp.where(scored, inter / jnp.maximum(union, 1.0), jnp.nan)
    n = scored.sum()
    mean = jnp.where(n > 0, jnp.where(scored, iou, 0.0).sum() / jnp.maximum(n, 1).astype(jnp.float32), jnp.nan)
    return iou, mean


def _counts(t, keep, c):
    return jnp.bincount(jnp.where(keep, t, c), length=c + 1)[:c].astype(jnp.int32)


def bev_scores(
    prediction: Int[ArrayLike, "*shape"],
    truth: Int[ArrayLike, "*shape"],
    *,
    observed: Bool[ArrayLike, "*shape"] | None = None,
    num_classes: int = 25,
    valid: Bool[ArrayLike, "*shape"] | None = None,
    void_class: int | None = VOID_CLASS,
) -> BevScores:
    """Score a top view on all cells and on its observed cells (`BevScores`).

    Scored cells: truth label in ``[0, num_classes)`` and ``valid``. ``observed`` (default: the
    prediction is a class in range, i.e. not `UNOBSERVED`) marks the cells the method made a
    claim about. ``all_cells`` is `semantic_iou` over the scored cells (an unobserved cell is a miss
    for its true class); ``observed_cells`` over the scored cells that were observed. mIoU
    averages over the classes present in the respective truth, ``void_class`` excluded
    (`truth_class_miou`). Any shape (batches are pooled); pure, jittable."""
    p = jnp.asarray(prediction)
    t = jnp.asarray(truth)
    c = int(num_classes)
    if c < 1:
        raise ValueError(f"bev_scores: num_classes must be positive, got {num_classes}")
    obs = (p >= 0) & (p < c) if observed is None else jnp.asarray(observed, bool)
    if obs.shape != t.shape:
        raise ValueError(f"bev_scores: observed {obs.shape} does not match the labels {t.shape}")
    keep = jnp.ones(t.shape, bool) if valid is None else jnp.asarray(valid, bool)
    if keep.shape != t.shape:
        raise ValueError(f"bev_scores: valid {keep.shape} does not match the labels {t.shape}")
    all_cells = semantic_iou(p, t, num_classes=c, valid=keep)
    observed_cells = semantic_iou(p, t, num_classes=c, valid=keep & obs)
    ti = t.astype(jnp.int32).reshape(-1)
    scored = keep.reshape(-1) & (ti >= 0) & (ti < c)
    truth_count = _counts(ti, scored, c)
    observed_truth_count = _counts(ti, scored & obs.reshape(-1), c)
    return pool_bev_scores(all_cells.intersection, all_cells.union, truth_count, observed_cells.intersection,
                           observed_cells.union, observed_truth_count, void_class=void_class)


def pool_bev_scores(
    intersection: Int[ArrayLike, " C"], union: Int[ArrayLike, " C"], truth_count: Int[ArrayLike, " C"],
    observed_intersection: Int[ArrayLike, " C"], observed_union: Int[ArrayLike, " C"],
    observed_truth_count: Int[ArrayLike, " C"], *, void_class: int | None = VOID_CLASS,
) -> BevScores:
    """`BevScores` from per-class counts (e.g. a `BevScores`' counts summed over samples: pooled
    scores). ``intersection`` / ``union`` / ``truth_count`` are over all scored cells, the
    ``observed_*`` ones over the observed scored cells; a count of scored cells is the sum of its
    truth counts."""

    tc = jnp.asarray(truth_count, jnp.int32)
    otc = jnp.asarray(observed_truth_count, jnp.int32)
    cells = tc.sum()
    observed_count = otc.sum()
    coverage = jnp.where(cells > 0, observed_count.astype(jnp.float32) / jnp.maximum(cells, 1).astype(jnp.float32),
                         jnp.nan)
    return BevScores(all_cells=_iou_scores(intersection, union),
                     observed_cells=_iou_scores(observed_intersection, observed_union),
                     truth_count=tc, observed_truth_count=otc, cells=cells, observed_count=observed_count,
                     coverage=coverage,
                     miou_all=truth_class_miou(intersection, union, tc, void_class=void_class)[1],
                     miou_observed=truth_class_miou(observed_intersection, observed_union, otc,
                                                    void_class=void_class)[1])
