"""Cluster-bootstrap intervals: hand-checked cases and properties."""

from __future__ import annotations

import numpy as np
import pytest

from traffictwin.stats import (
    Interval,
    excludes_zero,
    mean_ci,
    paired_mean_difference_ci,
    statistic_ci,
)


def test_constant_values_give_a_zero_width_interval() -> None:
    ci = mean_ci(np.full(10, 2.5), n_boot=200)
    assert (ci.estimate, ci.lo, ci.hi) == (2.5, 2.5, 2.5)


def test_interval_covers_the_mean_and_is_deterministic() -> None:
    x = np.random.default_rng(1).normal(3.0, 1.0, 400)
    a, b = mean_ci(x, seed=7), mean_ci(x, seed=7)
    assert a == b
    assert a.lo < x.mean() < a.hi
    # ~ normal theory: half-width ~ 1.96 sigma / sqrt(n) = 0.098
    assert (a.hi - a.lo) / 2 == pytest.approx(1.96 / np.sqrt(400), rel=0.15)


def test_groups_are_resampled_whole() -> None:
    # two groups of identical values: every resample's mean is one of 0, 0.5 (weighted), 1
    x = np.r_[np.zeros(5), np.ones(5)]
    g = np.r_[np.zeros(5), np.ones(5)]
    ci = mean_ci(x, g, n_boot=500, seed=0)
    assert ci.n_groups == 2 and ci.lo == 0.0 and ci.hi == 1.0
    # per-sample resampling of the same data is much narrower
    per_sample = mean_ci(x, n_boot=500, seed=0)
    assert per_sample.hi - per_sample.lo < 0.75


def test_correlated_groups_widen_the_interval() -> None:
    rng = np.random.default_rng(0)
    offsets = rng.normal(0, 1, 20)  # 20 scenarios, 30 near-duplicate samples each
    x = np.repeat(offsets, 30) + rng.normal(0, 0.1, 600)
    g = np.repeat(np.arange(20), 30)
    assert (mean_ci(x, g).hi - mean_ci(x, g).lo) > 3 * (mean_ci(x).hi - mean_ci(x).lo)


def test_paired_difference_sees_a_small_consistent_gain() -> None:
    rng = np.random.default_rng(2)
    base = rng.normal(0, 5, 300)  # large spread shared by both methods
    better = base - 0.1 + rng.normal(0, 0.01, 300)
    d = paired_mean_difference_ci(better, base)
    assert d.estimate == pytest.approx(-0.1, abs=0.01)
    assert excludes_zero(d) and d.hi < 0
    # unpaired, the same gain is lost in the spread
    assert not excludes_zero(
        Interval(0.0, mean_ci(better).lo - mean_ci(base).hi, mean_ci(better).hi - mean_ci(base).lo)
    )


def test_statistic_ci_matches_mean_ci_for_the_mean() -> None:
    x = np.random.default_rng(3).exponential(1.0, 200)
    g = np.repeat(np.arange(50), 4)
    s = statistic_ci(lambda idx: float(x[idx].mean()), x.size, g, n_boot=1500, seed=1)
    m = mean_ci(x, g, n_boot=1500, seed=1)
    assert s.estimate == pytest.approx(m.estimate)
    assert s.lo == pytest.approx(m.lo, abs=0.05) and s.hi == pytest.approx(m.hi, abs=0.05)


def test_statistic_ci_drops_undefined_resamples() -> None:
    y = np.r_[np.zeros(3), np.ones(3)]

    def share_positive_if_both(idx: np.ndarray) -> float:
        return float(y[idx].mean()) if 0 < y[idx].sum() < idx.size else float("nan")

    ci = statistic_ci(share_positive_if_both, 6, n_boot=300, seed=0)
    assert np.isfinite(ci.lo) and 0 < ci.lo <= ci.hi < 1


def test_excludes_zero() -> None:
    assert excludes_zero(Interval(1, 0.1, 2)) and excludes_zero(Interval(-1, -2, -0.1))
    assert not excludes_zero(Interval(0.5, -0.1, 1)) and not excludes_zero(Interval(0, 0, 1))


@pytest.mark.parametrize(
    "call, msg",
    [
        (lambda: mean_ci(np.array([])), "no samples"),
        (lambda: mean_ci(np.array([1.0, np.nan])), "non-finite"),
        (lambda: mean_ci(np.ones(3), np.ones(2)), "one label per sample"),
        (lambda: paired_mean_difference_ci(np.ones(3), np.ones(4)), "differ in length"),
    ],
)
def test_bad_input_is_named(call, msg: str) -> None:
    with pytest.raises(ValueError, match=msg):
        call()
