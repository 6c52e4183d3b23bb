"""Camera resolution study: SGM range error at the critical distance and SGM time vs image width.

``python -m benchmarks.stereo_resolution [--frames 80] [--widths 320 480 640]`` renders the same
fault-free frames of seeded driving sequences (:func:`traffictwin.sim.driving.generate_sequence`,
as the risk data does) at each width (height = width / 2, same 60 deg field of view and 16 cm
baseline), runs the default SGM with ``num_disparities`` scaled with the width (32 px at 320 px:
the same nearest range, ~1.4 m) and measures

* the relative depth error |Z - Z_gt| / Z_gt (median, 90th percentile) and the valid share at the
  critical distance -- the 1.5 s time headway at urban speeds of 8-14 m/s, 12-21 m -- over object
  pixels (not the road surface) and over every pixel with a surface, and per range bin
  (0-10, 10-30, 30-90 m); scenario-cluster bootstrap 95 % intervals (traffictwin.stats) for the
  critical-distance medians and their paired difference between the widths;
* SGM time per frame (median over frames; OpenCV's thread count and the machine's load average
  recorded) and render time.

Writes reports/metrics/stereo_resolution.json (flat ``w<width>/<metric>`` and ``study/<...>``
keys) and reports/figures/stereo_resolution.png and prints the JSON. A benchmark, not a DVC
stage: rerun it by hand when the camera or SGM changes.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import cv2
import numpy as np

from traffictwin.io.atomic import save_figure, write_json_atomic
from traffictwin.sim.camera import GroundTexture, StereoCamera
from traffictwin.sim.driving import DrivingConfig, generate_sequence
from traffictwin.stats import statistic_ci
from traffictwin.stereo.metrics import (
    CRITICAL_M,
    RANGE_EDGES_M,
    depth_error_counts,
    depth_error_summary,
    histogram_quantile,
    object_mask,
    range_bin_names,
)
from traffictwin.stereo.sgm import compute_disparity, make_matcher

ROOT = Path(__file__).resolve().parents[1]
#: distance bins of the figure's error curve (m)
CURVE_EDGES_M = np.arange(2.0, 62.0, 2.0)


def frames(n: int, seed: int) -> list[tuple]:
    """``n`` fault-free frames (frame, ground texture) of seeded sequences, 4 per sequence, with
    the sequence index (the bootstrap cluster)."""
    cfg = DrivingConfig(frames=4, fault_delay=0.0, fault_vertical=0.0)
    out: list[tuple] = []
    i = 0
    while len(out) < n:
        s = generate_sequence(seed, i, cfg)
        g = GroundTexture.from_world(s.world, res=0.1, seed=int(s.world.seed) % 100003)
        out += [(f, g, i) for f in s.frames]
        i += 1
    return out[:n]


def measure(width: int, nd320: int, items: list[tuple], seed: int) -> dict:
    """Render, match and score every frame of ``items`` at ``width``; per-frame histograms kept
    for the bootstrap."""
    cam = StereoCamera(width=width, height=width // 2)
    nd = max(16, int(round(nd320 * width / 320 / 16)) * 16)
    m = make_matcher(nd, 5, 3)
    rng = np.random.default_rng(seed)
    fx_b = cam.fx * cam.baseline
    sgm_ms, render_ms = [], []
    crit_obj, crit_all, bins, curve = [], [], None, None
    for f, g, _ in items:
        t0 = time.perf_counter()
        p = cam.render_pair(f.pose, f.boxes, g, rng=rng)
        render_ms.append(1e3 * (time.perf_counter() - t0))
        t0 = time.perf_counter()
        d = compute_disparity(p["left"], p["right"], matcher=m)
        sgm_ms.append(1e3 * (time.perf_counter() - t0))
        gt = p["disp_gt"]
        obj = object_mask(p["depth"], cam.cy, cam.fy, cam.mount_height)
        crit_obj.append(depth_error_counts(d[obj], gt[obj], fx_b, CRITICAL_M))
        crit_all.append(depth_error_counts(d, gt, fx_b, CRITICAL_M))
        c = depth_error_counts(d, gt, fx_b, RANGE_EDGES_M)
        bins = c if bins is None else {k: bins[k] + c[k] for k in c}
        c = depth_error_counts(d, gt, fx_b, CURVE_EDGES_M)
        curve = c if curve is None else {k: curve[k] + c[k] for k in c}
    return {
        "width": width,
        "height": cam.height,
        "num_disparities": nd,
        "fx_b": fx_b,
        "sgm_ms": np.array(sgm_ms),
        "render_ms": np.array(render_ms),
        "crit_obj": crit_obj,
        "crit_all": crit_all,
        "bins": bins,
        "curve": curve,
    }


def _median_of(counts: list[dict], idx: np.ndarray) -> float:
    return histogram_quantile(np.sum([counts[i]["hist"][0] for i in idx], axis=0), 0.5)


def summarise(res: dict, groups: np.ndarray, n_boot: int) -> dict[str, float]:
    """Flat metrics of one width (fractions, ms, px)."""
    w = res
    out: dict[str, float] = {
        "height": w["height"],
        "num_disparities": w["num_disparities"],
        "sgm_ms_median": float(np.median(w["sgm_ms"])),
        "sgm_ms_mean": float(np.mean(w["sgm_ms"])),
        "render_ms_median": float(np.median(w["render_ms"])),
    }
    for z in (CRITICAL_M[0], 15.0, CRITICAL_M[1]):
        out[f"gt_disparity_px_at_{z:g}m"] = w["fx_b"] / z
    for name in ("crit_obj", "crit_all"):
        counts = w[name]
        tot = {k: np.sum([c[k] for c in counts], axis=0) for k in counts[0]}
        s = depth_error_summary(tot, CRITICAL_M)
        b = range_bin_names(CRITICAL_M)[0]
        out[f"{name}_relerr_median"] = s[f"{b}_relerr_median"]
        out[f"{name}_relerr_p90"] = s[f"{b}_relerr_p90"]
        out[f"{name}_valid_share"] = s[f"{b}_valid_share"]
        out[f"{name}_gt_pixels"] = s[f"{b}_gt_pixels"]
        ci = statistic_ci(
            lambda idx, c=counts: _median_of(c, idx), len(counts), groups, n_boot=n_boot, seed=0
        )
        out[f"{name}_relerr_median_lo"], out[f"{name}_relerr_median_hi"] = ci.lo, ci.hi
    out.update(depth_error_summary(w["bins"], RANGE_EDGES_M))
    return out


def figure(results: list[dict], path: Path) -> None:
    """Median / 90th percentile relative depth error vs GT distance per width, critical band
    shaded; SGM time per frame per width."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4), gridspec_kw={"width_ratios": [2.2, 1]})
    mid = 0.5 * (CURVE_EDGES_M[:-1] + CURVE_EDGES_M[1:])
    for r, colour in zip(results, ("tab:blue", "tab:orange", "tab:green", "tab:red")):
        h = r["curve"]["hist"]
        med = [100 * histogram_quantile(x, 0.5) for x in h]
        p90 = [100 * histogram_quantile(x, 0.9) for x in h]
        label = f"{r['width']}×{r['height']} px"
        ax.plot(mid, med, "-", color=colour, label=f"{label}: median")
        ax.plot(mid, p90, "--", color=colour, label=f"{label}: 90th percentile")
    ax.axvspan(*CRITICAL_M, color="0.85", zorder=0, label="1.5 s headway at 8-14 m/s")
    ax.set_xlabel("GT distance Z [m]")
    ax.set_ylabel("relative depth error |Z - Z_gt| / Z_gt [%]")
    ax.set_ylim(0, 100)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    ax.set_title("SGM range error vs distance (fault-free frames)")
    names = [f"{r['width']}×{r['height']}" for r in results]
    bx.bar(names, [np.median(r["sgm_ms"]) for r in results], color="0.5")
    bx.set_xlabel("image size [px]")
    bx.set_ylabel("SGM time per frame [ms] (median)")
    bx.set_title("SGM cost")
    bx.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    save_figure(fig, path, dpi=110, bbox_inches=None)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=80)
    ap.add_argument("--widths", type=int, nargs="+", default=[320, 480, 640])
    ap.add_argument("--num-disparities", type=int, default=32, help="at 320 px, scaled with width")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--n-boot", type=int, default=1000)
    ap.add_argument("--out-json", default=str(ROOT / "reports/metrics/stereo_resolution.json"))
    ap.add_argument("--out-fig", default=str(ROOT / "reports/figures/stereo_resolution.png"))
    a = ap.parse_args(argv)
    if a.frames < 4 or any(w < 64 or w % 2 for w in a.widths):
        raise SystemExit("--frames must be >= 4 and --widths even numbers >= 64 px")
    load_before = os.getloadavg()[0]
    items = frames(a.frames, a.seed)
    groups = np.array([i for _, _, i in items])
    results = [measure(w, a.num_disparities, items, a.seed) for w in a.widths]
    out: dict = {
        "study/frames": len(items),
        "study/sequences": int(len(np.unique(groups))),
        "study/critical_lo_m": CRITICAL_M[0],
        "study/critical_hi_m": CRITICAL_M[1],
        "study/opencv_threads": int(cv2.getNumThreads()),
        "study/cpu_count": int(os.cpu_count() or 0),
        # other work on the machine slows the timings: the 1-min load average before / after
        "study/load_avg_before": load_before,
        "study/load_avg_after": os.getloadavg()[0],
    }
    for r in results:
        out.update({f"w{r['width']}/{k}": v for k, v in summarise(r, groups, a.n_boot).items()})
    if len(results) >= 2:  # paired: the same frames (same resampled sequences) at both widths
        lo_res, hi_res = results[0], results[-1]
        for name in ("crit_obj", "crit_all"):
            ci = statistic_ci(
                lambda idx, n=name: _median_of(hi_res[n], idx) - _median_of(lo_res[n], idx),
                len(items),
                groups,
                n_boot=a.n_boot,
                seed=0,
            )
            key = f"diff_w{hi_res['width']}_minus_w{lo_res['width']}/{name}_relerr_median"
            out[key], out[key + "_lo"], out[key + "_hi"] = ci.estimate, ci.lo, ci.hi
    out = {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in out.items()}
    write_json_atomic(a.out_json, out)
    figure(results, Path(a.out_fig))
    print(json.dumps({**out, "machine": platform.processor() or platform.machine()}, indent=2))
    return out


if __name__ == "__main__":
    main()
