"""Long-format tables for the DVC plots (stage ``plot_data``): one row per point and one column
that tells the series apart, so a Vega-Lite template (``.dvc/plots/``) colours by it. Pure
functions on DataFrames; the stage reads and writes the files (the ROC / precision-recall
tables: :func:`traffictwin.risk.charts.risk_curves`)."""

from __future__ import annotations

import re
from collections.abc import Mapping

import pandas as pd

LOSS_COLUMNS = {"train": "train/loss", "val": "val/loss"}
SCORE_COLUMN = re.compile(r"^(?P<method>.+)_(?P<metric>precision|recall|dice)_(?P<cls>occ|free)$")
CLASS_NAMES = {"occ": "occupied", "free": "free"}
METRIC_NAMES = {"precision": "precision", "recall": "recall", "dice": "Dice"}


def learning_curves(curves: Mapping[str, pd.DataFrame], x: str = "epoch") -> pd.DataFrame:
    """``model, <x>, split, loss`` for every model in ``curves`` (``{model name: table}``, each
    with the column ``x`` and at least one of ``train/loss`` / ``val/loss``); rows without a
    value of a split (validation logged less often) are left out of that split."""
    parts = []
    for name, df in curves.items():
        if x not in df.columns:
            raise ValueError(
                f"learning curve {name!r}: no column {x!r} (columns: {list(df.columns)})"
            )
        if not (cols := {c: split for split, c in LOSS_COLUMNS.items() if c in df.columns}):
            want = sorted(LOSS_COLUMNS.values())
            raise ValueError(f"learning curve {name!r}: none of the loss columns {want}")
        long = df[[x, *cols]].melt(id_vars=x, var_name="split", value_name="loss")
        long["split"] = long["split"].map(cols)
        long.insert(0, "model", name)
        parts.append(long.dropna(subset=["loss"]))
    if not parts:
        return pd.DataFrame(columns=["model", x, "split", "loss"])
    return pd.concat(parts, ignore_index=True)


def fusion_scores_long(wide: pd.DataFrame) -> pd.DataFrame:
    """``config, noise_r_m, noise_alpha_deg, method, class, metric, value`` from the wide
    per-configuration score table (``reports/plots/fusion_scores.csv``, columns
    ``<method>_<precision|recall|dice>_<occ|free>``); empty cells (a method not evaluated at a
    configuration) are left out."""
    ids = ["config", "noise_r_m", "noise_alpha_deg"]
    if missing := [c for c in ids if c not in wide.columns]:
        raise ValueError(f"fusion scores table: missing column(s) {missing}")
    if not (score_cols := [c for c in wide.columns if SCORE_COLUMN.match(c)]):
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
