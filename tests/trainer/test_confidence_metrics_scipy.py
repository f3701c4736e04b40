"""AUROC and the paired bootstrap, computed by ``scipy.stats``, against the values the hand-written loops they
replaced gave on the same fixed data (issue 66).

The literals were printed by the code at commit 2758e7f (``metrics/confidence.py``'s rank loop,
``metrics/paired.py``'s own percentile bootstrap) on :func:`_scores` and :func:`_paired`; the naive AUROC
below counts every pair, the definition the rank formula stands for.
"""

from __future__ import annotations

import numpy as np
import pytest

from popcode_trainer.metrics.confidence import auroc
from popcode_trainer.metrics.paired import paired_difference

OLD_AUROC = 0.8889055622248899
OLD_PAIRED = {"first": 0.5133333333333333, "second": 0.5466666666666666, "difference": 0.033333333333333326,
              "interval": (0.005812499999999973, 0.06166666666666676)}


def _scores() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(66)
    score = np.round(rng.random(200), 1)  # eleven values: many ties
    return score, rng.random(200) < score


def _paired() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(66)
    rng.random(400)  # the draws of _scores, so the data are those the old code saw
    first = rng.integers(0, 11, 120) / 10
    return first, np.clip(first + rng.integers(-2, 4, 120) / 10, 0, 1)


def _naive_auroc(score: np.ndarray, correct: np.ndarray) -> float:
    """Share of (correct, wrong) pairs whose correct one scores higher, ties counting half."""
    pairs = score[correct][:, None] - score[~correct][None, :]
    return float(((pairs > 0) + 0.5 * (pairs == 0)).mean())


def test_auroc_with_ties_matches_the_hand_written_ranks_and_the_pairwise_count() -> None:
    score, correct = _scores()
    assert auroc(score, correct) == pytest.approx(OLD_AUROC, abs=1e-12)
    assert auroc(score, correct) == pytest.approx(_naive_auroc(score, correct), abs=1e-12)


def test_paired_bootstrap_matches_the_hand_written_interval() -> None:
    """scipy draws the same instances from the same seed and takes the same percentiles: the interval moves by
    rounding only (bench/results/scipy-confidence-metrics.md)."""
    result = paired_difference(*_paired(), seed=0)
    assert result.instances == 120
    for key in ("first", "second", "difference"):
        assert getattr(result, key) == pytest.approx(OLD_PAIRED[key], abs=1e-12)
    np.testing.assert_allclose(result.interval, OLD_PAIRED["interval"], atol=1e-12)


def test_paired_bootstrap_of_one_instance_or_no_spread_is_the_difference_itself() -> None:
    """scipy refuses to resample a single observation; the interval of one instance (or of identical scores) is
    the difference itself, as the hand-written loop gave."""
    assert paired_difference(np.array([0.2]), np.array([0.7])).interval == pytest.approx((0.5, 0.5))
    assert paired_difference(np.full(5, 0.3), np.full(5, 0.4)).interval == pytest.approx((0.1, 0.1))
