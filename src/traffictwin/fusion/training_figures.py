"""Learning curves of one fusion or registration training run (drawn by plot_data from its
reports/plots CSV, with the kit of :mod:`traffictwin.report.curve_figures`): :func:`learning_curves`
(validation KLD(b), the selection metric, against the naive fusion's; training / validation loss;
validation occupied Dice; the best epoch marked) and :func:`registration_learning_curves`
(validation success rate, mean pose errors, losses)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from traffictwin.report.curve_figures import (
    LOSS_LINES,
    finish_figure,
    mark_best,
    per_epoch,
    plot_series,
    three_panels,
)


def learning_curves(rows: Sequence[Mapping[str, float]], title: str):
    """Figure of a run's per-epoch ``rows`` (the History callback's rows: ``epoch``, ``val/*``, ``train/loss``)."""
    fig, (ax1, ax2, ax3) = three_panels(rows, "learning_curves")
    e, v = per_epoch(rows, "val/kld_full")
    ax1.plot(e, v, "o-", color="#1f77b4", label="network")
    naive = per_epoch(rows, "val/kld_full_naive")
    ax1.plot(*naive, "--", color="#d62728", label="naive (noisy pose + Dempster)")
    if len(v):
        b = int(np.argmin(v))
        ax1.plot([e[b]], [v[b]], "*", ms=14, color="#ff7f0e", label=f"best epoch {int(e[b])}")
    ax1.set(ylabel="validation KLD(b) (nats per cell)", title="selection metric")
    plot_series(ax2, rows, LOSS_LINES)
    ax2.set(ylabel="loss (per cell)", title="training loss")
    plot_series(
        ax3, rows, (("val/dice_occ", "o-", "network"), ("val/dice_occ_naive", "--", "naive"))
    )
    ax3.set(ylabel="validation Dice, occupied (-)", title="occupied cells")
    return finish_figure(fig, title)


def registration_learning_curves(rows: Sequence[Mapping[str, float]], title: str):
    """Figure of a registration run's per-epoch rows: validation success rate, mean pose errors
    (m, deg) and the training / validation loss; the best epoch (lowest val/loss) is marked."""
    fig, (ax1, ax2, ax3) = three_panels(rows, "registration_learning_curves")
    plot_series(ax1, rows, (("val/success_rate", "o-", "validation"),), scale=100)
    mark_best(ax1, *per_epoch(rows, "val/loss"), " (val loss)")
    ax1.set(ylabel="success rate (%)", title="error < 0.5 m and < 1 deg", ylim=(0, 100))
    pose = (
        ("val/trans_err_m", "o-", "translation (m)"),
        ("val/rot_err_deg", "s-", "rotation (deg)"),
    )
    plot_series(ax2, rows, pose)
    ax2.set(ylabel="mean validation error (m | deg)", title="pose error")
    plot_series(ax3, rows, LOSS_LINES)
    ax3.set(ylabel="loss (-)", title="training loss")
    return finish_figure(fig, title)
