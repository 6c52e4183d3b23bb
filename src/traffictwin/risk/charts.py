"""Risk charts for the DVC plots (stage ``plot_data``): ROC and precision-recall curves of
critical frames, one per predictor, in long format (:mod:`traffictwin.report.plot_data`)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from traffictwin.report.plot_data import drop_collinear, precision_recall_curve
from traffictwin.risk.evaluation import roc_auc, roc_curve


def risk_curves(
    predictions: pd.DataFrame, label: str, risk_threshold: float, prefix: str = "pred_"
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """ROC and precision-recall tables of critical frames (``label > risk_threshold``), one curve
    per column ``<prefix><name>`` of ``predictions`` (the predictor ``<name> (AUC x.xxx)``).

    ``rank`` orders the points along a curve; points inside a horizontal or vertical run are
    left out (:func:`~traffictwin.report.plot_data.drop_collinear`: the same line). Rows with a missing label or prediction are left
    out of that predictor's curve."""
    if label not in predictions.columns:
        raise ValueError(f"risk predictions: no label column {label!r}")
    pred_cols = [c for c in predictions.columns if c.startswith(prefix)]
    if not pred_cols:
        raise ValueError(f"risk predictions: no prediction column {prefix}*")
    rocs, prs = [], []
    y = predictions[label].to_numpy(np.float64)
    for c in pred_cols:
        p = predictions[c].to_numpy(np.float64)
        ok = np.isfinite(y) & np.isfinite(p)
        positive = y[ok] > risk_threshold
        fpr, tpr = roc_curve(positive, p[ok])
        if fpr.size == 0:
            continue
        name = f"{c[len(prefix) :]} (AUC {roc_auc(positive, p[ok]):.3f})"
        k = drop_collinear(fpr, tpr)  # the same curve with its corner points only
        rocs.append(
            pd.DataFrame(
                {"predictor": name, "rank": np.arange(fpr.size)[k], "fpr": fpr[k], "tpr": tpr[k]}
            )
        )
        rec, prec = precision_recall_curve(positive, p[ok])
        k = drop_collinear(rec, prec)
        prs.append(
            pd.DataFrame(
                {
                    "predictor": name,
                    "rank": np.arange(rec.size)[k],
                    "recall": rec[k],
                    "precision": prec[k],
                }
            )
        )
    roc = (
        pd.concat(rocs, ignore_index=True)
        if rocs
        else pd.DataFrame(columns=["predictor", "rank", "fpr", "tpr"])
    )
    pr = (
        pd.concat(prs, ignore_index=True)
        if prs
        else pd.DataFrame(columns=["predictor", "rank", "recall", "precision"])
    )
    return roc, pr
