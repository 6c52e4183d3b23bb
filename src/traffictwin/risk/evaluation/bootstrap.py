"""Sequence-level (cluster) bootstrap of every metric (:class:`ClusterBootstrap`).

Every reported metric carries a sequence-level bootstrap interval. The test frames of one driving
sequence (frames.csv ``scenario``) are correlated, so whole sequences are resampled with
replacement (:func:`traffictwin.stats.resample_counts`: ``n_boot`` draws from ``seed``,
percentile interval at ``level``). One set of draws serves every predictor, so a difference
between two predictors is *paired* (both recomputed on the same resample). Each metric is a
function of per-sequence sums — squared errors, confusion counts, and for the ROC-AUC the
Mann–Whitney counts of every pair of sequences — so all resamples are a matrix product, not a
loop. A variant trained with several seeds is scored by the mean over its seeds of each metric,
resample by resample (:func:`mean_of_scores`, the seed-averaged metric).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from traffictwin.config import spec
from traffictwin.risk.evaluation.scoring import check_pair, primary
from traffictwin.risk.metric import risk_threshold, risk_to_thw
from traffictwin.stats import Interval, resample_counts

#: a statistic: (estimate on the test frames, (n_boot,) values on the resamples; NaN = undefined)
Stat = tuple[float, np.ndarray]


@dataclass
class CIConfig:
    """``evaluation.risk.ci``: ``n_boot`` resamples of the test sequences drawn from ``seed``;
    ``level``: the percentile interval's coverage (0.95 = 95 %)."""

    n_boot: int = spec(2000, min=100)
    seed: int = spec(0, min=0)
    level: float = spec(0.95, min=0.5, max=0.999)


class ClusterBootstrap:
    """One resampling plan for a set of test frames: the sequence (cluster) of each frame and
    ``n_boot`` draws of the sequences with replacement, shared by every predictor scored on
    these frames (so differences are paired). ``draws``: (n_boot, G) how often each sequence is
    drawn — the draws of :func:`traffictwin.stats.mean_ci` for the same seed."""

    def __init__(
        self, clusters: np.ndarray, n_boot: int = 2000, seed: int = 0, level: float = 0.95
    ) -> None:
        c = np.asarray(clusters).reshape(-1)
        if c.size == 0:
            raise ValueError("bootstrap: no test frames")
        _, codes = np.unique(c, return_inverse=True)
        self.clusters = c
        self.codes = codes.reshape(-1).astype(np.int64)
        self.n_groups = int(self.codes.max()) + 1
        self.n_boot, self.seed, self.level = int(n_boot), int(seed), float(level)
        self.draws = resample_counts(self.n_groups, self.n_boot, self.seed).astype(np.float64)

    @classmethod
    def from_config(cls, clusters: np.ndarray, ci: CIConfig) -> ClusterBootstrap:
        return cls(clusters, ci.n_boot, ci.seed, ci.level)

    @property
    def n(self) -> int:
        """Number of frames."""
        return int(self.codes.size)

    def subset(self, mask: np.ndarray) -> ClusterBootstrap:
        """The plan of the frames where ``mask`` holds (their sequences, fresh draws, same seed)."""
        return ClusterBootstrap(
            self.clusters[np.asarray(mask, bool)], self.n_boot, self.seed, self.level
        )

    def total(self, v: np.ndarray) -> Stat:
        """Sum of the per-frame values ``v`` over the frames and over each resample."""
        g = np.bincount(self.codes, weights=np.asarray(v, np.float64), minlength=self.n_groups)
        return float(g.sum()), self.draws @ g

    def interval(self, stat: Stat) -> Interval:
        """Percentile interval of the finite resampled values (NaN bounds when none or when the
        estimate itself is undefined)."""
        est, boot = float(stat[0]), np.asarray(stat[1], np.float64)
        boot = boot[np.isfinite(boot)]
        if not boot.size or not math.isfinite(est):
            return Interval(est, math.nan, math.nan, self.level, self.n_groups)
        a = (1.0 - self.level) / 2.0
        lo, hi = np.quantile(boot, [a, 1.0 - a])
        return Interval(est, float(lo), float(hi), self.level, self.n_groups)


