"""Disparity accuracy against ground truth (KITTI-style), and the depth error by range.

Only pixels with a surface (GT > 0) are evaluated. ``density`` = share of those where the
estimate is valid (>= 0); error measures are over pixels valid in both:
``bad2`` = share with |d - d_gt| > 2 px, ``d1`` = share with error > 3 px AND > 5 % of d_gt
(KITTI 2015 D1), ``epe`` = mean |d - d_gt| (px).

Disparity errors say little about ranging when disparities are small (a 0.5 px error at 2 px
is 25 % of the depth), so the relative depth error |Z - Z_gt| / Z_gt (Z = fx·B / d) is
reported per range bin of the GT depth: median and 90th percentile over valid pixels, and the
share of GT pixels with a valid estimate (:func:`depth_error_counts`, :func:`depth_error_summary`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # tables load pandas where one is built
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
    import pandas as pd

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
    """``frame_id``, density, bad2, d1, epe per frame (NaN where undefined), plus ``valid_share``
    when ``df`` has it (the GT-free :func:`~traffictwin.stereo.sgm.valid_share`); ``df`` from
    :func:`accuracy_table`."""
    out = df[["frame_id"]].copy()
    out["density"] = df.n_valid / df.n_gt.where(df.n_gt > 0)
    out["bad2"] = df.n_bad2 / df.n_valid.where(df.n_valid > 0)
    out["d1"] = df.n_d1 / df.n_valid.where(df.n_valid > 0)
    out["epe"] = df.sum_abs / df.n_valid.where(df.n_valid > 0)
    if "valid_share" in df.columns:
        out["valid_share"] = df.valid_share
    return out


# --------------------------------------------------------------------------- depth error by range
#: the critical distances (m): the 1.5 s time headway at urban speeds of 8-14 m/s
CRITICAL_M = (12.0, 21.0)


def object_mask(depth: np.ndarray, cy: float, fy: float, mount_height: float) -> np.ndarray:
    """Pixels of objects (boxes), not road surface or sky: finite depth (m) clearly in front of the
    ground plane ``Z = mount_height * fy / (v - cy)`` of that row (a camera without pitch;
    ``cy``, ``fy`` px, ``mount_height`` m). ``depth`` (..., H, W)."""
    v = np.arange(depth.shape[-2], dtype=np.float64)[:, None]
    with np.errstate(divide="ignore"):
        ground = np.where(v > cy, mount_height * fy / (v - cy), np.inf)
    return np.isfinite(depth) & (depth < 0.97 * ground)


#: default range bins of the relative depth error (m): near, urban critical distances, far
RANGE_EDGES_M = (0.0, 10.0, 30.0, 90.0)
#: histogram edges of the relative depth error |Z - Z_gt| / Z_gt: 0.05 % steps up to 100 %, then
#: 1 % (geometric) steps up to 100,000 %; values beyond (and a valid disparity of 0 px, Z = inf)
#: fall into a last, open bin. Quantiles read from it are exact to the step below 100 %.
ERROR_EDGES = np.concatenate([np.arange(0.0, 1.0, 0.0005), np.geomspace(1.0, 1000.0, 695)])


def relative_depth_error(disp: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """|Z - Z_gt| / Z_gt per pixel with Z = fx·B / d (so fx·B cancels: |d_gt / d - 1|); ``inf`` where
    the estimate is valid but 0 px, NaN where there is no GT (d_gt <= 0) or no estimate (d < 0)."""
    d = np.asarray(disp, np.float64)
    g = np.asarray(gt, np.float64)
    if d.shape != g.shape:
        raise ValueError(f"disparity shape {d.shape} differs from GT shape {g.shape}")
    out = np.full(d.shape, np.nan)
    ok = (g > 0) & (d >= 0)
    with np.errstate(divide="ignore"):
        out[ok] = np.abs(g[ok] / d[ok] - 1.0)
    return out


def _check_edges(range_edges: tuple[float, ...] | list[float], what: str = "range_edges") -> None:
    e = np.asarray(range_edges, float)
    if e.ndim != 1 or e.size < 2 or e[0] < 0 or np.any(np.diff(e) <= 0):
        raise ValueError(f"{what}: need >= 2 increasing distances >= 0 (m), got {list(e)}")


def depth_error_counts(
    disp: np.ndarray,
    gt: np.ndarray,
    fx_b: float,
    range_edges: tuple[float, ...] | list[float] = RANGE_EDGES_M,
) -> dict[str, np.ndarray]:
    """Sums for :func:`depth_error_summary` over one map or a stack (any shape, same for both).

    fx_b: focal length (px) times baseline (m), so the GT depth is Z_gt = fx_b / d_gt (m).
    Pixels with GT disparity are binned by Z_gt into ``range_edges`` (m, ``[lo, hi)``). Returns
    ``n_gt`` (B,) GT pixels per bin, ``n_valid`` (B,) of those with a valid estimate and ``hist``
    (B, len(ERROR_EDGES)) their relative depth errors on :data:`ERROR_EDGES` (last bin open).
    """
    if fx_b <= 0:
        raise ValueError(f"fx_b (focal length px x baseline m) must be > 0, got {fx_b}")
    _check_edges(range_edges)
    d = np.asarray(disp, np.float64).reshape(-1)
    g = np.asarray(gt, np.float64).reshape(-1)
    if d.shape != g.shape:
        raise ValueError(f"disparity size {d.size} differs from GT size {g.size}")
    edges = np.asarray(range_edges, float)
    has = g > 0
    z = np.full(g.shape, np.inf)
    z[has] = fx_b / g[has]
    rbin = np.searchsorted(edges, z, side="right") - 1  # -1 below, len-1 beyond the last edge
    nb = len(edges) - 1
    inb = has & (rbin >= 0) & (rbin < nb)
    val = inb & (d >= 0)
    n_gt = np.bincount(rbin[inb], minlength=nb).astype(np.int64)
    n_valid = np.bincount(rbin[val], minlength=nb).astype(np.int64)
    with np.errstate(divide="ignore"):
        err = np.abs(g[val] / d[val] - 1.0)
    ebin = np.searchsorted(ERROR_EDGES, err, side="right") - 1  # inf -> the open last bin
    ne = len(ERROR_EDGES)
    hist = np.bincount(rbin[val] * ne + ebin, minlength=nb * ne).reshape(nb, ne)
    return {"n_gt": n_gt, "n_valid": n_valid, "hist": hist.astype(np.int64)}


def histogram_quantile(hist: np.ndarray, q: float) -> float:
    """The ``q`` quantile of values counted in ``hist`` on :data:`ERROR_EDGES` (linear within a bin;
    ``inf`` when it falls in the open last bin, NaN for an empty histogram)."""
    h = np.asarray(hist, np.float64)
    n = h.sum()
    if n <= 0:
        return float("nan")
    cum = np.cumsum(h)
    target = q * n
    k = int(np.searchsorted(cum, target, side="left"))
    k = min(k, len(h) - 1)
    if k == len(ERROR_EDGES) - 1:
        return float("inf")
    before = cum[k - 1] if k > 0 else 0.0
    frac = (target - before) / h[k] if h[k] > 0 else 0.0
    lo, hi = ERROR_EDGES[k], ERROR_EDGES[k + 1]
    return float(lo + frac * (hi - lo))


def range_bin_names(range_edges: tuple[float, ...] | list[float] = RANGE_EDGES_M) -> list[str]:
    """Key-safe bin names, e.g. ``z0-10m`` (a '.' in an edge becomes 'p': ``z0p5-10m``)."""
    _check_edges(range_edges)
    fmt = [f"{float(e):g}".replace(".", "p") for e in range_edges]
    return [f"z{a}-{b}m" for a, b in zip(fmt[:-1], fmt[1:])]


def depth_error_summary(
    counts: dict[str, np.ndarray], range_edges: tuple[float, ...] | list[float] = RANGE_EDGES_M
) -> dict[str, float]:
    """``<bin>_relerr_median``, ``<bin>_relerr_p90`` (fractions; NaN without valid pixels, ``inf``
    beyond the histogram), ``<bin>_valid_share`` (valid among GT pixels) and ``<bin>_gt_pixels``
    per range bin of accumulated :func:`depth_error_counts`."""
    out: dict[str, float] = {}
    for b, name in enumerate(range_bin_names(range_edges)):
        n_gt = float(counts["n_gt"][b])
        out[f"{name}_relerr_median"] = histogram_quantile(counts["hist"][b], 0.5)
        out[f"{name}_relerr_p90"] = histogram_quantile(counts["hist"][b], 0.9)
        out[f"{name}_valid_share"] = float(counts["n_valid"][b]) / n_gt if n_gt else float("nan")
        out[f"{name}_gt_pixels"] = int(n_gt)
    return out


def add_counts(a: dict[str, np.ndarray] | None, b: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Element-wise sum of two :func:`depth_error_counts` results (``a`` None = start)."""
    if a is None:
        return {k: v.copy() for k, v in b.items()}
    return {k: a[k] + b[k] for k in a}
