"""ROC and precision-recall curves of critical frames (scikit-learn's curves, corner points only:
``drop_intermediate``), the one builder of their points for the figures
(:func:`traffictwin.risk.figures.plot_roc`) and the DVC plots (stage ``plot_data``:
:func:`risk_curves`). The AUC in a predictor's name is the metrics'
:func:`~traffictwin.risk.evaluation.roc_auc`, the trapezoid area under its ROC points."""

from __future__ import annotations

import numpy as np
import pandas as pd

from traffictwin.risk.evaluation.scoring import roc_auc

ROC_COLUMNS = ["predictor", "rank", "fpr", "tpr"]
PR_COLUMNS = ["predictor", "rank", "recall", "precision"]


def _finite(positive: np.ndarray, score: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pos = np.asarray(positive, bool).ravel()
    s = np.asarray(score, np.float64).ravel()
    if pos.shape != s.shape:
        raise ValueError(f"positive {pos.shape} and score {s.shape} must have the same length")
    ok = np.isfinite(s)
    return pos[ok], s[ok]


def roc_points(positive: np.ndarray, score: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """ROC points ``(fpr, tpr)`` of ``score`` as a detector of ``positive`` frames, from (0, 0)
    to (1, 1); frames with a non-finite score left out. Empty without both classes."""
    from sklearn.metrics import roc_curve

    pos, s = _finite(positive, score)
    if pos.all() or not pos.any():
        return np.zeros(0), np.zeros(0)
    return roc_curve(pos, s, drop_intermediate=True)[:2]


def pr_points(positive: np.ndarray, score: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Precision-recall points ``(recall, precision)`` of ``score >=`` each threshold, recall
    rising from scikit-learn's start (0, 1); frames with a non-finite score left out. Empty
    without a positive frame."""
    from sklearn.metrics import precision_recall_curve

    pos, s = _finite(positive, score)
    if not pos.any():
        return np.zeros(0), np.zeros(0)
    precision, recall, _ = precision_recall_curve(pos, s, drop_intermediate=True)
    return recall[::-1], precision[::-1]


def risk_curves(
    predictions: pd.DataFrame, label: str, risk_threshold: float, prefix: str = "pred_"
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """ROC and precision-recall tables (:data:`ROC_COLUMNS`, :data:`PR_COLUMNS`; ``rank`` orders
    the points along a curve: the ``.dvc/plots`` templates draw by it) of critical frames
    (``label > risk_threshold``), one curve per column ``<prefix><name>`` of ``predictions``
    (the predictor ``<name> (AUC x.xxx)``). Rows with a missing label or prediction are left out
    of that predictor's curves; a predictor whose ROC is undefined (one class only) has none."""
    if label not in predictions.columns:
        raise ValueError(f"risk predictions: no label column {label!r}")
    pred_cols = [c for c in predictions.columns if c.startswith(prefix)]
    if not pred_cols:
        raise ValueError(f"risk predictions: no prediction column {prefix}*")
    roc, pr = [], []  # rows
    y = predictions[label].to_numpy(np.float64)
    for c in pred_cols:
        p = predictions[c].to_numpy(np.float64)
        ok = np.isfinite(y) & np.isfinite(p)
        positive, p = y[ok] > risk_threshold, p[ok]
        fpr, tpr = roc_points(positive, p)
        if fpr.size == 0:
            continue
        name = f"{c[len(prefix) :]} (AUC {roc_auc(positive, p):.3f})"
        for rows, (a, b) in ((roc, (fpr, tpr)), (pr, pr_points(positive, p))):
            rows.extend((name, rank, *ab) for rank, ab in enumerate(zip(a, b)))
    return pd.DataFrame(roc, columns=ROC_COLUMNS), pd.DataFrame(pr, columns=PR_COLUMNS)
