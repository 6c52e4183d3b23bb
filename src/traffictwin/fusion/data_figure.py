"""Figure like the paper's Fig. 2: two input maps with their poses and the fused label, in the
project's one mass colour map (:mod:`traffictwin.report.colours`: free green, occupied red,
unknown grey, mixed by mass), axes in metres."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from traffictwin.grid import GridSpec
from traffictwin.io.atomic import pyplot, save_figure
from traffictwin.report.colours import legend_handles, show_masses


def pick_samples(ds: Any, n: int) -> list[dict[str, Any]]:
    """The first pair of the first ``n`` scenarios of a ``data/fusion`` dataset (consecutive
    scenarios use different road templates)."""
    from traffictwin.sim.world import TEMPLATES

    samples: list[dict[str, Any]] = []
    for si in range(len(ds.shards)):
        sh = ds.load_shard(si)
        _, first = np.unique(sh["scenario"], return_index=True)
        for i in first[: n - len(samples)]:
            s = {k: sh[k][i] for k in ("map1", "map2", "label", "pose1", "pose2")}
            s.update(template=TEMPLATES[int(sh["template"][i])], pair_id=int(sh["pair_id"][i]))
            samples.append(s)
        if len(samples) >= n:
            break
    return samples


def plot_fusion_samples(
    path: str | Path,
    samples: list[dict[str, np.ndarray]],
    grid: GridSpec,
    title: str = "fusion data samples",
) -> None:
    """Write a PNG with one row per sample: map 1, map 2, label (in map 1's frame).

    Each sample: ``map1``, ``map2``, ``label`` (2, H, W), ``pose1``, ``pose2`` (3,) world (m, rad),
    optional ``template`` (str) and ``pair_id`` (int).
    """
    if not samples:
        raise ValueError("plot_fusion_samples: no samples given")
    fig, axes = pyplot().subplots(len(samples), 3, figsize=(9, 4.6 * len(samples)), squeeze=False)
    for i, s in enumerate(samples):
        heads = [
            f"input map {k}\npose x={p[0]:.1f} m, y={p[1]:.1f} m, yaw={np.rad2deg(p[2]):.0f} deg"
            for k, p in ((1, s["pose1"]), (2, s["pose2"]))
        ]
        for ax, key, head in zip(
            axes[i], ("map1", "map2", "label"), [*heads, "label (fused, map 1's frame)"]
        ):
            show_masses(ax, s[key], grid.cell)
            ax.plot(0, 0, marker=(3, 0, 0), color="k", markersize=8)
            ax.set_title(head, fontsize=8)
            ax.xaxis.label.set_fontsize(7)
            ax.yaxis.label.set_fontsize(7)
            ax.tick_params(labelsize=6)
        name = f"{s.get('template', '')} pair {int(s.get('pair_id', i))}".strip()
        axes[i, 0].text(
            -0.35, 0.5, name, transform=axes[i, 0].transAxes, rotation=90, va="center", fontsize=8
        )
    fig.legend(handles=legend_handles(), loc="lower center", ncol=3, fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0.03, 0.03, 1, 0.97))
    save_figure(fig, path, dpi=90, bbox_inches=None, metadata={"Software": None})
