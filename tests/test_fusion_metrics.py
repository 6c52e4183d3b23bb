"""Fusion metrics on hand cases: KLD definitions, confusion counts, P/R/Dice, AUROC, binning."""

from __future__ import annotations

import numpy as np
import pytest

from traffictwin.fusion.metrics import (
    UncertaintyAUROC,
    aggregate,
    auroc_from_hist,
    confusion_counts,
    kld_fo,
    kld_fou,
    per_sample_metrics,
    pose_error_bins,
)


def maps(cells: list[tuple[float, float]], n: int = 1) -> np.ndarray:
    """(n, 2, 1, len(cells)) masses from a list of (m_F, m_O)."""
    a = np.array(cells, dtype=np.float32).T[:, None, :]
    return np.repeat(a[None], n, axis=0)


def test_perfect_prediction_kld_zero_dice_one():
    rng = np.random.default_rng(0)
    d = rng.dirichlet([1, 1, 1], size=(3, 8, 5))
    label = np.moveaxis(d[..., :2], -1, 1)
    s = per_sample_metrics(label, label)
    np.testing.assert_allclose(s["kld_fo"], 0, atol=1e-12)
    np.testing.assert_allclose(s["kld_fou"], 0, atol=1e-12)
    hard = maps([(1, 0), (0, 1), (0.9, 0.05), (0.1, 0.8)], n=2)
    s = per_sample_metrics(hard, hard)
    np.testing.assert_allclose(s["dice_occ"], 1)
    np.testing.assert_allclose(s["dice_free"], 1)
    np.testing.assert_allclose(s["precision_occ"], 1)
    np.testing.assert_allclose(s["recall_free"], 1)


def test_kld_hand_values():
    label = maps([(1.0, 0.0)])
    pred = maps([(0.5, 0.25)])
    # (a): 1*log(1/0.5) + 1e-7*log(1e-7/0.25)
    a = np.log(2) + 1e-7 * np.log(1e-7 / 0.25)
    assert kld_fo(label, pred)[0] == pytest.approx(a, rel=1e-9)
    # (b): adds u: label u = 0 -> 1e-7, pred u = 0.25
    b = a + 1e-7 * np.log(1e-7 / 0.25)
    assert kld_fou(label, pred)[0] == pytest.approx(b, rel=1e-9)
    # mean over cells: second cell perfect
    label2 = maps([(1.0, 0.0), (0.2, 0.3)])
    pred2 = maps([(0.5, 0.25), (0.2, 0.3)])
    assert kld_fo(label2, pred2)[0] == pytest.approx(a / 2, rel=1e-6)


def test_known_confusion_precision_recall():
    # label: 4 occupied, 4 free, 2 unknown cells
    lab = [(0, 1)] * 4 + [(1, 0)] * 4 + [(0.2, 0.2), (0, 0)]
    # pred on occupied: 3 occupied, 1 fully unknown (p_O = 0.5, neither); on free: 1 occupied, 3 free; unknown cells: anything
    pred = [(0, 0.9)] * 3 + [(0, 0)] + [(0.1, 0.8)] + [(0.7, 0.1)] * 3 + [(0, 1), (1, 0)]
    c = confusion_counts(maps(lab), maps(pred))
    assert (c["tp_occ"][0], c["fp_occ"][0], c["fn_occ"][0]) == (3, 1, 1)
    assert (c["tp_free"][0], c["fp_free"][0], c["fn_free"][0]) == (3, 0, 1)
    assert c["n_known"][0] == 8
    s = per_sample_metrics(maps(lab), maps(pred))
    assert s["precision_occ"][0] == pytest.approx(0.75)
    assert s["recall_occ"][0] == pytest.approx(0.75)
    assert s["dice_occ"][0] == pytest.approx(6 / 8)
    assert s["precision_free"][0] == pytest.approx(1.0)
    assert s["recall_free"][0] == pytest.approx(0.75)
    assert s["dice_free"][0] == pytest.approx(6 / 7)
    assert s["u_mean"][0] == pytest.approx(np.mean([1 - a - b for a, b in pred]), rel=1e-6)


def test_undefined_scores_are_nan_and_aggregate_pools_counts():
    lab = maps([(1, 0), (1, 0)])
    pred = maps([(1, 0), (0, 1)])
    s = per_sample_metrics(lab, pred)
    assert np.isnan(s["recall_occ"][0])  # no occupied label cell
    assert s["precision_occ"][0] == 0.0
    # pooled: sample 1 has TP_occ = 1, FP = 0; sample 2 TP = 0, FP = 1, FN = 1
    lab2 = np.concatenate([maps([(0, 1), (1, 0)]), maps([(0, 1), (1, 0)])])
    pred2 = np.concatenate([maps([(0, 1), (1, 0)]), maps([(1, 0), (0, 1)])])
    agg = aggregate(per_sample_metrics(lab2, pred2))
    assert agg["n"] == 2
    assert agg["precision_occ"] == pytest.approx(0.5)
    assert agg["recall_occ"] == pytest.approx(0.5)
    assert agg["dice_occ_sample_mean"] == pytest.approx(0.5)


def test_auroc_hand_cases():
    assert auroc_from_hist([0, 0, 1], [1, 0, 0]) == 1.0
    assert auroc_from_hist([1, 0, 0], [0, 0, 1]) == 0.0
    assert auroc_from_hist([1, 1], [1, 1]) == pytest.approx(0.5)
    # pos scores {2, 3}, neg {1, 2}: pairs (2>1)=1, (2=2)=.5, (3>1)=1, (3>2)=1 -> 3.5/4
    assert auroc_from_hist([0, 0, 1, 1], [0, 1, 1, 0]) == pytest.approx(3.5 / 4)
    assert np.isnan(auroc_from_hist([0, 0], [1, 1]))


def test_uncertainty_auroc_flags_errors():
    lab = maps([(0, 1), (0, 1), (1, 0), (1, 0), (0, 0)])
    # right with low u, wrong with high u; the unknown label cell is ignored
    pred = maps([(0, 0.9), (0.3, 0.1), (0.95, 0.0), (0.2, 0.4), (0.5, 0.5)])
    a = UncertaintyAUROC(bins=100)
    a.update(lab, pred)
    assert (a.n_wrong, a.n_right) == (2, 2)
    assert a.value() == 1.0
    b = UncertaintyAUROC(bins=100)
    b.update(lab, maps([(0, 0.5), (0.8, 0.2), (0.5, 0.0), (0.1, 0.85), (0, 0)]))
    assert b.value() == 0.0


def test_pose_error_bins():
    noise = np.array(
        [[0.3, 0.4, np.radians(1)], [3, 4, np.radians(-12)], [0, 0, 0], [10, 0, np.radians(30)]]
    )
    tb, rb, tl, rl = pose_error_bins(noise, [0, 1, 5], [0, 5, 15])
    np.testing.assert_array_equal(tb, [0, 2, 0, 2])  # 0.5 m, 5 m (edge -> upper bin), 0, 10
    np.testing.assert_array_equal(rb, [0, 1, 0, 2])
    assert tl == ["0-1m", "1-5m", ">=5m"] and rl == ["0-5deg", "5-15deg", ">=15deg"]
    with pytest.raises(ValueError, match="trans_edges_m"):
        pose_error_bins(noise, [1, 2], [0, 1])


def test_shape_errors_name_the_argument():
    with pytest.raises(ValueError, match="pred"):
        kld_fo(np.zeros((2, 4, 4)), np.zeros((3, 4, 4)))
    with pytest.raises(ValueError, match="same shape"):
        kld_fo(np.zeros((2, 4, 4)), np.zeros((2, 4, 5)))
