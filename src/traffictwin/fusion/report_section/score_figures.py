"""The report stage's own fusion score figures: precision / recall / Dice per configuration with
each panel's score axis zoomed to its data (the evaluation's figures span 0-1)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

SCORE_METRICS = ("precision", "recall", "Dice")


def zoomed_limits(
    values: np.ndarray, pad: float = 0.15, min_span: float = 0.01, top: float = 1.0
) -> tuple[float, float]:
    """y limits around the finite ``values``: their range widened by ``pad`` of itself on each
    side (at least ``min_span`` in all), never above ``top``; (0, top) without a finite value."""
    v = np.asarray(values, np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return 0.0, top
    lo, hi = float(v.min()), float(v.max())
    margin = max((hi - lo) * pad, (min_span - (hi - lo)) / 2, 0.0)
    upper = min(hi + margin, top)
    return min(lo - margin, upper - min_span), upper


def score_figure(
    scores: pd.DataFrame, configurations: Mapping[str, tuple[float, float]], cls: str
) -> Any:
    """Precision / recall / Dice of ``cls`` cells (``occupied`` / ``free``) per configuration
    (ticks: r and α), one line per method (:func:`traffictwin.fusion.figures.method_line`), each
    panel's y axis zoomed to its data (:func:`zoomed_limits`). ``scores``: the long table of
    :func:`traffictwin.report.plot_data.fusion_scores_long`. Returns the matplotlib figure."""
    from traffictwin.fusion.figures import CONFIG_NOTE, _plt, score_axes

    d = scores[scores["class"] == cls]
    cfgs = [c for c in configurations if c in set(d["config"])]
    fig, axes = _plt().subplots(1, 3, figsize=(13, 3.9))
    methods = sorted(set(d["method"]), key=lambda m: (m not in ("dnn", "naive"), m))
    for ax, metric in zip(axes, SCORE_METRICS):
        dm = d[(d["metric"] == metric) & d["config"].isin(cfgs)]
        by = {m: dm[dm["method"] == m] for m in methods}
        lines = [(m, g["config"].map(cfgs.index), g["value"]) for m, g in by.items() if len(g)]
        limits = zoomed_limits(dm["value"].to_numpy())
        score_axes(ax, lines, cfgs, configurations, ylim=limits, ylabel=f"{metric} ({cls} cells)")
    # every method once, in the order of first appearance
    legend = {lab: h for ax in axes for h, lab in zip(*ax.get_legend_handles_labels())}
    fig.legend(
        legend.values(), legend.keys(), fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 0.95)
    )
    head = f"Classification of {cls} cells vs pose-noise configuration (test split)"
    fig.suptitle(f"{head}\n{CONFIG_NOTE}", fontsize=11)
    fig.tight_layout()
    return fig


def draw_score_figures(
    wide_csv: Path, out_dir: Path, configurations: Mapping[str, tuple[float, float]]
) -> list[Path]:
    """The report stage's score figures: ``<out_dir>/fusion_scores_<occupied|free>_zoomed.png``
    from evaluate_fusion's wide table ``wide_csv`` (``reports/plots/fusion_scores.csv``); none
    when the table is absent (a partial pipeline)."""
    from traffictwin.io.atomic import save_figure
    from traffictwin.report.plot_data import fusion_scores_long

    if not Path(wide_csv).is_file():
        return []
    scores, out = fusion_scores_long(pd.read_csv(wide_csv)), Path(out_dir)
    return [
        save_figure(score_figure(scores, configurations, c), out / f"fusion_scores_{c}_zoomed.png")
        for c in ("occupied", "free")
    ]
