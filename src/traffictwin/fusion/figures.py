"""Figures of the fusion evaluation (paper Figs. 4–7), matplotlib Agg.

Each figure function returns the matplotlib ``Figure`` (so tests can check what it plots);
:func:`traffictwin.io.atomic.save_figure` writes it atomically as PNG and closes it.

- :func:`kld_boxplot` — KLD distribution per configuration, network vs baselines (Fig. 5);
- :func:`scores_plot` — precision / recall / Dice vs configuration for one class (Figs. 6, 7);

Maps (Fig. 4) are drawn by :mod:`traffictwin.fusion.map_figures` in the project's one mass colour
map (:mod:`traffictwin.report.colours`).

Legend labels are the methods' ``label`` in :data:`traffictwin.fusion.methods.METHODS` (a network
row ``<method>[<loss>]`` of ``fusion_variants``: the method's label + ``[<loss> loss]``); colours
and markers are :data:`METHOD_STYLE`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from traffictwin.io.atomic import pyplot as _plt

__all__ = [
    "CONFIG_AXIS",
    "CONFIG_NOTE",
    "config_label",
    "kld_boxplot",
    "scores_plot",
    "METHOD_STYLE",
]

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


def kld_boxplot(
    values: Mapping[str, Mapping[str, Sequence[float]]],
    configs: Sequence[str],
    methods: Sequence[str],
    ylabel: str = "KLD(label ‖ prediction)",
    title: str = "Fusion quality per configuration (test set)",
    noise: Mapping[str, Sequence[float]] | None = None,
    unit: str = "nats per cell",
):
    """Box plots: ``values[method][config]`` = per-sample KLDs; one group per configuration,
    one box per (configuration, method) with data, labelled ``gid = "<method>/<config>"`` (its
    median line ``"<method>/<config>/median"``); ``noise[config] = (r m, α deg)`` labels the
    configuration axis (:func:`config_label`).

    The y axis is logarithmic (matplotlib ``symlog``: KLD ≥ 0, exact zeros occur, e.g. the naive
    fusion without pose noise), linear only below a small threshold (:func:`_log_threshold`),
    so a row far above the others (a degenerate network at ~2 nats) no longer squashes the
    boxes near 0.01; the axis label names the quantity, its ``unit`` and the scale. Without
    any value the axes say so."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(1.9 * len(configs) + 2, 4.2))
    width = 0.8 / max(len(methods), 1)
    handles = []
    drawn: list[np.ndarray] = []
    for j, meth in enumerate(methods):
        data, pos, cfgs = [], [], []
        for i, cfg in enumerate(configs):
            v = np.asarray(values.get(meth, {}).get(cfg, []), dtype=float)
            v = v[np.isfinite(v)]
            if v.size:
                cfgs.append(cfg)
                data.append(v)
                pos.append(i + (j - (len(methods) - 1) / 2) * width)
        if not data:
            continue
        drawn += data
        handles.append(_method_boxes(ax, meth, data, pos, cfgs, width))
    ax.set_xticks(range(len(configs)))
    ax.set_xticklabels([config_label(c, noise) for c in configs])
    ax.set_xlabel(f"{CONFIG_AXIS}\n{CONFIG_NOTE}" if noise else "configuration")
    lin = _log_threshold(drawn)
    if lin is not None:
        ax.set_yscale("symlog", linthresh=lin, linscale=0.3)
        ax.set_ylim(bottom=0)
        ax.set_ylabel(f"{ylabel}\n({unit}; log scale, linear below {lin:g})")
    else:
        ax.set_ylabel(f"{ylabel} ({unit})")
    ax.set_title(title)
    ax.grid(axis="y", alpha=0.3)
    _box_legend(ax, handles)
    return fig


def _method_boxes(
    ax, meth: str, data: list[np.ndarray], pos: list[float], cfgs: list[str], width: float
):
    """One method's boxes at positions ``pos`` (one per configuration of ``cfgs`` with data),
    ``gid`` = ``"<method>/<config>"`` (median ``"…/median"``); returns the legend handle."""
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
    for med, cfg in zip(bp["medians"], cfgs):
        med.set_gid(f"{meth}/{cfg}/median")
    for b, cfg in zip(bp["boxes"], cfgs):
        b.set_gid(f"{meth}/{cfg}")
        b.set_facecolor(st["color"])
        b.set_alpha(0.6)
    handle = bp["boxes"][0]
    handle.set_label(st["label"])
    return handle


def _box_legend(ax, handles: list) -> None:
    """The methods' legend right of the axes, or a note that there was nothing to draw."""
    if handles:
        ax.legend(
            handles=handles,
            fontsize=8,
            loc="upper left",
            bbox_to_anchor=(1.01, 1.0),
            borderaxespad=0.0,
        )
    else:
        ax.text(
            0.5,
            0.5,
            "no KLD values to draw (no pair evaluated for these methods)",
            transform=ax.transAxes,
            ha="center",
            va="center",
            color="0.25",
            gid="empty",
        )


def scores_plot(
    scores: Mapping[str, Mapping[str, Mapping[str, float]]],
    configs: Sequence[str],
    methods: Sequence[str],
    cls: str,
    noise: Mapping[str, Sequence[float]] | None = None,
):
    """Precision / recall / Dice vs configuration for ``cls`` ("occ" or "free"); ``scores[method][config][metric]``.
    Three axes (precision, recall, Dice), one line per method (``gid`` = the method);
    ``noise[config] = (r m, α deg)`` labels the configuration axis (:func:`config_label`)."""
    plt = _plt()
    name = {"occ": "occupied", "free": "free"}.get(cls, cls)
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.8), sharey=True)
    x = np.arange(len(configs))
    for ax, metric in zip(axes, ("precision", "recall", "dice")):
        for meth in methods:
            y = [scores.get(meth, {}).get(c, {}).get(f"{metric}_{cls}", np.nan) for c in configs]
            st = _style(meth)
            ls = "-" if meth in ("dnn", "naive") else "--"
            ax.plot(x, y, ls, marker=st["marker"], color=st["color"], label=st["label"], gid=meth)
        ax.set_xticks(x)
        ax.set_xticklabels([config_label(c, noise) for c in configs])
        ax.set_xlabel(CONFIG_AXIS if noise else "configuration", fontsize=9)
        ax.set_title(f"{metric.capitalize()} ({name} cells)")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("score")
    axes[0].set_ylim(0, 1.02)
    axes[-1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0)
    head = f"Classification scores for {name} cells vs pose-noise configuration (test set)"
    fig.suptitle(f"{head}\n{CONFIG_NOTE}" if noise else head, fontsize=11 if noise else None)
    fig.tight_layout()
    return fig
