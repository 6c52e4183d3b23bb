"""Long-format tables for the DVC plots (stage ``plot_data``): one row per point, one column that
tells the series apart (``model``, ``method``, ``predictor``), so a Vega-Lite template colours by
it (templates in ``.dvc/plots/``).

- :func:`learning_curves`: ``model, epoch, split, loss`` from the training-curve tables (one per
  model; the training and validation loss columns ``train/loss`` / ``val/loss``).
- :func:`fusion_scores_long`: ``config, noise_r_m, noise_alpha_deg, method, class, metric, value``
  from the wide per-configuration score table (columns ``<method>_<metric>_<occ|free>``).
- :func:`precision_recall_curve`: the points of a precision-recall curve (the risk section's
  ``risk_curves`` builds the ROC / PR tables of critical frames with it).

Pure functions on DataFrames; the stage reads and writes the files.
"""

from __future__ import annotations

import re
from collections.abc import Mapping

import numpy as np
import pandas as pd

LOSS_COLUMNS = {"train": "train/loss", "val": "val/loss"}
SCORE_COLUMN = re.compile(r"^(?P<method>.+)_(?P<metric>precision|recall|dice)_(?P<cls>occ|free)$")
CLASS_NAMES = {"occ": "occupied", "free": "free"}
METRIC_NAMES = {"precision": "precision", "recall": "recall", "dice": "Dice"}


def learning_curves(curves: Mapping[str, pd.DataFrame], x: str = "epoch") -> pd.DataFrame:
    """``model, <x>, split, loss`` for every model in ``curves`` (``{model name: table}``).

    Each table needs the column ``x`` and at least one of ``train/loss`` / ``val/loss``; rows
    without a value of a split (validation logged less often) are left out of that split."""
    parts = []
    for name, df in curves.items():
        if x not in df.columns:
            raise ValueError(
                f"learning curve {name!r}: no column {x!r} (columns: {list(df.columns)})"
            )
        cols = {split: c for split, c in LOSS_COLUMNS.items() if c in df.columns}
        if not cols:
            raise ValueError(
                f"learning curve {name!r}: none of the loss columns {sorted(LOSS_COLUMNS.values())}"
            )
        long = df[[x, *cols.values()]].melt(id_vars=x, var_name="split", value_name="loss")
        long["split"] = long["split"].map({c: s for s, c in cols.items()})
        long.insert(0, "model", name)
        parts.append(long.dropna(subset=["loss"]))
    if not parts:
        return pd.DataFrame(columns=["model", x, "split", "loss"])
    return pd.concat(parts, ignore_index=True)


def fusion_scores_long(wide: pd.DataFrame) -> pd.DataFrame:
    """``config, noise_r_m, noise_alpha_deg, method, class, metric, value`` from the wide table
    (``reports/plots/fusion_scores.csv``); methods not evaluated at a configuration (empty cells)
    are left out. ``class``: ``occupied`` / ``free``; ``metric``: precision, recall, Dice."""
    ids = ["config", "noise_r_m", "noise_alpha_deg"]
    missing = [c for c in ids if c not in wide.columns]
    if missing:
        raise ValueError(f"fusion scores table: missing column(s) {missing}")
    score_cols = [c for c in wide.columns if SCORE_COLUMN.match(c)]
    if not score_cols:
        raise ValueError(
            "fusion scores table: no <method>_<precision|recall|dice>_<occ|free> column"
        )
    long = wide[ids + score_cols].melt(id_vars=ids, var_name="column", value_name="value")
    parts = long["column"].str.extract(SCORE_COLUMN)
    long["method"] = parts["method"]
    long["class"] = parts["cls"].map(CLASS_NAMES)
    long["metric"] = parts["metric"].map(METRIC_NAMES)
    long = long.dropna(subset=["value"])
    return long[[*ids, "method", "class", "metric", "value"]].reset_index(drop=True)


def precision_recall_curve(
    positive: np.ndarray, score: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``(recall, precision)`` flagging the frames with score >= each distinct score, highest
    first (recall rising from the first threshold to 1). Empty arrays without a positive frame."""
    pos = np.asarray(positive, bool).ravel()
    s = np.asarray(score, np.float64).ravel()
    n_pos = int(pos.sum())
    if n_pos == 0 or s.size == 0:
        return np.zeros(0), np.zeros(0)
    order = np.argsort(-s, kind="stable")
    s, pos = s[order], pos[order]
    last = np.r_[np.flatnonzero(np.diff(s)), s.size - 1]
    tps = np.cumsum(pos)[last]
    flagged = last + 1.0
    return tps / n_pos, tps / flagged


def drop_collinear(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Mask of the points of the polyline ``(x, y)`` to keep: every point but those inside a
    horizontal or vertical run (same x or same y as both neighbours), so the drawn line is the same
    with far fewer points (ROC / PR curves step in x or in y)."""
    x, y = np.asarray(x), np.asarray(y)
    keep = np.ones(x.size, bool)
    if x.size > 2:
        inner_x = (x[1:-1] == x[:-2]) & (x[1:-1] == x[2:])
        inner_y = (y[1:-1] == y[:-2]) & (y[1:-1] == y[2:])
        keep[1:-1] = ~(inner_x | inner_y)
    return keep
