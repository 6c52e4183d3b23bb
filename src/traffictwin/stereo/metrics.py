"""Disparity accuracy against ground truth (KITTI-style).

Only pixels with a surface (GT > 0) are evaluated. ``density`` = share of those where the
estimate is valid (>= 0); error measures are over pixels valid in both:
``bad2`` = share with |d - d_gt| > 2 px, ``d1`` = share with error > 3 px AND > 5 % of d_gt
(KITTI 2015 D1), ``epe`` = mean |d - d_gt| (px).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import pandas as pd

#: the accumulated sums of :func:`disparity_errors`
SUM_KEYS = ("n_gt", "n_valid", "n_bad2", "n_d1", "sum_abs")


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


def accuracy_table(
    frames: pd.DataFrame, per_frame: Mapping[int, Sequence[Mapping[str, float]]]
) -> pd.DataFrame:
    """``frames`` (one row per stereo frame: ``shard``, ``idx``, ``split``, ``fault``, ...) joined
    with the per-frame :func:`disparity_errors` sums, ``per_frame[shard][idx]``."""
    rows = [
        {"shard": i, "idx": k, **e} for i in sorted(per_frame) for k, e in enumerate(per_frame[i])
    ]
    return frames.merge(pd.DataFrame(rows), on=["shard", "idx"], how="left", validate="one_to_one")


def grouped_accuracy(
    df: pd.DataFrame, splits: Sequence[str], faults: Sequence[str]
) -> dict[str, float]:
    """``<group>/<density|bad2|d1|epe>`` over all frames, per split (``split`` column) and per fault
    type (``fault`` column, group ``fault_<f>``); groups without frames are left out; ``df`` from
    :func:`accuracy_table`."""
    groups = [("all", df)] + [(s, df[df.split == s]) for s in splits]
    groups += [(f"fault_{f}", df[df.fault == f]) for f in faults]
    metrics: dict[str, float] = {}
    for name, part in groups:
        if len(part) == 0:
            continue
        sums = {k: float(part[k].sum()) for k in SUM_KEYS}
        for m, v in summarise(sums).items():
            metrics[f"{name}/{m}"] = v
    return metrics


def per_frame_accuracy(df: pd.DataFrame) -> pd.DataFrame:
    """``frame_id``, density, bad2, d1, epe per frame (NaN where undefined); ``df`` from
    :func:`accuracy_table`."""
    out = df[["frame_id"]].copy()
    out["density"] = df.n_valid / df.n_gt.where(df.n_gt > 0)
    out["bad2"] = df.n_bad2 / df.n_valid.where(df.n_valid > 0)
    out["d1"] = df.n_d1 / df.n_valid.where(df.n_valid > 0)
    out["epe"] = df.sum_abs / df.n_valid.where(df.n_valid > 0)
    return out
