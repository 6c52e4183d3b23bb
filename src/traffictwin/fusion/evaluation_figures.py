"""The fusion evaluation's figures from its outputs (stage plot_data): the KLD(b) box plot, the
zoomed score plots (:mod:`traffictwin.fusion.figures`) and the maps of Fig. 4
(:mod:`traffictwin.fusion.map_figures`)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from traffictwin.fusion.evaluation.keys import FIGURE_METHODS
from traffictwin.fusion.figures import kld_boxplot, score_figure
from traffictwin.fusion.map_figures import qualitative_grid

if TYPE_CHECKING:
    import pandas as pd


def evaluation_figures(
    kld: pd.DataFrame,
    scores: pd.DataFrame,
    metrics: Mapping[str, Any],
    panels: Mapping[str, np.ndarray],
    meta: Mapping[str, Any],
) -> dict[str, Any]:
    """The fusion evaluation's figures by file stem, from its outputs: ``fusion_kld_boxplot``
    (KLD(b) per pair: ``kld``, the ``fusion_kld`` plot table; cf. Fig. 5),
    ``fusion_scores_occupied`` / ``fusion_scores_free`` (``scores``: the long score table of
    :func:`traffictwin.report.plot_data.fusion_scores_long`; Figs. 6, 7; the pair counts:
    fusion.json ``metrics``) and
    ``fusion_qualitative`` (Fig. 4: ``panels`` and ``meta`` of
    :func:`traffictwin.fusion.evaluation.figure_inputs`). Network rows (variants) appear beside
    the methods where they exist."""
    configs, nets = list(meta["configs"]), list(meta["network_rows"])
    r_alpha = {c: tuple(meta["noise"][c]) for c in configs}
    box_rows = [*FIGURE_METHODS, *(r for r in nets if r not in FIGURE_METHODS)]
    kvals = {
        m: {c: g["kld_fou"].to_numpy() for c, g in rows.groupby("config")}
        for m, rows in kld.groupby("method")
    }
    n = metrics["n_pairs"]
    slow = "" if n["registered"] == n["per_config"] else f"; registered on {n['registered']}"
    return {
        "fusion_kld_boxplot": kld_boxplot(
            kvals,
            configs,
            box_rows,
            ylabel="KLD(b): KL(label ‖ prediction) over (m_F, m_O, u)",
            title=f"KLD(b) per configuration (test set, {n['per_config']} pairs{slow})",
            noise=r_alpha,
        ),
        "fusion_scores_occupied": score_figure(scores, r_alpha, "occupied"),
        "fusion_scores_free": score_figure(scores, r_alpha, "free"),
        "fusion_qualitative": qualitative_grid(
            {k: list(v) for k, v in panels.items()},
            configs,
            meta["cell_m"],
            title=f"pair {meta['pair_id']}: pose error = {meta['fraction']:.0%} of (r, r, α)",
            noise=r_alpha,
        ),
    }
