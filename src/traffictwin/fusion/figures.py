"""Figures of the fusion evaluation (paper Figs. 5–7), matplotlib Agg: :func:`kld_boxplot` (KLD
per configuration and method) and :func:`score_figure` (precision / recall / Dice per
configuration, each panel's score axis zoomed to its data); the maps (Fig. 4): :mod:`traffictwin.fusion.map_figures`. Each returns the
``Figure`` (tests check what it plots); :func:`traffictwin.io.atomic.save_figure` writes it.
Legend labels: the methods' ``label`` (:data:`traffictwin.fusion.methods.METHODS`; a network row
``<method>[<loss>]``: + ``[<loss> loss]``); colours and markers: :data:`METHOD_STYLE`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd

from traffictwin.io.atomic import pyplot as _plt

METHOD_STYLE: dict[str, dict] = {
    "dnn": {"color": "#1f77b4", "marker": "o"},
    "naive": {"color": "#d62728", "marker": "s"},
    "registered": {"color": "#2ca02c", "marker": "^"},
    "naive-yager": {"color": "#ff7f0e", "marker": "v"},
    "naive-cautious": {"color": "#9467bd", "marker": "D"},
    "ego": {"color": "#7f7f7f", "marker": "x"},
    "registered+network": {"color": "#8c564b", "marker": "P"},
    "dnn[paper]": {"color": "#17becf", "marker": "<"},
    "dnn[paper_kl]": {"color": "#bcbd22", "marker": ">"},
    "dnn[mass]": {"color": "#e377c2", "marker": "*"},
    "learned": {"color": "#393b79", "marker": "h"},
    "learned+network": {"color": "#637939", "marker": "X"},
    "learned-refined": {"color": "#5254a3", "marker": "H"},
    "learned-refined+network": {"color": "#8ca252", "marker": "p"},
}


def config_label(name: str, noise: Mapping[str, Sequence[float]] | None = None) -> str:
    """Tick label of configuration ``name`` with its pose noise ``noise[name] = (r m, α deg)``
    (the 98 % intervals of the translation per axis and of the heading): ``"D\nr 5 m\nα 20°"``;
    just ``name`` without ``noise``."""
    if not noise or name not in noise:
        return name
    r, alpha = noise[name]
    return f"{name}\nr {r:g} m\nα {alpha:g}°"


def _style(method: str) -> dict:
    """Colour, marker and legend label of a method or network row (``dnn[paper]``: the dnn label
    + `` [paper loss]``)."""
    from traffictwin.fusion.methods import METHODS

    base, _, loss = method.partition("[")
    style = {"color": "#000000", "marker": "o", **METHOD_STYLE.get(method, {}), "label": method}
    if base in METHODS:
        style["label"] = METHODS[base].label + (f" [{loss.rstrip(']')} loss]" if loss else "")
    return style


#: the configuration axis in plain words (the tick labels carry each configuration's r and α) ...
CONFIG_AXIS = "configuration (pose error bounds r, α)"
#: ... and what the bounds mean (docs/design.md "Pose noise": per axis, 98 % two-sided intervals)
CONFIG_NOTE = (
    "pose error bounds, per axis: 98 % of the noisy poses are off by less than r (m) in x, "
    "r in y and α (°) in heading"
)


#: what an empty KLD box plot says, and how (centred, grey, ``gid`` "empty")
EMPTY_BOX = "no KLD values to draw (no pair evaluated for these methods)"
EMPTY_NOTE = {"ha": "center", "va": "center", "color": "0.25", "gid": "empty"}


def _log_threshold(data: Sequence[np.ndarray]) -> float | None:
    """Where a symmetric-log KLD axis turns linear: the power of ten at or below the 5 % quantile
    of the positive values (within [1e-6, 1e-3]); ``None`` without a positive value."""
    v = np.concatenate([np.asarray(d, float).ravel() for d in data]) if data else np.zeros(0)
    v = v[np.isfinite(v) & (v > 0)]
    if v.size == 0:
        return None
    return float(np.clip(10.0 ** np.floor(np.log10(np.quantile(v, 0.05))), 1e-6, 1e-3))


def config_axis(ax, configs: Sequence[str], noise, xlabel: str, **kw) -> None:
    """x ticks at 0, 1, ... labelled by :func:`config_label`, and the axis label ``xlabel``."""
    ax.set_xticks(range(len(configs)), [config_label(c, noise) for c in configs])
    ax.set_xlabel(xlabel, **kw)


def method_line(ax, x, y, meth: str) -> None:
    """``meth``'s line in its :data:`METHOD_STYLE` (solid for network and naive), ``gid`` = it."""
    ax.plot(x, y, "-" if meth in ("dnn", "naive") else "--", **_style(meth), gid=meth)


