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
    plt = pyplot()
    n = len(samples)
    if n == 0:
        raise ValueError("plot_fusion_samples: no samples given")
    fig, axes = plt.subplots(n, 3, figsize=(9, 4.6 * n), squeeze=False)
    for i, s in enumerate(samples):
        p1, p2 = s["pose1"], s["pose2"]
        head = f"{s.get('template', '')} pair {int(s.get('pair_id', i))}".strip()
        for j, (key, name, pose) in enumerate(
            (
                ("map1", "input map 1", p1),
                ("map2", "input map 2", p2),
                ("label", "label (fused, map 1's frame)", None),
            )
        ):
            ax = axes[i, j]
            show_masses(ax, s[key], grid.cell)
            ax.plot(0, 0, marker=(3, 0, 0), color="k", markersize=8)
            if pose is not None:
                ax.set_title(
                    f"{name}\npose x={pose[0]:.1f} m, y={pose[1]:.1f} m, yaw={np.rad2deg(pose[2]):.0f} deg",
                    fontsize=8,
                )
            else:
                ax.set_title(name, fontsize=8)
            ax.xaxis.label.set_fontsize(7)
            ax.yaxis.label.set_fontsize(7)
            ax.tick_params(labelsize=6)
        axes[i, 0].text(
            -0.35, 0.5, head, transform=axes[i, 0].transAxes, rotation=90, va="center", fontsize=8
        )
    fig.legend(handles=legend_handles(), loc="lower center", ncol=3, fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0.03, 0.03, 1, 0.97))
    save_figure(fig, path, dpi=90, bbox_inches=None, metadata={"Software": None})
