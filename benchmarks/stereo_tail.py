"""Where the tail of the critical-object range error sits: SGM and the learned stereo network on
the default run's fault-free test frames, the 90th percentile split by depth edges.

    python -m benchmarks.stereo_tail [--risk data/risk] [--disparity data/disparity]
                                     [--model models/stereo/learned]

Needs the default run's ``data/risk``, ``data/disparity`` and ``models/stereo/learned`` (``dvc
repro train_stereo``). Over the pixels stereo.json's ``crit_obj`` figures are on (object pixels at
the critical distances :data:`~traffictwin.stereo.metrics.CRITICAL_M` where SGM and the network
both estimate), per source (:func:`tail_breakdown`): median and 90th percentile of the relative
range error |Z - Z_gt| / Z_gt, the 90th percentile without the pixels within 1 and 2 px of a depth
edge (the exact disparity jumps by more than 0.5 px there), those pixels' share of all and of the
worst 10 %, the absolute disparity error (px) at the 90th percentile and the share off by more
than 1 px. Prints JSON. A benchmark, not a DVC stage: it reads a finished run.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

#: a depth edge: the exact disparity changes by more than this (px) within a pixel's neighbourhood
JUMP_PX = 0.5


def edge_bands(gt: np.ndarray, jump_px: float = JUMP_PX) -> dict[int, np.ndarray]:
    """Pixels of exact disparity maps ``gt`` (N, H, W) px within 1 and 2 px of a depth edge (the
    disparity spans more than ``jump_px`` over their 3x3 / 5x5 neighbourhood), by distance."""
    g = np.asarray(gt, np.float64)
    out = {}
    for px in (1, 2):
        size = (1, 2 * px + 1, 2 * px + 1)
        out[px] = (
            ndimage.maximum_filter(g, size=size) - ndimage.minimum_filter(g, size=size)
        ) > jump_px
    return out


def _p90(x: np.ndarray) -> float:
    """The empirical 90th percentile (the smallest value with at least 90 % of ``x`` at or below
    it): no interpolation, so an infinite error stays one."""
    return float(np.quantile(x, 0.9, method="inverted_cdf"))


def tail_breakdown(
    gt: np.ndarray, estimates: Mapping[str, np.ndarray], mask: np.ndarray, jump_px: float = JUMP_PX
) -> dict[str, Any]:
    """Per source of ``estimates`` (disparity maps like ``gt``, px), over the pixels of ``mask``:
    the relative range error |d_gt / d - 1| (= |Z - Z_gt| / Z_gt) summarised as the module says.
    ``mask`` must hold only pixels where ``gt`` > 0 and every estimate >= 0 (an estimate of 0 px,
    an infinite range, counts as an infinite error, as in stereo.json)."""
    g = np.asarray(gt, np.float64)
    bands = edge_bands(g, jump_px)
    edge = {px: b[mask] for px, b in bands.items()}
    out: dict[str, Any] = {
        "pixels": int(mask.sum()),
        **{f"edge{px}px_share": float(e.mean()) for px, e in edge.items()},
    }
    for name, est in estimates.items():
        d = np.asarray(est, np.float64)[mask]
        with np.errstate(divide="ignore"):
            rel = np.abs(g[mask] / d - 1.0)
        err = np.abs(d - g[mask])
        p90 = _p90(rel)
        top = rel >= p90
        out[name] = {
            "median": float(np.median(rel)),
            "p90": p90,
            **{f"p90_without_edge{px}px": _p90(rel[~e]) for px, e in edge.items()},
            **{f"edge{px}px_share_of_worst10": float(e[top].mean()) for px, e in edge.items()},
            "abs_err_px_p90": _p90(err),
            "over_1px_share": float((err > 1.0).mean()),
        }
    return out


def main(argv: list[str] | None = None) -> dict[str, Any]:
    from traffictwin.io.shards import Dataset, derived_dataset
    from traffictwin.risk.stereo_io import load_stereo_model, predict
    from traffictwin.risk.stereo_shards import load_stereo_shard
    from traffictwin.stereo.evaluation import critical_objects
    from traffictwin.stereo.metrics import CRITICAL_M

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--risk", default="data/risk")
    ap.add_argument("--disparity", default="data/disparity")
    ap.add_argument("--model", default="models/stereo/learned")
    a = ap.parse_args(argv)
    ds = Dataset(a.risk, kind="risk", verify=False)
    sgm_ds = derived_dataset(a.disparity, "disparity", ds, a.risk, "disparity")
    net = load_stereo_model(Path(a.model))
    thr = float(net.meta["spread_threshold_px"])
    cam = ds.manifest["camera"]
    fx_b = float(cam["fx"]) * float(cam["baseline"])
    frames = ds.table("frames.csv")
    parts: dict[str, list[np.ndarray]] = {"gt": [], "sgm": [], "learned": [], "mask": []}
    for i in range(len(ds.shards)):
        rows = frames[frames.shard == i].sort_values("idx")
        sel = ((rows.split == "test") & (rows.fault == "none")).to_numpy()
        if not sel.any():
            continue
        sh = load_stereo_shard(ds, i, ("left", "right", "disp_gt"))
        d_sgm = sgm_ds.load_shard(i)["disp_sgm"][sel]
        base = d_sgm if net.spec.base == "sgm" else None
        d, spread = predict(net, sh["left"][sel], sh["right"][sel], 8, sgm=base)
        d = np.where(spread <= thr, d, -1.0)
        gt = sh["disp_gt"][sel]
        z = np.where(gt > 0, fx_b / np.maximum(gt, 1e-12), np.inf)
        crit = critical_objects(gt, fx_b, cam) & (z >= CRITICAL_M[0]) & (z < CRITICAL_M[1])
        parts["mask"].append(crit & (d_sgm >= 0) & (d >= 0))
        for k, v in (("gt", gt), ("sgm", d_sgm), ("learned", d)):
            parts[k].append(v)
    stack = {k: np.concatenate(v) for k, v in parts.items()}
    res = tail_breakdown(stack["gt"], {k: stack[k] for k in ("sgm", "learned")}, stack["mask"])
    print(json.dumps(res, indent=1))
    return res


if __name__ == "__main__":
    main()
