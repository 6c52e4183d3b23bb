"""Figures of the risk data part (matplotlib, Agg): grid-map risk metric (paper Fig. 3), stereo
image + disparity (paper Fig. 2) and an ORB-flagged stereo pair."""

from __future__ import annotations

from dataclasses import replace
from itertools import chain
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from traffictwin.io.atomic import pyplot, save_figure
from traffictwin.io.shards import Dataset
from traffictwin.risk.dataset import RiskDataSpec
from traffictwin.risk.metric import (
    RiskCalculator,
    path_to_subject_frame,
    rasterise,
    region_mask,
    swept_cells,
    to_subject_frame,
)
from traffictwin.sim.camera import GroundTexture
from traffictwin.sim.driving import generate_sequence
from traffictwin.sim.scene import Boxes
from traffictwin.stereo.orb import OrbParams, cross_checked_matches

plt = pyplot()
N_MATCHES = 40  # the ORB figure's matches drawn (the best by descriptor distance)


def risk_metric_figure(
    seed: int, spec: RiskDataSpec, path: str | Path, max_sequences: int = 12
) -> dict:
    """Camera view + grid map of one frame with an object in the driving corridor (paper Fig. 3):
    occupied border cells (black), cells occupied within 3 s at constant velocity (blue), the
    paper's region (light grey) and the driving corridor searched by the headline label (light
    green), the subject (red), the nearest object found and its distance (orange)."""
    grid = spec.grid
    calc = RiskCalculator(grid, replace(spec.risk, region="corridor"))
    frames = (
        (seq, fr, calc(fr.pose, fr.speed, fr.boxes, fr.path, fr.lane_width))
        for i in range(max_sequences)
        for seq in [generate_sequence(seed, i, spec.driving)]
        for fr in seq.frames
    )
    first = next(frames)  # the fall-back
    seq, fr, r = next((c for c in chain([first], frames) if 0.4 < c[2].thw < 3.0), first)
    texture = GroundTexture.from_world(seq.world, res=spec.ground_res)
    img = spec.camera.render_eye(fr.pose, fr.boxes, texture)[0]
    obstacles = calc.obstacles(fr.boxes)
    rel = to_subject_frame(fr.boxes.subset(obstacles), fr.pose)
    lab = rasterise(rel, grid, "border")
    rgb = np.ones(grid.shape + (3,))
    rgb[region_mask(grid, replace(spec.risk, region="paper"))] = [0.93, 0.93, 0.93]
    corridor = region_mask(
        grid,
        replace(spec.risk, region="corridor", lane_width=fr.lane_width),
        path_to_subject_frame(fr.path, fr.pose),
    )
    rgb[corridor] = [0.85, 0.97, 0.85]
    rgb[swept_cells(rel, grid)] = [0.45, 0.6, 1.0]
    rgb[lab > 0] = [0.0, 0.0, 0.0]  # over the swept cells
    if r.target >= 0:
        rgb[lab == 1 + int(np.flatnonzero(obstacles == r.target)[0])] = [1.0, 0.55, 0.0]
    L, W = spec.risk.subject_length, spec.risk.subject_width
    sub = rasterise(Boxes([[0.0, 0.0]], [[L, W, 1.5]], [0.0], [0]), grid, "filled") > 0
    rgb[sub] = [0.85, 0.1, 0.1]
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.6), gridspec_kw={"width_ratios": [1.6, 1]})
    ax[0].imshow(cv2.cvtColor(img, cv2.COLOR_BGR2RGB))
    ax[0].set_title(f"{seq.world.template} / {seq.situation}: v = {fr.speed:.1f} m/s")
    ax[0].axis("off")
    ext = [grid.width / 2, -grid.width / 2, -grid.length / 2, grid.length / 2]  # col 0 = +y (left)
    ax[1].imshow(rgb, extent=ext, interpolation="nearest")
    ax[1].set(xlabel="y (m, + = left)", ylabel="x (m, forward)")
    ax[1].set_title(f"THW {r.thw:.2f} s, d = {r.distance:.1f} m, risk {r.risk_thw:.3f}")
    fig.suptitle(
        "Risk metric calculator: grid map (black: object border cells, blue: next 3 s, "
        "green: driving corridor, grey: paper region, orange: nearest object, red: subject)",
        fontsize=9,
    )
    save_figure(fig, path)
    return dict(thw=r.thw, risk=r.risk_thw, template=seq.world.template, situation=seq.situation)


