"""Figures of the fusion evaluation (paper Figs. 5–7), matplotlib Agg: :func:`kld_boxplot` (KLD
per configuration and method) and :func:`scores_plot` (precision / recall / Dice per
configuration); the maps (Fig. 4): :mod:`traffictwin.fusion.map_figures`. Each returns the
``Figure`` (tests check what it plots); :func:`traffictwin.io.atomic.save_figure` writes it.
Legend labels: the methods' ``label`` (:data:`traffictwin.fusion.methods.METHODS`; a network row
``<method>[<loss>]``: + ``[<loss> loss]``); colours and markers: :data:`METHOD_STYLE`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

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


def _label(row: str) -> str:
    """Legend label of a method or network row (``dnn[paper]`` → the dnn label + ``[paper loss]``)."""
    from traffictwin.fusion.methods import METHODS

    base, _, loss = row.partition("[")
    if base not in METHODS:
        return row
    return METHODS[base].label + (f" [{loss.rstrip(']')} loss]" if loss else "")


def _style(method: str) -> dict:
    return {
        "color": "#000000",
        "marker": "o",
        **METHOD_STYLE.get(method, {}),
        "label": _label(method),
    }


#: the configuration axis in plain words (the tick labels carry each configuration's r and α) ...
CONFIG_AXIS = "configuration (pose error bounds r, α)"
#: ... and what the bounds mean (docs/design.md "Pose noise": per axis, 98 % two-sided intervals)
CONFIG_NOTE = (
    "pose error bounds, per axis: 98 % of the noisy poses are off by less than r (m) in x, "
    "r in y and α (°) in heading"
)


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
    ax.set_xticks(range(len(configs)))
    ax.set_xticklabels([config_label(c, noise) for c in configs])
    ax.set_xlabel(xlabel, **kw)


def method_line(ax, x, y, meth: str) -> None:
    """``meth``'s line in its :data:`METHOD_STYLE` (solid for network and naive), ``gid`` = it."""
    st = _style(meth)
    ls = "-" if meth in ("dnn", "naive") else "--"
    ax.plot(x, y, ls, marker=st["marker"], color=st["color"], label=st["label"], gid=meth)


def kld_boxplot(
    values: Mapping[str, Mapping[str, Sequence[float]]],
    configs: Sequence[str],
    methods: Sequence[str],
    ylabel: str = "KLD(label ‖ prediction)",
    title: str = "Fusion quality per configuration (test set)",
    noise: Mapping[str, Sequence[float]] | None = None,
    unit: str = "nats per cell",
):
    """Box plots of ``values[method][config]`` (per-sample KLDs): one group per configuration,
    one box per (configuration, method) with data, ``gid = "<method>/<config>"`` (its median line
    ``"<method>/<config>/median"``); ``noise[config] = (r m, α deg)`` labels the configuration
    axis. The y axis is ``symlog`` (KLD ≥ 0 with exact zeros, linear below
    :func:`_log_threshold`), so a degenerate row at ~2 nats does not squash the boxes near 0.01;
    its label names the quantity, ``unit`` and scale. Without any value the axes say so."""
    fig, ax = _plt().subplots(figsize=(1.9 * len(configs) + 2, 4.2))
    width = 0.8 / max(len(methods), 1)
    handles, drawn = [], []
    for j, meth in enumerate(methods):
        got = {c: np.asarray(values.get(meth, {}).get(c, []), dtype=float) for c in configs}
        got = {c: v[np.isfinite(v)] for c, v in got.items()}
        cfgs = [c for c in configs if got[c].size]
        if not cfgs:
            continue
        pos = [configs.index(c) + (j - (len(methods) - 1) / 2) * width for c in cfgs]
        drawn += [got[c] for c in cfgs]
        handles.append(_method_boxes(ax, meth, [got[c] for c in cfgs], pos, cfgs, width))
    config_axis(ax, configs, noise, f"{CONFIG_AXIS}\n{CONFIG_NOTE}" if noise else "configuration")
    lin = _log_threshold(drawn)
    if lin is not None:
        ax.set_yscale("symlog", linthresh=lin, linscale=0.3)
        ax.set_ylim(bottom=0)
        ax.set_ylabel(f"{ylabel}\n({unit}; log scale, linear below {lin:g})")
    else:
        ax.set_ylabel(f"{ylabel} ({unit})")
    ax.set_title(title)
    ax.grid(axis="y", alpha=0.3)
    if handles:
        ax.legend(
            handles=handles,
            fontsize=8,
            loc="upper left",
            bbox_to_anchor=(1.01, 1.0),
            borderaxespad=0.0,
        )
    else:
        empty = "no KLD values to draw (no pair evaluated for these methods)"
        ax.text(
            0.5,
            0.5,
            empty,
            transform=ax.transAxes,
            ha="center",
            va="center",
            color="0.25",
            gid="empty",
        )
    return fig


def _method_boxes(ax, meth: str, data: list, pos: list[float], cfgs: list[str], width: float):
    """One method's boxes at ``pos`` (one per configuration of ``cfgs``), ``gid`` as in
    :func:`kld_boxplot`; returns the legend handle."""
    st = _style(meth)
    bp = ax.boxplot(
        data,
        positions=pos,
        widths=width * 0.85,
        patch_artist=True,
        showfliers=True,
        flierprops={"markersize": 2, "markeredgecolor": st["color"]},
        medianprops={"color": "black"},
    )
    for med, box, cfg in zip(bp["medians"], bp["boxes"], cfgs):
        med.set_gid(f"{meth}/{cfg}/median")
        box.set(gid=f"{meth}/{cfg}", facecolor=st["color"], alpha=0.6)
    bp["boxes"][0].set_label(st["label"])
    return bp["boxes"][0]


def scores_plot(
    scores: Mapping[str, Mapping[str, Mapping[str, float]]],
    configs: Sequence[str],
    methods: Sequence[str],
    cls: str,
    noise: Mapping[str, Sequence[float]] | None = None,
):
    """Precision / recall / Dice (``scores[method][config][<metric>_<cls>]``, ``cls`` "occ" or
    "free") per configuration: three axes, one line per method (``gid`` = the method)."""
    name = {"occ": "occupied", "free": "free"}.get(cls, cls)
    fig, axes = _plt().subplots(1, 3, figsize=(12, 3.8), sharey=True)
    for ax, metric in zip(axes, ("precision", "recall", "dice")):
        for meth in methods:
            y = [scores.get(meth, {}).get(c, {}).get(f"{metric}_{cls}", np.nan) for c in configs]
            method_line(ax, np.arange(len(configs)), y, meth)
        config_axis(ax, configs, noise, CONFIG_AXIS if noise else "configuration", fontsize=9)
        ax.set_title(f"{metric.capitalize()} ({name} cells)")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("score")
    axes[0].set_ylim(0, 1.02)
    axes[-1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0)
    head = f"Classification scores for {name} cells vs pose-noise configuration (test set)"
    fig.suptitle(f"{head}\n{CONFIG_NOTE}" if noise else head, fontsize=11 if noise else None)
    fig.tight_layout()
    return fig
