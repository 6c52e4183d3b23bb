"""Point metrics of one predictor against one label column (Feth et al., sec. 4).

Risk scale (docs/design.md "Risk metric"; the conversions live in :mod:`traffictwin.risk.metric`):
``risk = min(1 / THW, 20) / 20``; no vehicle ahead or speed 0 → risk 0. A situation is *critical*
when THW < t (t: the primary of ``evaluation.risk.thresholds_s``, the paper's threshold), i.e. when
``risk > risk_threshold(t)`` (``min(1/t, 20) / 20``).

Reported per predictor against a label column: MSE and MAE of the normalised risk (the paper's
"testing average error" is the MSE), the THW error in seconds (risk → THW, both capped at
``thw_cap`` s so "no vehicle" is finite), and at each threshold the confusion matrix laid out as
the paper's Table 1 (rows predicted, columns actual), accuracy (the paper's and Wang & Kato's: :data:`PAPER`),
balanced accuracy, precision/recall/specificity/F1 of the critical class and ROC-AUC of the
predicted risk as a score for "critical". Recall (specificity) is undefined without actual
critical (uncritical) frames; precision is 0 without predicted critical frames.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from traffictwin import paper_numbers as _P
from traffictwin.risk.metric import primary, risk_threshold, risk_to_thw

#: the paper's figures (sec. 4, Table 1) and the related work's best accuracy, as fractions, from
#: :mod:`traffictwin.paper_numbers` (their one source)
PAPER = {
    "test/mse": _P.RISK["test_mse"].value,
    "accuracy": _P.RISK["accuracy"].value / 100,
    "wang_kato_accuracy": _P.RISK["wang_kato_accuracy"].value / 100,
    "threshold_s": _P.RISK["thw_threshold_s"].value,
    "confusion": {k: n.value for k, n in _P.RISK_CONFUSION.items()},
    "n_frames": _P.RISK["n_effective"].value,
}
#: metrics where lower is better (every other reported metric: higher is better)
LOWER_IS_BETTER = (
    "test/mse",
    "test/mae",
    "test/rmse",
    "test/thw_mae_s",
    "test/thw_mae_critical_s",
    "test/thw_median_error_critical_s",
)


def regression_metrics(
    y: np.ndarray, p: np.ndarray, thw_cap: float = 10.0, *, critical_s: float
) -> dict[str, float]:
    """``test/mse``, ``test/mae``, ``test/rmse`` (normalised risk) and THW errors in s (capped);
    the ``*_critical_s`` errors over the frames whose true THW is below ``critical_s`` (s)."""
    y, p = check_pair(y, p)
    e = p - y
    ty, tp = risk_to_thw(y, thw_cap), risk_to_thw(p, thw_cap)
    crit = y > risk_threshold(critical_s)
    return {
        "test/mse": float(np.mean(e**2)),
        "test/mae": float(np.mean(np.abs(e))),
        "test/rmse": float(np.sqrt(np.mean(e**2))),
        "test/thw_mae_s": float(np.mean(np.abs(tp - ty))),
        "test/thw_mae_critical_s": float(np.mean(np.abs(tp - ty)[crit]))
        if crit.any()
        else float("nan"),
        "test/thw_median_error_critical_s": float(np.median(np.abs(tp - ty)[crit]))
        if crit.any()
        else float("nan"),
        "test/n": int(len(y)),
    }


def classification_metrics(
    y: np.ndarray, p: np.ndarray, thw_s: float, cut: float | None = None
) -> dict[str, Any]:
    """Critical-vs-uncritical metrics at THW threshold ``thw_s``; the critical class is positive.
    A frame is predicted critical when ``p > cut`` (the predictor's decision threshold chosen on
    validation, :mod:`traffictwin.risk.selection`; default: the label's own ``risk_threshold``)."""
    y, p = check_pair(y, p)
    thr = risk_threshold(thw_s)
    cut = thr if cut is None else float(cut)
    a, b = y > thr, p > cut
    tp, fp = int(np.sum(a & b)), int(np.sum(~a & b))
    fn, tn = int(np.sum(a & ~b)), int(np.sum(~a & ~b))
    n = max(len(y), 1)
    nan = float("nan")
    prec = tp / (tp + fp) if tp + fp else 0.0
    rec = tp / (tp + fn) if tp + fn else nan  # undefined without actual critical frames
    spec = tn / (tn + fp) if tn + fp else nan
    f1 = nan if math.isnan(rec) else (2 * prec * rec / (prec + rec) if prec + rec else 0.0)
    if a.all() or not a.any():
        bal = float("nan")
        auc = float("nan")  # undefined with a single actual class
    else:
        bal = 0.5 * (rec + spec)
        auc = roc_auc(a, p)
    return {
        "threshold_s": float(thw_s),
        "risk_threshold": float(thr),
        "decision_cut": float(cut),
        "confusion": {"tp": tp, "fp": fp, "fn": fn, "tn": tn},
        "confusion_pct": {
            k: 100.0 * v / n for k, v in {"tp": tp, "fp": fp, "fn": fn, "tn": tn}.items()
        },
        "accuracy": (tp + tn) / n,
        "balanced_accuracy": bal,
        "precision": prec,
        "recall": rec,
        "specificity": spec,
        "f1": f1,
        "roc_auc": auc,
        "critical_fraction_true": float(np.mean(a)) if len(a) else float("nan"),
        "critical_fraction_pred": float(np.mean(b)) if len(b) else float("nan"),
    }


def roc_auc(positive: np.ndarray, score: np.ndarray) -> float:
    """Area under the ROC curve (ties count half; the Mann–Whitney U statistic), NaN for one class."""
    positive = np.asarray(positive, bool)
    score = np.asarray(score, np.float64)
    n_pos, n_neg = int(positive.sum()), int((~positive).sum())
    if n_pos == 0 or n_neg == 0:
        return float("nan")
    from scipy.stats import rankdata

    ranks = rankdata(score)  # average ranks for ties
    return float((ranks[positive].sum() - n_pos * (n_pos + 1) / 2) / (n_pos * n_neg))


def evaluate(
    y: np.ndarray,
    p: np.ndarray,
    thresholds_s: Sequence[float],
    thw_cap: float = 10.0,
    cuts: Mapping[float, float] | None = None,
) -> dict[str, Any]:
    """Regression metrics (the critical frames: THW below the primary threshold,
    ``thresholds_s[0]``) plus ``at_<t>s`` classification metrics for every threshold (decision
    cut ``cuts[t]`` where given)."""
    out: dict[str, Any] = regression_metrics(y, p, thw_cap, critical_s=primary(thresholds_s))
    for t in thresholds_s:
        out[f"at_{t:g}s"] = classification_metrics(y, p, t, (cuts or {}).get(t))
    return out


def confusion_labels(y: np.ndarray, p: np.ndarray, thw_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame class names (``critical``/``uncritical``) of actual and predicted risk."""
    thr = risk_threshold(thw_s)
    names = np.array(["uncritical", "critical"])
    return names[(np.asarray(y) > thr).astype(int)], names[(np.asarray(p) > thr).astype(int)]


def label_agreement(a: np.ndarray, b: np.ndarray, thresholds_s: Sequence[float]) -> dict[str, Any]:
    """How two label columns (e.g. paper vs camera_fov region) differ: MSE and class agreement."""
    a, b = check_pair(a, b)
    out: dict[str, Any] = {
        "mse": float(np.mean((a - b) ** 2)),
        "fraction_equal": float(np.mean(np.isclose(a, b))),
    }
    for t in thresholds_s:
        thr = risk_threshold(t)
        out[f"class_agreement_at_{t:g}s"] = float(np.mean((a > thr) == (b > thr)))
    return out


def check_pair(y: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Labels and predictions as flat float64 arrays of one length (errors: empty, non-finite)."""
    y = np.asarray(y, np.float64).ravel()
    p = np.asarray(p, np.float64).ravel()
    if y.shape != p.shape:
        raise ValueError(f"labels and predictions differ in length: {y.shape} vs {p.shape}")
    if len(y) == 0:
        raise ValueError("no frames to evaluate (empty test split after the ORB check?)")
    if not (np.all(np.isfinite(y)) and np.all(np.isfinite(p))):
        raise ValueError("labels/predictions contain non-finite values")
    return y, p


def summarise_paper_comparison(metrics: Mapping[str, Any], thw_s: float) -> dict[str, float]:
    """Differences to the paper for one predictor's metrics (positive = worse MSE / better accuracy;
    the accuracy at THW threshold ``thw_s`` (s), the primary)."""
    at = metrics.get(f"at_{thw_s:g}s", {})
    return {
        "mse_minus_paper": float(metrics["test/mse"]) - PAPER["test/mse"],
        "accuracy_minus_paper": float(at.get("accuracy", float("nan"))) - PAPER["accuracy"],
        "accuracy_minus_wang_kato": float(at.get("accuracy", float("nan")))
        - PAPER["wang_kato_accuracy"],
    }


def example_indices(y: np.ndarray, p: np.ndarray, thw_s: float) -> tuple[int, int]:
    """The paper's Fig. 7 frames: the best-predicted critical frame (the best frame when none is
    critical) and the worst-predicted frame (the second worst when that is the same frame)."""
    err = np.abs(p - y)
    crit = np.flatnonzero(y > risk_threshold(thw_s))
    good = int(crit[np.argmin(err[crit])]) if len(crit) else int(np.argmin(err))
    bad = (
        int(np.argsort(err)[-2])
        if int(np.argmax(err)) == good and len(err) > 1
        else int(np.argmax(err))
    )
    return good, bad


def confusion_table(frame_id: Any, y: np.ndarray, p: np.ndarray, thw_s: float) -> Any:
    """``frame_id``, ``actual``, ``predicted`` class per frame (the ``dvc plots`` confusion data)."""
    import pandas as pd

    actual, predicted = confusion_labels(y, p, thw_s)
    return pd.DataFrame({"frame_id": frame_id, "actual": actual, "predicted": predicted})
