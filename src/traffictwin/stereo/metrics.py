"""Disparity accuracy against ground truth (KITTI-style).

Only pixels with a surface (GT > 0) are evaluated. ``density`` = share of those where the
estimate is valid (>= 0); error measures are over pixels valid in both:
``bad2`` = share with |d - d_gt| > 2 px, ``d1`` = share with error > 3 px AND > 5 % of d_gt
(KITTI 2015 D1), ``epe`` = mean |d - d_gt| (px).
"""

from __future__ import annotations

import numpy as np


def disparity_errors(disp: np.ndarray, gt: np.ndarray) -> dict[str, float]:
    """Sums for the metrics over one or many frames: n_gt, n_valid, n_bad2, n_d1, sum_abs (px)."""
    disp = np.asarray(disp, np.float32)
    gt = np.asarray(gt, np.float32)
    if disp.shape != gt.shape:
        raise ValueError(f"disparity shape {disp.shape} differs from GT shape {gt.shape}")
    has = gt > 0
    val = has & (disp >= 0)
    err = np.abs(disp[val] - gt[val])
    g = gt[val]
    return {
        "n_gt": float(has.sum()),
        "n_valid": float(val.sum()),
        "n_bad2": float((err > 2.0).sum()),
        "n_d1": float(((err > 3.0) & (err > 0.05 * g)).sum()),
        "sum_abs": float(err.sum(dtype=np.float64)),
    }


def summarise(sums: dict[str, float]) -> dict[str, float]:
    """density, bad2, d1, epe from accumulated :func:`disparity_errors` sums (NaN if empty)."""
    nv = sums["n_valid"]
    return {
        "density": sums["n_valid"] / sums["n_gt"] if sums["n_gt"] else float("nan"),
        "bad2": sums["n_bad2"] / nv if nv else float("nan"),
        "d1": sums["n_d1"] / nv if nv else float("nan"),
        "epe": sums["sum_abs"] / nv if nv else float("nan"),
    }


def add_sums(a: dict[str, float], b: dict[str, float]) -> dict[str, float]:
    return {k: a.get(k, 0.0) + b[k] for k in b}
