"""Shared statistics: cluster (scenario / sequence) bootstrap confidence intervals.

Test samples of one scenario or driving sequence are correlated (neighbouring frames, the pairs
of one encounter), so intervals resample *groups* with replacement, never single samples. Every
method of a comparison is evaluated on the same samples: a difference between two methods is
bootstrapped *paired*, with the same group draws for both. A difference is a finding only when
its interval excludes zero (:func:`excludes_zero`).

Intervals are percentile intervals of ``n_boot`` resamples drawn from ``numpy.random.default_rng(seed)``,
so they are deterministic for a seed.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import MISSING, dataclass

import numpy as np

from traffictwin.config import spec


@dataclass(frozen=True)
class Interval:
    """A point estimate with its bootstrap ``level`` interval ``[lo, hi]`` (same units as the data)."""

    estimate: float
    lo: float
    hi: float
    level: float = 0.95
    n_groups: int = 0

    def as_dict(self) -> dict[str, float]:
        return {
            "estimate": self.estimate,
            "lo": self.lo,
            "hi": self.hi,
            "level": self.level,
            "n_groups": self.n_groups,
        }


@dataclass
class CIConfig:
    """Bootstrap settings of an evaluation's intervals (``evaluation.fusion_ci``, ``twin.ci``):
    ``n_boot`` resamples of the clusters drawn from ``seed``; ``level`` the interval's coverage
    (0.95 = 95 % percentile interval)."""

    n_boot: int = spec(MISSING, min=100)
    seed: int = spec(MISSING, min=0)
    level: float = spec(MISSING, min=0.5, max=0.999)


def excludes_zero(ci: Interval) -> bool:
    """True when the interval lies wholly above or below 0 (a finding, not noise)."""
    return bool(ci.lo > 0 or ci.hi < 0)


def _group_index(n: int, groups: np.ndarray | None) -> tuple[np.ndarray, int]:
    """Dense group codes 0..G-1 for ``n`` samples (each sample its own group when ``groups`` is None)."""
    if groups is None:
        return np.arange(n), n
    groups = np.asarray(groups)
    if groups.shape != (n,):
        raise ValueError(f"groups: expected one label per sample ({n}), got shape {groups.shape}")
    _, codes = np.unique(groups, return_inverse=True)
    return codes.reshape(-1), int(codes.max()) + 1 if n else 0


def resample_counts(n_groups: int, n_boot: int, seed: int) -> np.ndarray:
    """(n_boot, G) how often each group is drawn in each resample (G draws with replacement)."""
    rng = np.random.default_rng(seed)
    return rng.multinomial(n_groups, np.full(n_groups, 1.0 / n_groups), size=n_boot)


def _check(values: np.ndarray, name: str) -> np.ndarray:
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    if v.size == 0:
        raise ValueError(f"{name}: no samples to bootstrap")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{name}: {int((~np.isfinite(v)).sum())} non-finite values")
    return v


def mean_ci(
    values: np.ndarray,
    groups: np.ndarray | None = None,
    *,
    n_boot: int = 2000,
    level: float = 0.95,
    seed: int = 0,
) -> Interval:
    """Mean of ``values`` with a cluster-bootstrap interval (groups resampled, vectorised)."""
    v = _check(values, "values")
    codes, g = _group_index(v.size, groups)
    sums = np.bincount(codes, weights=v, minlength=g)
    counts = np.bincount(codes, minlength=g).astype(np.float64)
    draws = resample_counts(g, n_boot, seed)
    boot = (draws @ sums) / np.maximum(draws @ counts, 1e-12)
    a = (1.0 - level) / 2.0
    lo, hi = np.quantile(boot, [a, 1.0 - a])
    return Interval(float(v.mean()), float(lo), float(hi), level, g)


def paired_mean_difference_ci(
    a: np.ndarray,
    b: np.ndarray,
    groups: np.ndarray | None = None,
    *,
    n_boot: int = 2000,
    level: float = 0.95,
    seed: int = 0,
) -> Interval:
    """Mean of ``a - b`` over the same samples, groups resampled together (a paired comparison)."""
    a = _check(a, "a")
    b = _check(b, "b")
    if a.shape != b.shape:
        raise ValueError(f"paired samples differ in length: {a.size} vs {b.size}")
    return mean_ci(a - b, groups, n_boot=n_boot, level=level, seed=seed)


def statistic_ci(
    stat: Callable[[np.ndarray], float],
    n: int,
    groups: np.ndarray | None = None,
    *,
    n_boot: int = 1000,
    level: float = 0.95,
    seed: int = 0,
) -> Interval:
    """Any statistic of a sample set (e.g. ROC-AUC, balanced accuracy) with a cluster-bootstrap interval.

    ``stat(idx)`` computes the statistic on the samples ``idx`` (an index array into the data it
    closes over), so paired comparisons compute both methods on the same ``idx``. Resamples whose
    statistic is undefined (NaN, e.g. one class missing) are dropped.
    """
    codes, g = _group_index(n, groups)
    members = np.argsort(codes, kind="stable")
    starts = np.searchsorted(codes[members], np.arange(g + 1))
    rng = np.random.default_rng(seed)
    boot = np.empty(n_boot)
    for i in range(n_boot):  # one statistic per resample (not per sample)
        picked = rng.integers(0, g, size=g)
        idx = np.concatenate([members[starts[k] : starts[k + 1]] for k in picked])
        boot[i] = stat(idx)
    boot = boot[np.isfinite(boot)]
    est = float(stat(np.arange(n)))
    if boot.size == 0:
        return Interval(est, float("nan"), float("nan"), level, g)
    a = (1.0 - level) / 2.0
    lo, hi = np.quantile(boot, [a, 1.0 - a])
    return Interval(est, float(lo), float(hi), level, g)