def score_axes(ax, lines, configs: Sequence[str], noise, **props) -> None:
    """A score panel: one :func:`method_line` per ``(method, x, y)`` of ``lines``, the
    configuration axis (:func:`config_axis`), ``ax.set(**props)`` and a grid."""
    for meth, x, y in lines:
        method_line(ax, x, y, meth)
    config_axis(ax, configs, noise, CONFIG_AXIS if noise else "configuration", fontsize=9)
    ax.set(**props)
    ax.grid(alpha=0.3)


def kld_boxplot(
    values: Mapping[str, Mapping[str, Sequence[float]]],
    configs: Sequence[str],
    methods: Sequence[str],
    ylabel: str = "KLD(label ‖ prediction)",
    title: str = "Fusion quality per configuration (test set)",
    noise: Mapping[str, Sequence[float]] | None = None,
):
    """Box plots of ``values[method][config]`` (per-sample KLDs): one group per configuration,
    one box per (configuration, method) with data, ``gid = "<method>/<config>"`` (its median line
    ``"<method>/<config>/median"``); ``noise[config] = (r m, α deg)`` labels the configuration
    axis. The y axis is ``symlog`` (KLD ≥ 0 with exact zeros, linear below
    :func:`_log_threshold`), so a degenerate row at ~2 nats does not squash the boxes near 0.01;
    its label names the quantity, unit and scale. Without any value the axes say so."""
    fig, ax = _plt().subplots(figsize=(1.9 * len(configs) + 2, 4.2))
    width = 0.8 / max(len(methods), 1)
    drawn = []
    for j, meth in enumerate(methods):
        got = {c: np.asarray(values.get(meth, {}).get(c, []), dtype=float) for c in configs}
        got = {c: v[np.isfinite(v)] for c, v in got.items() if np.isfinite(v).any()}
        if not got:
            continue
        st = _style(meth)
        bp = ax.boxplot(
            list(got.values()),
            positions=[configs.index(c) + (j - (len(methods) - 1) / 2) * width for c in got],
            widths=width * 0.85,
            patch_artist=True,
            flierprops={"markersize": 2, "markeredgecolor": st["color"]},
            medianprops={"color": "black"},
        )
        for med, box, cfg in zip(bp["medians"], bp["boxes"], got):
            med.set_gid(f"{meth}/{cfg}/median")
            box.set(gid=f"{meth}/{cfg}", facecolor=st["color"], alpha=0.6)
        bp["boxes"][0].set_label(st["label"])  # the legend's one entry per method
        drawn += got.values()
    config_axis(ax, configs, noise, f"{CONFIG_AXIS}\n{CONFIG_NOTE}" if noise else "configuration")
    if lin := _log_threshold(drawn):
        ax.set_yscale("symlog", linthresh=lin, linscale=0.3)
        ax.set_ylim(bottom=0)
    unit = f"\n(nats per cell; log scale, linear below {lin:g})" if lin else " (nats per cell)"
    ax.set(ylabel=f"{ylabel}{unit}", title=title)
    ax.grid(axis="y", alpha=0.3)
    if drawn:
        ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    else:
        ax.text(0.5, 0.5, EMPTY_BOX, transform=ax.transAxes, **EMPTY_NOTE)
    return fig


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
    (ticks: r and α), one line per method (:func:`method_line`), each
    panel's y axis zoomed to its data (:func:`zoomed_limits`). ``scores``: the long table of
    :func:`traffictwin.report.plot_data.fusion_scores_long`. Returns the matplotlib figure."""
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