def ratio(a: Stat, b: Stat, empty: float = math.nan) -> Stat:
    """a / b (``empty`` where b = 0)."""
    est = a[0] / b[0] if b[0] != 0 else empty
    with np.errstate(divide="ignore", invalid="ignore"):
        boot = np.where(b[1] != 0, a[1] / np.where(b[1] != 0, b[1], 1.0), empty)
    return float(est), boot


def lin(a: Stat, b: Stat, ca: float = 1.0, cb: float = 1.0) -> Stat:
    """ca·a + cb·b."""
    return ca * a[0] + cb * b[0], ca * a[1] + cb * b[1]


def _f1(prec: Stat, rec: Stat) -> Stat:
    """2PR / (P + R); 0 where P + R = 0, NaN where the recall is undefined."""
    num = (2.0 * prec[0] * rec[0], 2.0 * prec[1] * rec[1])
    f = ratio(num, lin(prec, rec), 0.0)
    est = math.nan if math.isnan(rec[0]) else f[0]
    return est, np.where(np.isnan(rec[1]), math.nan, f[1])


def _auc_stat(positive: np.ndarray, score: np.ndarray, plan: ClusterBootstrap) -> Stat:
    """ROC-AUC (Mann–Whitney, ties half) of ``score`` for ``positive`` and its resampled values.

    ``K[g, h]`` = the Mann–Whitney count of the positives of sequence g against the negatives of
    sequence h; a resample drawing sequence g ``d_g`` times has AUC ``dᵀ K d / ((d·n⁺)(d·n⁻))``.
    """
    pos = np.asarray(positive, bool)
    s = np.asarray(score, np.float64)
    g, codes = plan.n_groups, plan.codes
    n_pos = np.bincount(codes[pos], minlength=g).astype(np.float64)
    n_neg = np.bincount(codes[~pos], minlength=g).astype(np.float64)
    if not n_pos.sum() or not n_neg.sum():
        return math.nan, np.full(plan.n_boot, math.nan)
    neg_codes, neg_s = codes[~pos], s[~pos]
    order = np.lexsort((neg_s, neg_codes))  # negatives sorted by sequence, then score
    neg_codes, neg_s = neg_codes[order], neg_s[order]
    bounds = np.searchsorted(neg_codes, np.arange(g + 1))
    sp, gp = s[pos], codes[pos]
    k = np.zeros((g, g))
    for h in np.flatnonzero(n_neg):  # one vectorised count per sequence (not per frame)
        neg = neg_s[bounds[h] : bounds[h + 1]]
        lo = np.searchsorted(neg, sp, "left")
        hi = np.searchsorted(neg, sp, "right")
        k[:, h] = np.bincount(gp, weights=lo + 0.5 * (hi - lo), minlength=g)
    d = plan.draws
    est = float(k.sum() / (n_pos.sum() * n_neg.sum()))
    num = np.einsum("bg,gh,bh->b", d, k, d, optimize=True)
    den = (d @ n_pos) * (d @ n_neg)
    with np.errstate(divide="ignore", invalid="ignore"):
        boot = np.where(den > 0, num / np.where(den > 0, den, 1.0), math.nan)
    return est, boot


