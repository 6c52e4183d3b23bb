"""Figures of the learned stereo network: learning curves (drawn with
:mod:`traffictwin.report.curve_figures`) and test-frame examples."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from traffictwin.io.atomic import pyplot as _plt
from traffictwin.report.curve_figures import (
    LOSS_LINES,
    finish_figure,
    mark_best,
    plot_series,
    three_panels,
)


def learning_curves(rows: Sequence[Mapping[str, float]], title: str):
    """Per-epoch validation EPE (px) and bad-1 (%), and the training / validation loss; the best
    epoch (lowest val/epe) is marked."""
    fig, (ax1, ax2, ax3) = three_panels(rows, "learning_curves")
    mark_best(ax1, *plot_series(ax1, rows, (("val/epe", "o-", "validation"),)))
    ax1.set(ylabel="end-point error (px)", title="validation EPE")
    plot_series(ax2, rows, (("val/bad1", "s-", "validation"),), scale=100)
    ax2.set(ylabel="pixels with error > 1 px (%)", title="validation bad-1")
    plot_series(ax3, rows, LOSS_LINES)
    ax3.set(ylabel="loss (-)", title="loss")
    return finish_figure(fig, title)


def example_figure(
    left: np.ndarray,
    exact: np.ndarray,
    sgm: np.ndarray,
    learned: np.ndarray,
    vmax: float,
):
    """Rows of frames, columns left | exact | SGM | learned | |learned - exact| (px, colour bars);
    invalid (< 0) disparities and pixels without ground truth are shown blank."""
    n = len(left)
    fig, axes = _plt().subplots(
        n, 5, figsize=(16, 2.1 * n + 0.6), squeeze=False, subplot_kw={"xticks": [], "yticks": []}
    )
    titles = ("left image", "exact disparity (px)", "SGM (px)", "learned (px)")
    for ax, head in zip(axes[0], (*titles, "|learned - exact| (px)")):
        ax.set_title(head, fontsize=9)
    for i in range(n):
        err = np.where((exact[i] > 0) & (learned[i] >= 0), np.abs(learned[i] - exact[i]), np.nan)
        axes[i, 0].imshow(left[i][..., ::-1])
        valid = [np.where(d[i] >= 0, d[i], np.nan) for d in (sgm, learned)]
        maps = (np.where(exact[i] > 0, exact[i], np.nan), *valid, err)
        for ax, img, cmap, top in zip(
            axes[i, 1:], maps, ("viridis",) * 3 + ("magma",), (vmax,) * 3 + (2.0,)
        ):
            im = ax.imshow(img, cmap=cmap, vmin=0, vmax=top)
            fig.colorbar(im, ax=ax, fraction=0.025, pad=0.01, label="px")
    fig.tight_layout()
    return fig


def fault_free_test_examples(risk, sgm, learned, rows: int = 3):
    """:func:`example_figure` of ``rows`` evenly spaced fault-free test frames of the risk data
    ``risk`` (Dataset: left image, exact disparity), with their SGM (``sgm``) and learned
    (``learned``) disparities (Datasets of the same shards); colour scale: the 99th percentile of
    their exact disparity (px, at least 1)."""
    frames = risk.table("frames.csv").sort_values(["shard", "idx"])
    picks = frames[(frames.split == "test") & (frames.fault == "none")]
    if not len(picks):
        raise ValueError(f"{risk.root}: no fault-free test frame to show")
    at = np.unique(np.linspace(0, len(picks) - 1, rows).round().astype(int))
    picked = picks[["shard", "idx"]].to_numpy()[at]
    sources = ((risk, "left"), (risk, "disp_gt"), (sgm, "disp_sgm"), (learned, "disp_learned"))
    left, gt, sgm_d, learned_d = (
        np.stack([ds.load_shard(int(i), [key])[key][k] for i, k in picked]) for ds, key in sources
    )
    vmax = float(max(np.percentile(gt[gt > 0], 99), 1.0)) if (gt > 0).any() else 1.0
    return example_figure(left, gt, sgm_d, learned_d, vmax)
