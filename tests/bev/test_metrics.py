"""`bev_scores`: a top view scored on all cells (unobserved = miss) and on its observed cells, with
coverage, against counts worked out by hand; pooling equals scoring the concatenation."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from jaxfish import bev


def test_scores_on_all_and_on_observed_cells_by_hand():
    # truth: void, 1, 1, 1, 2, 2, 3, 3; the prediction leaves four cells unobserved (-1)
    truth = np.array([0, 1, 1, 1, 2, 2, 3, 3])
    pred = np.array([1, 1, -1, 1, 2, -1, -1, -1])
    s = bev.bev_scores(pred, truth, num_classes=5)
    # all cells: class 1: 2 / 4 (a void cell predicted 1, an unobserved 1); class 2: 1 / 2; class 3: 0 / 2
    np.testing.assert_allclose(np.asarray(s.all_cells.iou)[1:4], [2 / 4, 1 / 2, 0.0])
    assert float(s.miou_all) == pytest.approx((2 / 4 + 1 / 2 + 0.0) / 3)
    # observed cells (0, 1, 3, 4): class 1: 2 / 3, class 2: 1 / 1; class 3 has no observed cell: not scored
    np.testing.assert_allclose(np.asarray(s.observed_cells.iou)[1:3], [2 / 3, 1.0])
    assert float(s.miou_observed) == pytest.approx((2 / 3 + 1.0) / 2)
    assert float(s.coverage) == pytest.approx(4 / 8) and int(s.cells) == 8 and int(s.observed_count) == 4
    np.testing.assert_array_equal(np.asarray(s.truth_count), [1, 3, 2, 2, 0])
    np.testing.assert_array_equal(np.asarray(s.observed_truth_count), [1, 2, 1, 0, 0])
    # the same under jit; an explicit observed mask overrides "a class in range"
    j = jax.jit(lambda p, t: bev.bev_scores(p, t, num_classes=5))(pred, truth)
    assert float(j.miou_observed) == pytest.approx(float(s.miou_observed))
    everything = bev.bev_scores(pred, truth, num_classes=5, observed=np.ones(8, bool))
    assert float(everything.coverage) == 1.0 and float(everything.miou_observed) == pytest.approx(float(s.miou_all))


def test_pooled_scores_equal_the_concatenation_and_nothing_scored_is_nan():
    rng = np.random.default_rng(0)
    truth = rng.integers(0, 6, (3, 40))
    pred = np.where(rng.random((3, 40)) < 0.3, -1, rng.integers(0, 6, (3, 40)))
    parts = [bev.bev_scores(p, t, num_classes=6) for p, t in zip(pred, truth, strict=True)]

    def total(name):
        return sum(np.asarray(getattr(p, name)) for p in parts)

    pooled = bev.pool_bev_scores(
        sum(np.asarray(p.all_cells.intersection) for p in parts), sum(np.asarray(p.all_cells.union) for p in parts),
        total("truth_count"), sum(np.asarray(p.observed_cells.intersection) for p in parts),
        sum(np.asarray(p.observed_cells.union) for p in parts), total("observed_truth_count"))
    whole = bev.bev_scores(pred, truth, num_classes=6)
    for f in ("miou_all", "miou_observed", "coverage"):
        assert float(getattr(pooled, f)) == pytest.approx(float(getattr(whole, f)))
    void = bev.bev_scores(np.zeros(4, int), np.zeros(4, int), num_classes=3)
    assert np.isnan(float(void.miou_all)) and np.isnan(float(void.miou_observed)) and float(void.coverage) == 1.0
    with pytest.raises(ValueError, match="observed"):
        bev.bev_scores(pred[0], truth[0], observed=np.ones(3, bool))