def bootstrap_scores(
    y: np.ndarray,
    p: np.ndarray,
    plan: ClusterBootstrap,
    thresholds_s: Sequence[float],
    thw_cap: float = 10.0,
    cuts: Mapping[float, float] | None = None,
) -> dict[str, Stat]:
    """Every reported metric of predictions ``p`` for labels ``y`` (normalised risk, on the frames
    of ``plan``) as :data:`Stat`, keyed like :func:`evaluate`'s dict with ``|`` between levels
    (``test/mse``, ``at_1.5s|roc_auc``, ...). The estimates equal :func:`evaluate`'s values
    (with the same decision ``cuts``)."""
    y, p = check_pair(y, p)
    if y.size != plan.n:
        raise ValueError(f"bootstrap: {y.size} predictions for a plan of {plan.n} frames")
    n = plan.total(np.ones_like(y))
    e = p - y
    mse = ratio(plan.total(e * e), n)
    dt = np.abs(risk_to_thw(p, thw_cap) - risk_to_thw(y, thw_cap))
    crit = (y > risk_threshold(primary(thresholds_s))).astype(np.float64)
    out: dict[str, Stat] = {
        "test/mse": mse,
        "test/mae": ratio(plan.total(np.abs(e)), n),
        "test/rmse": (math.sqrt(mse[0]), np.sqrt(mse[1])),
        "test/thw_mae_s": ratio(plan.total(dt), n),
        "test/thw_mae_critical_s": ratio(plan.total(dt * crit), plan.total(crit)),
        "test/thw_median_error_critical_s": weighted_median_stat(dt, crit > 0, plan),
    }
    for t in thresholds_s:
        thr = risk_threshold(t)
        cut = (cuts or {}).get(t, thr)
        a, b = y > thr, p > cut
        tp, fp, fn, tn = (
            plan.total(m.astype(np.float64)) for m in (a & b, ~a & b, a & ~b, ~a & ~b)
        )
        prec = ratio(tp, lin(tp, fp), 0.0)
        rec = ratio(tp, lin(tp, fn))
        spec_ = ratio(tn, lin(tn, fp))
        at = f"at_{t:g}s|"
        out.update(
            {
                at + "accuracy": ratio(lin(tp, tn), n),
                at + "balanced_accuracy": lin(rec, spec_, 0.5, 0.5),
                at + "precision": prec,
                at + "recall": rec,
                at + "specificity": spec_,
                at + "f1": _f1(prec, rec),
                at + "roc_auc": _auc_stat(a, p, plan),
                at + "critical_fraction_true": ratio(plan.total(a.astype(np.float64)), n),
                at + "critical_fraction_pred": ratio(plan.total(b.astype(np.float64)), n),
            }
        )
    return out


def weighted_median_stat(v: np.ndarray, mask: np.ndarray, plan: ClusterBootstrap) -> Stat:
    """Median of ``v`` over the frames where ``mask`` holds, and on each resample (a frame counts
    as often as its sequence is drawn; the lower median of the weighted values)."""
    m = np.asarray(mask, bool)
    if not m.any():
        return math.nan, np.full(plan.n_boot, math.nan)
    vals = np.asarray(v, np.float64)[m]
    order = np.argsort(vals, kind="stable")
    vals = vals[order]
    w = plan.draws[:, plan.codes[m][order]]  # (n_boot, n) weight of each sorted value
    cum = np.cumsum(w, axis=1)
    tot = cum[:, -1:]
    idx = np.argmax(cum >= 0.5 * tot, axis=1)
    boot = np.where(tot[:, 0] > 0, vals[idx], math.nan)
    return float(np.median(vals)), boot


def spread_stat(p: np.ndarray, plan: ClusterBootstrap) -> Stat:
    """Standard deviation of the predictions ``p`` over the frames (and each resample)."""
    p = np.asarray(p, np.float64)
    p = p - p.mean()  # centred: no cancellation for (near-)constant predictions
    n = plan.total(np.ones_like(p))
    m1, m2 = ratio(plan.total(p), n), ratio(plan.total(p * p), n)
    var = lin(m2, (m1[0] ** 2, m1[1] ** 2), 1.0, -1.0)
    return math.sqrt(max(var[0], 0.0)), np.sqrt(np.maximum(var[1], 0.0))


def mean_of_scores(
    runs: Sequence[Mapping[str, Stat]], seed_draws: np.ndarray | None = None
) -> dict[str, Stat]:
    """The seed-averaged metric: mean over runs (seeds) of each metric, resample by resample
    (every run scored on the same plan). ``seed_draws`` (n_boot, R): how often each run is drawn
    in each resample (seeds resampled with replacement, so training randomness is in the
    interval: the bootstrap over seeds × sequences); ``None`` = every run once."""
    if not runs:
        raise ValueError("mean_of_scores: no runs")
    out: dict[str, Stat] = {}
    for k in runs[0]:
        boots = np.stack([r[k][1] for r in runs])  # (R, n_boot)
        if seed_draws is None:
            boot = np.mean(boots, axis=0)
        else:
            w = np.asarray(seed_draws, np.float64).T  # (R, n_boot)
            if w.shape != boots.shape:
                raise ValueError(
                    f"seed_draws {w.T.shape} for {len(runs)} runs × {boots.shape[1]} resamples"
                )
            with np.errstate(invalid="ignore"):
                boot = np.sum(np.where(w > 0, boots, 0.0) * w, axis=0) / w.sum(axis=0)
        out[k] = (float(np.mean([r[k][0] for r in runs])), boot)
    return out


