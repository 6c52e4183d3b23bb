"""Long-format tables for the DVC plots (stage ``plot_data``): one row per point, one column that
tells the series apart (``model``, ``method``, ``predictor``), so a Vega-Lite template colours by
it (templates in ``.dvc/plots/``).

- :func:`learning_curves`: ``model, epoch, split, loss`` from the training-curve tables (one per
  model; the training and validation loss columns ``train/loss`` / ``val/loss``).
- :func:`fusion_scores_long`: ``config, noise_r_m, noise_alpha_deg, method, class, metric, value``
  from the wide per-configuration score table (columns ``<method>_<metric>_<occ|free>``).

The ROC / precision-recall tables of critical frames: :func:`traffictwin.risk.charts.risk_curves`.

Pure functions on DataFrames; the stage reads and writes the files.
"""

from __future__ import annotations

import re
from collections.abc import Mapping

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
