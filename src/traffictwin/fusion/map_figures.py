"""Map figures of the fusion evaluation (paper Fig. 4) in the project's one mass colour map
(:mod:`traffictwin.report.colours`), axes in metres; apart from :mod:`traffictwin.fusion.figures`
so that no stage depends on the map colour code through the score plots."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from traffictwin.io.atomic import pyplot as _plt
from traffictwin.report.colours import legend_handles, show_masses


def qualitative_grid(
    rows: Mapping[str, Sequence[np.ndarray]],
    configs: Sequence[str],
    cell: float,
    title: str = "",
    noise: Mapping[str, Sequence[float]] | None = None,
):
    """Image grid: one row per entry of ``rows`` (e.g. label / naive / network: masses (2, H, W)),
    one column per config; :func:`traffictwin.report.colours.show_masses` (axes in metres,
    ``cell`` m per cell) and the colour map's legend below the panels; ``noise[config] = (r m,
    α deg)`` goes into the column titles."""
    names = list(rows)
    h, w = np.asarray(rows[names[0]][0]).shape[-2:]
    fig, axes = _plt().subplots(
        len(names),
        len(configs),
        figsize=(2.3 * len(configs) + 0.8, 2.3 * len(names) * h / w + 1.4),
        squeeze=False,
        sharex=True,
        sharey=True,
    )
    for r, name in enumerate(names):
        for c, cfg in enumerate(configs):
            ax = axes[r][c]
            show_masses(ax, rows[name][c], cell)
            ax.tick_params(labelsize=7)
            head = f": r {noise[cfg][0]:g} m, α {noise[cfg][1]:g}°" if cfg in (noise or {}) else ""
            ax.set_title(f"config {cfg}{head}" if r == 0 else "", fontsize=9)
            ax.set_xlabel("y (m, + = left)" if r == len(names) - 1 else "", fontsize=8)
            ax.set_ylabel(f"{name}\nx (m, forward)" if c == 0 else "", fontsize=8)
    fig.legend(handles=legend_handles(), loc="lower center", ncol=3, fontsize=8, frameon=False)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    return fig