def seed_draws(n_runs: int, plan: ClusterBootstrap, stream: int = 1) -> np.ndarray:
    """(n_boot, n_runs) draws of the runs (seeds) with replacement, one row per resample of
    ``plan``, from the plan's seed + ``stream`` (deterministic; independent of the sequence draws)."""
    return resample_counts(n_runs, plan.n_boot, plan.seed + 7919 * stream).astype(np.float64)


def difference_of_scores(a: Mapping[str, Stat], b: Mapping[str, Stat]) -> dict[str, Stat]:
    """Paired difference a − b of every metric both have (same plan, same resamples)."""
    return {k: (a[k][0] - b[k][0], a[k][1] - b[k][1]) for k in a if k in b}


def _nest(flat: Mapping[str, Any]) -> dict[str, Any]:
    """``{"at_1.5s|f1": v}`` → ``{"at_1.5s": {"f1": v}}``."""
    out: dict[str, Any] = {}
    for k, v in flat.items():
        sec, _, name = k.rpartition("|")
        (out.setdefault(sec, {}) if sec else out)[name] = v
    return out


def lohi(iv: Interval) -> dict[str, float]:
    """An interval's bounds as ``{lo, hi}`` (the ``<metric>_ci`` entries of risk.json)."""
    return {"lo": iv.lo, "hi": iv.hi}


def scores_with_ci(
    scores: Mapping[str, Stat], plan: ClusterBootstrap, into: dict[str, Any] | None = None
) -> dict[str, Any]:
    """Nested metrics dict with ``<metric>`` (the estimate) and ``<metric>_ci`` {lo, hi} for every
    score; ``into``: an existing dict (e.g. :func:`evaluate`'s) to add the intervals to."""
    out = into if into is not None else {}
    for k, st in scores.items():
        iv = plan.interval(st)
        sec, _, name = k.rpartition("|")
        d = out.setdefault(sec, {}) if sec else out
        d.setdefault(name, iv.estimate)
        d[f"{name}_ci"] = lohi(iv)
    return out


def bootstrap_p(boot: np.ndarray) -> float:
    """Two-sided bootstrap p-value of "the difference is 0": twice the smaller share of the
    finite resampled differences on either side of 0 (capped at 1; NaN without resamples)."""
    b = np.asarray(boot, np.float64)
    b = b[np.isfinite(b)]
    if not b.size:
        return math.nan
    return float(min(1.0, 2.0 * min(np.mean(b <= 0.0), np.mean(b >= 0.0))))


def holm(pvalues: Mapping[str, float]) -> dict[str, float]:
    """Holm–Bonferroni adjusted p-values (family-wise error) of the finite ``pvalues``:
    the i-th smallest of m becomes max over j <= i of min(1, (m − j + 1)·p_(j))."""
    items = sorted(
        ((k, float(v)) for k, v in pvalues.items() if math.isfinite(v)), key=lambda kv: kv[1]
    )
    m, run, out = len(items), 0.0, {}
    for i, (k, v) in enumerate(items):
        run = max(run, min(1.0, (m - i) * v))
        out[k] = run
    return out


def difference_json(diff: Mapping[str, Stat], plan: ClusterBootstrap) -> dict[str, Any]:
    """Nested ``{metric: {estimate, lo, hi, p}}`` of paired differences (a − b); ``p``: the
    two-sided bootstrap p-value (:func:`bootstrap_p`)."""
    flat = {}
    for k, st in diff.items():
        iv = plan.interval(st)
        flat[k] = {"estimate": iv.estimate, "lo": iv.lo, "hi": iv.hi, "p": bootstrap_p(st[1])}
    return _nest(flat)
