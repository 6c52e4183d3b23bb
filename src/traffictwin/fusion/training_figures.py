"""Learning curves of one fusion or registration training run (matplotlib Agg; saved by the
train stages): :func:`learning_curves` (validation KLD(b), the selection metric, against the naive
fusion's; training / validation loss; validation occupied Dice; the best epoch marked) and
:func:`registration_learning_curves` (validation success rate, mean pose errors, losses). Nothing
here imports the fusion methods or the evaluation figures: those re-run no training stage.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from traffictwin.io.atomic import pyplot as _plt

# the training and validation loss per epoch: (History key, line style, legend label)
LOSS_LINES = (("train/loss", "o-", "train"), ("val/loss", "s-", "validation"))


def _series(rows: Sequence[Mapping[str, float]], key: str) -> tuple[np.ndarray, np.ndarray]:
    pts = [(r["epoch"], r[key]) for r in rows if r.get(key) is not None]
    e, v = np.array(pts, dtype=np.float64).reshape(-1, 2).T
    return e, v


def plot_series(ax, rows: Sequence[Mapping[str, float]], lines: Sequence[tuple[str, str, str]]):
    """One line per ``(key, style, label)`` of ``lines``: ``rows``' values of ``key`` per epoch."""
    for key, style, lab in lines:
        ek, vk = _series(rows, key)
        ax.plot(ek, vk, style, label=lab)


def three_panels(rows: Sequence[Mapping[str, float]], what: str):
    """A figure with three axes side by side for ``rows``; ``ValueError`` without epochs."""
    if not rows:
        raise ValueError(f"{what}: no epochs to plot")
    return _plt().subplots(1, 3, figsize=(13, 3.6))


def finish_figure(fig, axes, title: str):
    """Grid and legend on every axis of ``axes``, ``title`` over the figure; returns ``fig``."""
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def learning_curves(
    rows: Sequence[Mapping[str, float]], title: str, selection: str = "val/kld_full"
):
    """Figure of a run's per-epoch ``rows`` (the History callback's rows: ``epoch``, ``val/*``, ``train/loss``)."""
    fig, (ax1, ax2, ax3) = three_panels(rows, "learning_curves")
    e, v = _series(rows, selection)
    ax1.plot(e, v, "o-", color="#1f77b4", label="network")
    en, vn = _series(rows, f"{selection}_naive")
    ax1.plot(en, vn, "--", color="#d62728", label="naive (noisy pose + Dempster)")
    if len(v):
        b = int(np.argmin(v))
        ax1.plot([e[b]], [v[b]], "*", ms=14, color="#ff7f0e", label=f"best epoch {int(e[b])}")
    ax1.set(xlabel="epoch", ylabel="validation KLD(b) (nats per cell)", title="selection metric")
    plot_series(ax2, rows, LOSS_LINES)
    ax2.set(xlabel="epoch", ylabel="loss (per cell)", title="training loss")
    plot_series(
        ax3, rows, (("val/dice_occ", "o-", "network"), ("val/dice_occ_naive", "--", "naive"))
    )
    ax3.set(xlabel="epoch", ylabel="validation Dice, occupied (-)", title="occupied cells")
    return finish_figure(fig, (ax1, ax2, ax3), title)


def registration_learning_curves(rows: Sequence[Mapping[str, float]], title: str):
    """Figure of a registration run's per-epoch rows: validation success rate, mean pose errors
    (m, deg) and the training / validation loss; the best epoch (lowest val/loss) is marked."""
    fig, (ax1, ax2, ax3) = three_panels(rows, "registration_learning_curves")
    e, v = _series(rows, "val/success_rate")
    ax1.plot(e, 100 * v, "o-", label="validation")
    el, vl = _series(rows, "val/loss")
    if len(vl):
        b = int(np.argmin(vl))
        ax1.axvline(el[b], color="#ff7f0e", ls=":", label=f"best epoch {int(el[b])} (val loss)")
    ax1.set(
        xlabel="epoch", ylabel="success rate (%)", title="error < 0.5 m and < 1 deg", ylim=(0, 100)
    )
    pose = (
        ("val/trans_err_m", "o-", "translation (m)"),
        ("val/rot_err_deg", "s-", "rotation (deg)"),
    )
    plot_series(ax2, rows, pose)
    ax2.set(xlabel="epoch", ylabel="mean validation error (m | deg)", title="pose error")
    plot_series(ax3, rows, LOSS_LINES)
    ax3.set(xlabel="epoch", ylabel="loss (-)", title="training loss")
    return finish_figure(fig, (ax1, ax2, ax3), title)
