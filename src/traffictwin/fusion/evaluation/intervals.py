"""Cluster-bootstrap statistics of the fusion evaluation (:mod:`traffictwin.stats`; cluster =
scenario = ``pair_id // 1000``): one row's intervals, paired differences of two rows on their
common pairs, and the pooled Dice / AUROC(u) recomputed in each resample (same draws)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from traffictwin.fusion.evaluation.keys import scenario_of
from traffictwin.fusion.metrics import auroc_from_hist, prf
from traffictwin.stats import (
    CIConfig,
    Interval,
    mean_ci,
    paired_mean_difference_ci,
    resample_counts,
)

if TYPE_CHECKING:  # pandas loads where a table is built: check_params imports this package
    import pandas as pd


def ci_kwargs(ci: CIConfig) -> dict[str, float | int]:
    """``n_boot``, ``level``, ``seed`` of ``ci`` as keyword arguments of :mod:`traffictwin.stats`."""
    return {"n_boot": ci.n_boot, "level": ci.level, "seed": ci.seed}


def scenario_codes(pair_id: np.ndarray) -> tuple[np.ndarray, int]:
    """Dense scenario codes 0..G-1 of pairs (the order :func:`traffictwin.stats.mean_ci` uses)."""
    _, codes = np.unique(scenario_of(pair_id), return_inverse=True)
    codes = codes.reshape(-1)
    return codes, int(codes.max()) + 1 if codes.size else 0


def scenario_draws(n_groups: int, ci: CIConfig) -> np.ndarray:
    """(n_boot, G) resample counts of the scenarios: the same draws as ``stats.mean_ci`` (same seed)."""
    return resample_counts(n_groups, ci.n_boot, ci.seed)


def percentile_interval(estimate: float, boot: np.ndarray, level: float, n_groups: int) -> Interval:
    """Percentile interval of the finite bootstrap values ``boot`` (NaN bounds when none)."""
    boot = np.asarray(boot, dtype=np.float64)
    boot = boot[np.isfinite(boot)]
    if not boot.size:
        return Interval(float(estimate), math.nan, math.nan, level, n_groups)
    a = (1.0 - level) / 2.0
    lo, hi = np.quantile(boot, [a, 1.0 - a])
    return Interval(float(estimate), float(lo), float(hi), level, n_groups)


def pooled_dice(
    frame: pd.DataFrame, cls: str, codes: np.ndarray, n_groups: int, draws: np.ndarray
) -> tuple[float, np.ndarray]:
    """Pooled Dice of class ``cls`` (2TP / (2TP + FP + FN) over all pairs) and its value in each
    resample (``draws`` @ per-scenario sums of the per-pair counts)."""
    counts = [frame[f"{k}_{cls}"].to_numpy(np.float64) for k in ("tp", "fp", "fn")]
    sums = [np.bincount(codes, weights=v, minlength=n_groups) for v in counts]
    estimate = float(prf(*(v.sum() for v in counts))[2])
    return estimate, prf(*(draws @ g for g in sums))[2]


def _auroc_boot(
    pos: np.ndarray,
    neg: np.ndarray,
    codes: np.ndarray,
    n_groups: int,
    draws: np.ndarray,
    chunk: int = 256,
) -> np.ndarray:
    """AUROC of u in each resample from per-pair histograms ``pos``/``neg`` (N, bins): summed per
    scenario, then ``draws`` @ those sums (``chunk`` resamples at a time to bound memory)."""
    onehot = np.zeros((n_groups, len(codes)))
    onehot[codes, np.arange(len(codes))] = 1.0
    pg, ng = onehot @ np.asarray(pos, np.float64), onehot @ np.asarray(neg, np.float64)
    out = np.empty(len(draws))
    for s in range(0, len(draws), chunk):  # a few blocks of resamples, each vectorised
        out[s : s + chunk] = auroc_from_hist(draws[s : s + chunk] @ pg, draws[s : s + chunk] @ ng)
    return out


def row_intervals(
    frame: pd.DataFrame, pos: np.ndarray, neg: np.ndarray, ci: CIConfig
) -> dict[str, Interval]:
    """Cluster-bootstrap intervals of one row at one configuration, keyed by :data:`CI_KEYS`.

    ``frame``: its per-pair metrics with ``pair_id``; ``pos``/``neg``: per-pair histograms of u
    on wrong / right label-known cells (same order). KLD and u means: :func:`~traffictwin.stats.mean_ci`;
    Dice and AUROC(u) recomputed from the resampled per-scenario sums (same draws).
    """
    pid = frame["pair_id"].to_numpy(np.int64)
    groups = scenario_of(pid)
    kw = ci_kwargs(ci)
    out = {
        "kld_fou_mean": mean_ci(frame["kld_fou"].to_numpy(), groups, **kw),
        "kld_fo_mean": mean_ci(frame["kld_fo"].to_numpy(), groups, **kw),
        "u_mean": mean_ci(frame["u_mean"].to_numpy(), groups, **kw),
    }
    codes, g = scenario_codes(pid)
    draws = scenario_draws(g, ci)
    for cls in ("occ", "free"):
        est, boot = pooled_dice(frame, cls, codes, g, draws)
        out[f"dice_{cls}"] = percentile_interval(est, boot, ci.level, g)
    est = auroc_from_hist(np.sum(pos, axis=0), np.sum(neg, axis=0))
    boot = _auroc_boot(pos, neg, codes, g, draws)
    out["u_auroc"] = percentile_interval(est, boot, ci.level, g)
    if "reg_success" in frame:  # methods that estimate a pose
        out["success_rate"] = mean_ci(frame["reg_success"].to_numpy(np.float64), groups, **kw)
    return out


def paired_intervals(
    a: pd.DataFrame, b: pd.DataFrame, ci: CIConfig
) -> tuple[dict[str, Interval], int]:
    """Paired differences ``a − b`` of :data:`DIFF_KEYS` over the pairs both rows evaluated
    (matched by ``pair_id``), scenarios resampled together; and the number of common pairs."""
    common, ia, ib = np.intersect1d(
        a["pair_id"].to_numpy(np.int64), b["pair_id"].to_numpy(np.int64), return_indices=True
    )
    if not common.size:
        return {}, 0
    a, b = a.iloc[ia], b.iloc[ib]
    groups = scenario_of(common)
    kw = ci_kwargs(ci)
    out = {
        k: paired_mean_difference_ci(
            a[k.removesuffix("_mean")].to_numpy(),
            b[k.removesuffix("_mean")].to_numpy(),
            groups,
            **kw,
        )
        for k in ("kld_fou_mean", "kld_fo_mean")
    }
    codes, g = scenario_codes(common)
    draws = scenario_draws(g, ci)
    ea, ba = pooled_dice(a, "occ", codes, g, draws)
    eb, bb = pooled_dice(b, "occ", codes, g, draws)
    out["dice_occ"] = percentile_interval(ea - eb, ba - bb, ci.level, g)
    if "reg_success" in a and "reg_success" in b:  # both estimate a pose: success-rate difference
        out["success_rate"] = paired_mean_difference_ci(
            a["reg_success"].to_numpy(np.float64),
            b["reg_success"].to_numpy(np.float64),
            groups,
            **kw,
        )
    return out, int(common.size)


def lohi(iv: Interval) -> dict[str, float]:
    """An interval's bounds as fusion.json stores them: ``{lo, hi}``."""
    return {"lo": iv.lo, "hi": iv.hi}
