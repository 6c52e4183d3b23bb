"""Figures of the twin: one twin map with each vehicle's contribution and pose uncertainty, and a
timeline of the ego's time headway from its own map, from the twin and from the truth."""

from __future__ import annotations

import numpy as np
import pandas as pd

from traffictwin.grid import GridSpec
from traffictwin.io.atomic import pyplot as _plt
from traffictwin.report.colours import legend_handles, show_masses
from traffictwin.sim.cooperative import ROLES
from traffictwin.twin.evaluation import EGO
from traffictwin.twin.figure_inputs import THW_CAP, TwinSnapshot, timeline_table

# vehicle markers on the twin map: blue, orange, purple, cyan, pink, brown (none of the mass
# colour map's green, red or grey, so a marker stays visible on free, occupied and unknown cells)
VEHICLE_COLOURS = ("#1f77b4", "#ff7f0e", "#9467bd", "#17becf", "#e377c2", "#8c564b")


def timeline_figure(
    table: pd.DataFrame,
    configuration: str,
    method: str,
    sequence: int,
    critical_thw: float,
    warn_thw: float,
):
    """THW (s) over time (s) of one sequence: truth, the ego's own map and the twin; critical frames
    (true THW < ``critical_thw``) shaded, the warning level ``warn_thw`` (s) drawn, frames where the
    ego's lidar sees the hazard marked."""
    tt = timeline_table(table, configuration, method, sequence)
    f = table[(table["configuration"] == configuration) & (table["sequence"] == sequence)]
    f = f[f["method"] == EGO]
    fig, ax = _plt().subplots(figsize=(7.5, 3.6))
    styles = {"truth": ("k", "-", "o"), "ego map": ("#7f7f7f", "--", "x")}
    for name, g in tt.groupby("series", sort=False):
        default = ("#9467bd", ":", "^") if str(name).endswith("TTC") else ("#d62728", "-", "s")
        color, ls, mk = styles.get(name, default)
        ax.plot(g["time"], g["thw"], color=color, linestyle=ls, marker=mk, ms=4, label=name)
    dt = float(np.median(np.diff(np.sort(f["time"].unique())))) if len(f) > 1 else 0.1
    for t in f.loc[f["critical"], "time"]:
        ax.axvspan(t - dt / 2, t + dt / 2, color="#ffd8b0", lw=0)
    seen = f.loc[f["ego_sees_hazard"], "time"]
    label = "ego's lidar sees the hazard"
    ax.plot(seen, np.full(len(seen), THW_CAP * 0.97), "|", color="#1f77b4", ms=10, label=label)
    ax.axhline(critical_thw, color="#ff7f0e", lw=1, label=f"critical: THW < {critical_thw:g} s")
    if warn_thw != critical_thw:
        ax.axhline(warn_thw, color="#2ca02c", lw=1, ls="--", label=f"warning: THW < {warn_thw:g} s")
    kind, hazard = f["kind"].iloc[0], f["hazard"].iloc[0]
    ax.set(
        xlabel="time (s)",
        ylabel=f"time headway / time to conflict (s, capped at {THW_CAP:g})",
        ylim=(0, THW_CAP * 1.02),
        title=f"Sequence {sequence} ({kind}, {hazard}), configuration {configuration}: shaded = truly critical",
    )
    ax.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    return fig


def twin_map_figure(
    snap: TwinSnapshot, grid: GridSpec, radius: float, method: str, configuration: str
):
    """The twin of ``snap`` (ego frame) with every vehicle's true position, its noisy position
    with the configuration's pose error bound (circle of ``radius`` r m: 98 % of the noisy
    positions are off by less than r per axis) and the pose the twin used; beside it each
    vehicle's own map where the twin put it. Draws only."""
    from matplotlib.patches import Circle

    n = len(snap.contributions)
    fig, axes = _plt().subplots(1, n + 1, figsize=(3.2 * (n + 1), 4.9))
    roles = ["ego"] + [ROLES[1] if k % 2 == 1 else ROLES[2] for k in range(1, n)]
    show_masses(axes[0], snap.masses, grid.cell, title=f"twin ({method}), config {configuration}")
    for k in range(n):
        c = VEHICLE_COLOURS[k % len(VEHICLE_COLOURS)]
        tx, ty = snap.true_rel[k, :2]
        axes[0].plot(ty, tx, "o", color=c, ms=6, mfc="none", label=f"{k}: {roles[k]} (true)")
        if k:
            x, y = snap.rel[k, :2]
            axes[0].plot(y, x, "x", color=c, ms=6)
            axes[0].add_patch(Circle((y, x), radius, fill=False, color=c, ls=":", lw=1))
            mark = "+" if snap.used[k] else "s"
            axes[0].plot(snap.poses[k, 1], snap.poses[k, 0], mark, color=c, ms=8)
        used = "used" if snap.used[k] else "left out (registration rejected)"
        title = f"vehicle {k} ({roles[k]}): {used if k else 'reference'}"
        show_masses(axes[k + 1], snap.contributions[k], grid.cell, title=title)
        axes[k + 1].plot(ty, tx, "o", color=c, ms=6, mfc="none")
    axes[0].legend(fontsize=6, loc="lower left")
    fig.suptitle(
        "o true position, x noisy position, + pose the twin used; dotted circle: pose error "
        f"bound r = {radius:g} m around the noisy position\n(per axis: 98 % of the noisy "
        "positions are off by less than r in x, and 98 % by less than r in y)",
        fontsize=8,
    )
    fig.legend(handles=legend_handles(), loc="lower center", ncol=3, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    return fig
