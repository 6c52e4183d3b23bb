"""The learning-curve kit of every trained network's figure (stage plot_data): per-epoch series
from a run's History rows, three panels side by side, the best epoch marked, one finish (x label
"epoch", grid, legend, title). Used by :mod:`traffictwin.stereo.figures` and
:mod:`traffictwin.fusion.training_figures`."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from traffictwin.io.atomic import pyplot as _plt

#: the training and validation loss per epoch: (row key, line style, legend label)
LOSS_LINES = (("train/loss", "o-", "train"), ("val/loss", "s-", "validation"))


def per_epoch(rows: Sequence[Mapping[str, float]], key: str) -> tuple[np.ndarray, np.ndarray]:
    """(epochs, values) of the rows that have ``key``."""
    pts = [(r["epoch"], r[key]) for r in rows if r.get(key) is not None]
    return tuple(np.array(pts, dtype=np.float64).reshape(-1, 2).T)


def plot_series(ax, rows: Sequence[Mapping[str, float]], lines, scale: float = 1.0):
    """One line per ``(key, style, label)`` of ``lines``: ``rows``' values of ``key`` (times
    ``scale``) per epoch; returns the last line's (epochs, values)."""
    for key, style, label in lines:
        e, v = per_epoch(rows, key)
        ax.plot(e, scale * v, style, label=label)
    return e, v


def mark_best(ax, e: np.ndarray, v: np.ndarray, note: str = "") -> None:
    """A dotted line at the epoch of the lowest ``v`` (none without values)."""
    if len(v):
        b = int(np.argmin(v))
        ax.axvline(e[b], color="#ff7f0e", ls=":", label=f"best epoch {int(e[b])}{note}")


def three_panels(rows: Sequence[Mapping[str, float]], what: str):
    """A figure with three axes side by side for ``rows``; ``ValueError`` without epochs."""
    if not rows:
        raise ValueError(f"{what}: no epochs to plot")
    return _plt().subplots(1, 3, figsize=(13, 3.6))


def finish_figure(fig, title: str):
    """x label "epoch", grid and legend on every axis, ``title`` over the figure; returns ``fig``."""
    for ax in fig.axes:
        ax.set_xlabel("epoch")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    return fig