def stereo_figure(
    left: np.ndarray,
    right: np.ndarray,
    gt: np.ndarray,
    sgm: np.ndarray,
    path: str | Path,
    title: str = "",
) -> None:
    """Left/right image, GT disparity and SGM disparity (px, one colour bar each: yellow = near,
    invalid black; colour scale 0 to the 99th percentile of the GT), like the paper's Fig. 2."""
    vmax = float(np.percentile(gt[gt > 0], 99)) if (gt > 0).any() else 1.0
    panels = (
        (left, "left image"),
        (right, "right image"),
        (np.ma.masked_less_equal(gt, 0.0), "ground-truth disparity f·B/Z (black: sky)"),
        (np.ma.masked_less(sgm, 0.0), "SGM disparity (black: invalid)"),  # OpenCV's invalid: < 0
    )
    cmap = plt.get_cmap("viridis").with_extremes(bad="black")
    fig, ax = plt.subplots(2, 2, figsize=(10.8, 5.2), subplot_kw=dict(xticks=[], yticks=[]))
    for a, (img, name) in zip(ax.ravel(), panels):
        if img.ndim == 3:
            a.imshow(cv2.cvtColor(img, cv2.COLOR_BGR2RGB))
        else:  # disparity (px) from 0 to vmax, masked cells black
            im = a.imshow(img, cmap=cmap, vmin=0.0, vmax=vmax)
            fig.colorbar(im, ax=a, fraction=0.046, pad=0.02, label="disparity (px)")
        a.set_title(name)
    if title:
        fig.suptitle(title, fontsize=9)
    save_figure(fig, path)


def stereo_example_figure(risk: Dataset, disparity: Dataset, path: str | Path) -> None:
    """:func:`stereo_figure` of the first fault-free frame faster than 3 m/s (else the first frame)
    of the risk data ``risk`` and its SGM disparity ``disparity``."""
    frames = risk.table("frames.csv")
    clean = frames[(frames.fault == "none") & (frames.speed > 3)]
    row = (clean if len(clean) else frames).iloc[0]
    sh, sd = risk.load_shard(int(row.shard)), disparity.load_shard(int(row.shard))
    k = int(row.idx)
    title = f"frame {int(row.frame_id)} ({row.template}, {row.situation}), v = {row.speed:.1f} m/s"
    stereo_figure(sh["left"][k], sh["right"][k], sh["disp_gt"][k], sd["disp_sgm"][k], path, title)


def orb_example_figure(
    risk: Dataset, orb_table: pd.DataFrame, params: OrbParams, path: str | Path
) -> None:
    """The first flagged pair with an injected fault (else the first flagged, else the first pair;
    ``orb_table``: the orb.csv rows of ``risk``'s frames), left and right image side by side with
    the best :data:`N_MATCHES` ORB matches drawn (``params``: the detector's settings)."""
    t = orb_table
    o = next(x for x in (t[t.outlier & (t.fault != "none")], t[t.outlier], t) if len(x)).iloc[0]
    fid = int(o.frame_id)
    frames = risk.table("frames.csv")
    row = frames[frames.frame_id == fid].iloc[0]
    sh, k = risk.load_shard(int(row.shard)), int(row.idx)
    left, right = sh["left"][k], sh["right"][k]
    W = left.shape[1]
    kl, kr, matches = cross_checked_matches(left, right, **params.detector())
    fig, ax = plt.subplots(figsize=(11, 3.4))
    ax.imshow(cv2.cvtColor(np.concatenate([left, right], 1), cv2.COLOR_BGR2RGB))
    for m in sorted(matches, key=lambda m: m.distance)[:N_MATCHES]:
        (x0, y0), (x1, y1) = kl[m.queryIdx].pt, kr[m.trainIdx].pt
        ax.plot([x0, x1 + W], [y0, y1], "-", lw=0.7, color="yellow" if abs(y0 - y1) <= 2 else "red")
    ax.axis("off")
    title = f"frame {fid}: fault '{row.fault}', mean |dx| {o.mean_dx:.2f} px, mean |dy| "
    title += f"{o.mean_dy:.2f} px, outlier={bool(o.outlier)}  (yellow: |dy| <= 2 px, red: larger)"
    ax.set_title(title, fontsize=9)
    save_figure(fig, path)
