"""Relative depth error by range bin: hand-computed cases."""

from __future__ import annotations

import numpy as np
import pytest

from traffictwin.stereo.metrics import (
    ERROR_EDGES,
    RANGE_EDGES_M,
    add_counts,
    depth_error_counts,
    depth_error_summary,
    histogram_quantile,
    range_bin_names,
    relative_depth_error,
)

STEP = 0.0005  # ERROR_EDGES' step below 100 %


def test_relative_depth_error_per_pixel():
    gt = np.array([[10.0, 5.0, 2.0, 0.0, 4.0, 4.0]], np.float32)
    est = np.array([[8.0, 5.0, 4.0, 3.0, -1.0, 0.0]], np.float32)
    e = relative_depth_error(est, gt)
    # Z = fx·B / d: |Z - Z_gt| / Z_gt = |d_gt / d - 1|
    assert e[0, :3] == pytest.approx([10 / 8 - 1, 0.0, 0.5])
    assert np.isnan(e[0, 3]) and np.isnan(e[0, 4])  # no GT / no estimate
    assert np.isinf(e[0, 5])  # valid 0 px = infinitely far
    with pytest.raises(ValueError, match="shape"):
        relative_depth_error(est, gt[:, :3])


def _hand_case() -> tuple[np.ndarray, np.ndarray]:
    """fx·B = 40 px·m, so Z_gt = 40 / d_gt: 5 m, 10 m, 20 m, 20 m, 40 m, 160 m, no surface."""
    gt = np.array([[8.0, 4.0, 2.0, 2.0, 1.0, 0.25, 0.0]])
    est = np.array([[10.0, -1.0, 2.5, 1.0, 1.1, 0.25, 3.0]])
    return est, gt


def test_depth_error_counts_bins_by_gt_range():
    est, gt = _hand_case()
    c = depth_error_counts(est, gt, 40.0)
    # 0-10 m: the 5 m pixel; 10-30 m: 10 m ([lo, hi)), 20 m, 20 m; 30-90 m: 40 m; 160 m: outside
    assert c["n_gt"].tolist() == [1, 3, 1]
    assert c["n_valid"].tolist() == [1, 2, 1]  # the 10 m pixel has no estimate
    assert c["hist"].shape == (3, len(ERROR_EDGES)) and c["hist"].sum(axis=1).tolist() == [1, 2, 1]
    s = depth_error_summary(c)
    # 0-10 m: |8/10 - 1| = 0.2; 10-30 m: 0.2 and |2/1 - 1| = 1.0; 30-90 m: |1/1.1 - 1| = 1/11
    assert s["z0-10m_relerr_median"] == pytest.approx(0.2, abs=STEP)
    assert s["z10-30m_relerr_median"] == pytest.approx(0.2, abs=STEP)  # lower of two (inverted CDF)
    assert s["z10-30m_relerr_p90"] == pytest.approx(1.0, rel=0.01)
    assert s["z30-90m_relerr_median"] == pytest.approx(1 / 11, abs=STEP)
    assert s["z10-30m_valid_share"] == pytest.approx(2 / 3)
    assert s["z0-10m_valid_share"] == 1.0 and s["z10-30m_gt_pixels"] == 3
    # custom bins; a stack sums like separate calls
    c2 = depth_error_counts(est, gt, 40.0, [0.0, 25.0, 200.0])
    assert c2["n_gt"].tolist() == [4, 2] and c2["n_valid"].tolist() == [3, 2]
    two = depth_error_counts(np.stack([est, est]), np.stack([gt, gt]), 40.0)
    summed = add_counts(add_counts(None, c), c)
    assert all(np.array_equal(two[k], summed[k]) for k in summed)


def test_histogram_quantile_matches_the_inverted_cdf():
    rng = np.random.default_rng(0)
    vals = np.abs(rng.normal(0.0, 0.2, 5000))
    hist = np.bincount(
        np.searchsorted(ERROR_EDGES, vals, side="right") - 1, minlength=len(ERROR_EDGES)
    )
    for q in (0.1, 0.5, 0.9):
        exact = np.quantile(vals, q, method="inverted_cdf")
        assert histogram_quantile(hist, q) == pytest.approx(exact, abs=STEP)
    assert np.isnan(histogram_quantile(np.zeros(len(ERROR_EDGES)), 0.5))


def test_infinite_errors_land_in_the_open_bin():
    gt = np.full((1, 10), 4.0)
    est = np.full((1, 10), 4.0)
    est[0, :2] = 0.0  # 2 of 10 valid pixels at 0 px: Z = inf
    s = depth_error_summary(depth_error_counts(est, gt, 40.0))  # Z_gt = 10 m
    assert s["z10-30m_relerr_median"] == pytest.approx(0.0, abs=STEP)
    assert np.isinf(s["z10-30m_relerr_p90"])
    assert np.isnan(s["z0-10m_relerr_median"]) and np.isnan(s["z0-10m_valid_share"])


def test_range_bin_names_and_bad_bins():
    assert range_bin_names(RANGE_EDGES_M) == ["z0-10m", "z10-30m", "z30-90m"]
    assert range_bin_names([0.5, 2, 12.25]) == ["z0p5-2m", "z2-12p25m"]
    for bad in ([10.0], [0.0, 10.0, 5.0], [-1.0, 10.0]):
        with pytest.raises(ValueError, match="increasing distances"):
            depth_error_counts(np.ones((2, 2)), np.ones((2, 2)), 40.0, bad)
    with pytest.raises(ValueError, match="fx_b"):
        depth_error_counts(np.ones((2, 2)), np.ones((2, 2)), 0.0)
