"""Metrics for the risk network (Feth et al., sec. 4) and the evaluation of several predictors.

Risk scale (docs/design.md "Risk metric"; the conversions live in :mod:`traffictwin.risk.metric`):
``risk = min(1 / THW, 20) / 20``; no vehicle ahead or speed 0 → risk 0. A situation is *critical*
when THW < t (paper: t = 1.5 s), i.e. when ``risk > risk_threshold(t)`` (= 1/30 at 1.5 s, 1/20 at
1.0 s).

Reported per predictor against a label column: MSE and MAE of the normalised risk (the paper's
"testing average error" is the MSE: 0.01470), the THW error in seconds (risk → THW, both capped at
``thw_cap`` s so "no vehicle" is finite), and at each threshold the confusion matrix laid out as
the paper's Table 1 (rows predicted, columns actual), accuracy (paper 72.87 %; Wang & Kato 70.77 %),
balanced accuracy, precision/recall/specificity/F1 of the critical class and ROC-AUC of the
predicted risk as a score for "critical". Recall (specificity) is undefined without actual
critical (uncritical) frames; precision is 0 without predicted critical frames.

Statistics (:class:`ClusterBootstrap`): every reported metric carries a sequence-level bootstrap
interval. The test frames of one driving sequence (frames.csv ``scenario``) are correlated, so
whole sequences are resampled with replacement (:func:`traffictwin.stats.resample_counts`:
``n_boot`` draws from ``seed``, percentile interval at ``level``). One set of draws serves every
predictor, so a difference between two predictors is *paired* (both recomputed on the same
resample). Each metric is a function of per-sequence sums — squared errors, confusion counts,
and for the ROC-AUC the Mann–Whitney counts of every pair of sequences — so all resamples are a
matrix product, not a loop. A variant trained with several seeds (``replicate_of``) is scored by
the mean over its seeds of each metric, resample by resample (the seed-averaged metric).
A model whose test predictions have a standard deviation below ``collapse_std`` is *collapsed*
(one output for every frame): it is reported as a failed run and never interpreted.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from itertools import combinations
from typing import Any

import numpy as np

from traffictwin.config import spec
from traffictwin.io.jsonio import json_clean
from traffictwin.risk.baselines import constant_predictions, fit_speed_only, geometric_risk
from traffictwin.risk.dataset import SPLITS
from traffictwin.risk.metric import CRITICAL_THW, risk_threshold, risk_to_thw
from traffictwin.stats import Interval, mean_ci, resample_counts

#: the paper's figures (sec. 4, Table 1) and the related work's best accuracy
PAPER = {
    "test/mse": 0.01470,
    "accuracy": 0.7287,
    "wang_kato_accuracy": 0.7077,
    "threshold_s": 1.5,
    "confusion": {"tp": 67052, "fp": 19069, "fn": 9737, "tn": 10312},
    "n_frames": 106170,
}
#: default THW thresholds (s): the paper's critical threshold first, then 1 s
THRESHOLDS_S = (CRITICAL_THW, 1.0)
#: label columns of the three regions (docs/design.md "Risk metric"), the headline corridor first
REGION_LABELS = ("risk_thw_corridor", "risk_thw_paper", "risk_thw_fov")
#: metrics where lower is better (every other reported metric: higher is better)
LOWER_IS_BETTER = (
    "test/mse",
    "test/mae",
    "test/rmse",
    "test/thw_mae_s",
    "test/thw_mae_critical_s",
    "test/thw_median_error_critical_s",
)
#: baselines, in report order; ``geometric_gt``: the corridor rule on ground-truth disparity
BASELINES = ("train_mean", "train_median", "speed_only", "geometric_sgm", "geometric_gt")
#: predictors fed ground-truth disparity (not available at inference): a reference, not an oracle —
#: the corridor rule's straight band is not the true (curved) corridor of the label
GT_INPUT = ("geometric_gt",)
#: oracles (true geometry along the true corridor): none is evaluated
ORACLES: tuple[str, ...] = ()
#: suffix of a variant's seed-averaged predictor (the variant and its ``replicate_of`` runs)
SEED_MEAN = "[seed_mean]"


def regression_metrics(y: np.ndarray, p: np.ndarray, thw_cap: float = 10.0) -> dict[str, float]:
    """``test/mse``, ``test/mae``, ``test/rmse`` (normalised risk) and THW errors in s (capped)."""
    y, p = _check(y, p)
    e = p - y
    ty, tp = risk_to_thw(y, thw_cap), risk_to_thw(p, thw_cap)
    crit = y > risk_threshold(CRITICAL_THW)
    return {
        "test/mse": float(np.mean(e**2)),
        "test/mae": float(np.mean(np.abs(e))),
        "test/rmse": float(np.sqrt(np.mean(e**2))),
        "test/thw_mae_s": float(np.mean(np.abs(tp - ty))),
        "test/thw_mae_critical_s": float(np.mean(np.abs(tp - ty)[crit]))
        if crit.any()
        else float("nan"),
        "test/thw_median_error_critical_s": float(np.median(np.abs(tp - ty)[crit]))
        if crit.any()
        else float("nan"),
        "test/n": int(len(y)),
    }


def classification_metrics(
    y: np.ndarray, p: np.ndarray, thw_s: float = CRITICAL_THW, cut: float | None = None
) -> dict[str, Any]:
    """Critical-vs-uncritical metrics at THW threshold ``thw_s``; the critical class is positive.
    A frame is predicted critical when ``p > cut`` (the predictor's decision threshold chosen on
    validation, :mod:`traffictwin.risk.selection`; default: the label's own ``risk_threshold``)."""
    y, p = _check(y, p)
    thr = risk_threshold(thw_s)
    cut = thr if cut is None else float(cut)
    a, b = y > thr, p > cut
    tp, fp = int(np.sum(a & b)), int(np.sum(~a & b))
    fn, tn = int(np.sum(a & ~b)), int(np.sum(~a & ~b))
    n = max(len(y), 1)
    nan = float("nan")
    prec = tp / (tp + fp) if tp + fp else 0.0
    rec = tp / (tp + fn) if tp + fn else nan  # undefined without actual critical frames
    spec = tn / (tn + fp) if tn + fp else nan
    f1 = nan if math.isnan(rec) else (2 * prec * rec / (prec + rec) if prec + rec else 0.0)
    if a.all() or not a.any():
        bal = float("nan")
        auc = float("nan")  # undefined with a single actual class
    else:
        bal = 0.5 * (rec + spec)
        auc = roc_auc(a, p)
    return {
        "threshold_s": float(thw_s),
        "risk_threshold": float(thr),
        "decision_cut": float(cut),
        "confusion": {"tp": tp, "fp": fp, "fn": fn, "tn": tn},
        "confusion_pct": {
            k: 100.0 * v / n for k, v in {"tp": tp, "fp": fp, "fn": fn, "tn": tn}.items()
        },
        "accuracy": (tp + tn) / n,
        "balanced_accuracy": bal,
        "precision": prec,
        "recall": rec,
        "specificity": spec,
        "f1": f1,
        "roc_auc": auc,
        "critical_fraction_true": float(np.mean(a)) if len(a) else float("nan"),
        "critical_fraction_pred": float(np.mean(b)) if len(b) else float("nan"),
    }


def roc_auc(positive: np.ndarray, score: np.ndarray) -> float:
    """Area under the ROC curve (ties count half; the Mann–Whitney U statistic), NaN for one class."""
    positive = np.asarray(positive, bool)
    score = np.asarray(score, np.float64)
    n_pos, n_neg = int(positive.sum()), int((~positive).sum())
    if n_pos == 0 or n_neg == 0:
        return float("nan")
    from scipy.stats import rankdata

    ranks = rankdata(score)  # average ranks for ties
    return float((ranks[positive].sum() - n_pos * (n_pos + 1) / 2) / (n_pos * n_neg))


def roc_curve(positive: np.ndarray, score: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """ROC points ``(fpr, tpr)`` from (0, 0) to (1, 1), one per distinct score (descending); the
    trapezoid area under them is :func:`roc_auc` (ties count half). Empty arrays for one class."""
    pos = np.asarray(positive, bool).ravel()
    s = np.asarray(score, np.float64).ravel()
    n_pos, n_neg = int(pos.sum()), int((~pos).sum())
    if n_pos == 0 or n_neg == 0:
        return np.zeros(0), np.zeros(0)
    order = np.argsort(-s, kind="stable")
    s, pos = s[order], pos[order]
    last = np.r_[np.flatnonzero(np.diff(s)), s.size - 1]  # last frame of each distinct score
    tps, fps = np.cumsum(pos)[last], np.cumsum(~pos)[last]
    return np.r_[0.0, fps / n_neg], np.r_[0.0, tps / n_pos]


def evaluate(
    y: np.ndarray,
    p: np.ndarray,
    thresholds_s: Sequence[float] = THRESHOLDS_S,
    thw_cap: float = 10.0,
    cuts: Mapping[float, float] | None = None,
) -> dict[str, Any]:
    """Regression metrics plus ``at_<t>s`` classification metrics for every threshold (decision
    cut ``cuts[t]`` where given)."""
    out: dict[str, Any] = regression_metrics(y, p, thw_cap)
    for t in thresholds_s:
        out[f"at_{t:g}s"] = classification_metrics(y, p, t, (cuts or {}).get(t))
    return out


def confusion_labels(
    y: np.ndarray, p: np.ndarray, thw_s: float = CRITICAL_THW
) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame class names (``critical``/``uncritical``) of actual and predicted risk."""
    thr = risk_threshold(thw_s)
    names = np.array(["uncritical", "critical"])
    return names[(np.asarray(y) > thr).astype(int)], names[(np.asarray(p) > thr).astype(int)]


def label_agreement(
    a: np.ndarray, b: np.ndarray, thresholds_s: Sequence[float] = THRESHOLDS_S
) -> dict[str, Any]:
    """How two label columns (e.g. paper vs camera_fov region) differ: MSE and class agreement."""
    a, b = _check(a, b)
    out: dict[str, Any] = {
        "mse": float(np.mean((a - b) ** 2)),
        "fraction_equal": float(np.mean(np.isclose(a, b))),
    }
    for t in thresholds_s:
        thr = risk_threshold(t)
        out[f"class_agreement_at_{t:g}s"] = float(np.mean((a > thr) == (b > thr)))
    return out


def _check(y: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    y = np.asarray(y, np.float64).ravel()
    p = np.asarray(p, np.float64).ravel()
    if y.shape != p.shape:
        raise ValueError(f"labels and predictions differ in length: {y.shape} vs {p.shape}")
    if len(y) == 0:
        raise ValueError("no frames to evaluate (empty test split after the ORB check?)")
    if not (np.all(np.isfinite(y)) and np.all(np.isfinite(p))):
        raise ValueError("labels/predictions contain non-finite values")
    return y, p


def summarise_paper_comparison(metrics: Mapping[str, Any]) -> dict[str, float]:
    """Differences to the paper for one predictor's metrics (positive = worse MSE / better accuracy)."""
    at = metrics.get(f"at_{CRITICAL_THW:g}s", {})
    return {
        "mse_minus_paper": float(metrics["test/mse"]) - PAPER["test/mse"],
        "accuracy_minus_paper": float(at.get("accuracy", float("nan"))) - PAPER["accuracy"],
        "accuracy_minus_wang_kato": float(at.get("accuracy", float("nan")))
        - PAPER["wang_kato_accuracy"],
    }


# --------------------------------------------------------------------------------------------
# sequence-level (cluster) bootstrap of every metric
# --------------------------------------------------------------------------------------------

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


def _div(a: Stat, b: Stat, empty: float = math.nan) -> Stat:
    """a / b (``empty`` where b = 0)."""
    est = a[0] / b[0] if b[0] != 0 else empty
    with np.errstate(divide="ignore", invalid="ignore"):
        boot = np.where(b[1] != 0, a[1] / np.where(b[1] != 0, b[1], 1.0), empty)
    return float(est), boot


def _lin(a: Stat, b: Stat, ca: float = 1.0, cb: float = 1.0) -> Stat:
    """ca·a + cb·b."""
    return ca * a[0] + cb * b[0], ca * a[1] + cb * b[1]


def _f1(prec: Stat, rec: Stat) -> Stat:
    """2PR / (P + R); 0 where P + R = 0, NaN where the recall is undefined."""
    num = (2.0 * prec[0] * rec[0], 2.0 * prec[1] * rec[1])
    f = _div(num, _lin(prec, rec), 0.0)
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
    thresholds_s: Sequence[float] = THRESHOLDS_S,
    thw_cap: float = 10.0,
    cuts: Mapping[float, float] | None = None,
) -> dict[str, Stat]:
    """Every reported metric of predictions ``p`` for labels ``y`` (normalised risk, on the frames
    of ``plan``) as :data:`Stat`, keyed like :func:`evaluate`'s dict with ``|`` between levels
    (``test/mse``, ``at_1.5s|roc_auc``, ...). The estimates equal :func:`evaluate`'s values
    (with the same decision ``cuts``)."""
    y, p = _check(y, p)
    if y.size != plan.n:
        raise ValueError(f"bootstrap: {y.size} predictions for a plan of {plan.n} frames")
    n = plan.total(np.ones_like(y))
    e = p - y
    mse = _div(plan.total(e * e), n)
    dt = np.abs(risk_to_thw(p, thw_cap) - risk_to_thw(y, thw_cap))
    crit = (y > risk_threshold(CRITICAL_THW)).astype(np.float64)
    out: dict[str, Stat] = {
        "test/mse": mse,
        "test/mae": _div(plan.total(np.abs(e)), n),
        "test/rmse": (math.sqrt(mse[0]), np.sqrt(mse[1])),
        "test/thw_mae_s": _div(plan.total(dt), n),
        "test/thw_mae_critical_s": _div(plan.total(dt * crit), plan.total(crit)),
        "test/thw_median_error_critical_s": weighted_median_stat(dt, crit > 0, plan),
    }
    for t in thresholds_s:
        thr = risk_threshold(t)
        cut = (cuts or {}).get(t, thr)
        a, b = y > thr, p > cut
        tp, fp, fn, tn = (
            plan.total(m.astype(np.float64)) for m in (a & b, ~a & b, a & ~b, ~a & ~b)
        )
        prec = _div(tp, _lin(tp, fp), 0.0)
        rec = _div(tp, _lin(tp, fn))
        spec_ = _div(tn, _lin(tn, fp))
        at = f"at_{t:g}s|"
        out.update(
            {
                at + "accuracy": _div(_lin(tp, tn), n),
                at + "balanced_accuracy": _lin(rec, spec_, 0.5, 0.5),
                at + "precision": prec,
                at + "recall": rec,
                at + "specificity": spec_,
                at + "f1": _f1(prec, rec),
                at + "roc_auc": _auc_stat(a, p, plan),
                at + "critical_fraction_true": _div(plan.total(a.astype(np.float64)), n),
                at + "critical_fraction_pred": _div(plan.total(b.astype(np.float64)), n),
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
    m1, m2 = _div(plan.total(p), n), _div(plan.total(p * p), n)
    var = _lin(m2, (m1[0] ** 2, m1[1] ** 2), 1.0, -1.0)
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


def _g(d: Any, *keys: str) -> Any:
    """``d[k0][k1]...`` or ``None``."""
    for k in keys:
        if not isinstance(d, Mapping) or k not in d:
            return None
        d = d[k]
    return d


def _nest(flat: Mapping[str, Any]) -> dict[str, Any]:
    """``{"at_1.5s|f1": v}`` → ``{"at_1.5s": {"f1": v}}``."""
    out: dict[str, Any] = {}
    for k, v in flat.items():
        sec, _, name = k.rpartition("|")
        (out.setdefault(sec, {}) if sec else out)[name] = v
    return out


def _lohi(iv: Interval) -> dict[str, float]:
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
        d[f"{name}_ci"] = _lohi(iv)
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


# --------------------------------------------------------------------------------------------
# the whole evaluation: networks + baselines on the same test frames
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Target:
    """A target of issue 16 (default profile, test split, headline): ``op`` compares the value
    (or, with ``ci_required``, the whole interval) with ``threshold``."""

    description: str
    threshold: float
    op: str
    ci_required: bool = False


TARGETS: dict[str, Target] = {
    # the predictor users get (models/risk/shipped, chosen on validation), issue 31
    "shipped_balanced_accuracy_1.5s": Target(
        "balanced accuracy of the shipped predictor at THW 1.5 s", 0.95, ">="
    ),
    "shipped_balanced_accuracy_1s": Target(
        "balanced accuracy of the shipped predictor at THW 1.0 s", 0.90, ">="
    ),
    "shipped_roc_auc": Target("ROC-AUC of the shipped predictor at THW 1.5 s", 0.97, ">="),
    "shipped_recall_pedestrian": Target(
        "recall of the shipped predictor at THW 1.5 s, pedestrian situations", 0.85, ">="
    ),
    "shipped_recall_cut_in": Target(
        "recall of the shipped predictor at THW 1.5 s, cut-in situations", 0.85, ">="
    ),
    "shipped_thw_median_error_critical_s": Target(
        "median |THW error| (s) of the shipped predictor on truly critical frames (THW < 1.5 s)",
        0.2,
        "<=",
    ),
    # the learned model (best group on validation, seeds resampled) vs the validation-tuned rule
    "learned_vs_rule_auc": Target(
        "ROC-AUC learned − SGM corridor rule (paired, seeds × sequences): interval wholly above 0",
        0.0,
        ">",
        True,
    ),
    "learned_vs_rule_balanced_accuracy": Target(
        "balanced accuracy learned − SGM corridor rule (paired, seeds × sequences): interval wholly above 0",
        0.0,
        ">",
        True,
    ),
    "auc_vs_speed_only": Target(
        "ROC-AUC learned − speed-only baseline (paired): interval wholly above 0", 0.0, ">", True
    ),
    "holdout_balanced_accuracy_drop": Target(
        "balanced accuracy drop: the hybrid on the standard test split − the hybrid trained without "
        "the held-out road templates on their test frames",
        0.05,
        "<=",
    ),
    "spread": Target(
        "smallest standard deviation of a trained variant's test predictions (no collapsed model)",
        math.nan,
        ">=",
    ),
}


def judge(iv: Interval, target: Target, threshold: float | None = None) -> dict[str, Any]:
    """``value``, ``lo``, ``hi``, ``met`` (the estimate — or, for ``ci_required``, the lower /
    upper bound — on the target's side) and ``ci_beyond_threshold`` (the whole interval there)."""
    thr = target.threshold if threshold is None else threshold
    e, lo, hi = iv.estimate, iv.lo, iv.hi
    out: dict[str, Any] = {"value": e, "lo": lo, "hi": hi, "threshold": thr, "op": target.op}
    if not math.isfinite(e):
        return {**out, "met": False, "ci_beyond_threshold": False, "why": "undefined"}
    side = {
        ">=": lambda v: v >= thr,
        ">": lambda v: v > thr,
        "<=": lambda v: v <= thr,
        "<": lambda v: v < thr,
    }[target.op]
    bound = lo if target.op in (">=", ">") else hi
    beyond = math.isfinite(bound) and side(bound)
    met = beyond if target.ci_required else side(e)
    return {**out, "met": bool(met), "ci_beyond_threshold": bool(beyond)}


def _variant_groups(
    variants: Sequence[str], replicate_of: Mapping[str, str | None]
) -> dict[str, list[str]]:
    """Base variant → its evaluated runs (the base first, then its replicates in order); chains of
    ``replicate_of`` resolve to the root."""

    def root(v: str) -> str:
        seen = {v}
        while replicate_of.get(v):
            v = str(replicate_of[v])
            if v in seen:
                raise ValueError(f"risk_model.variants: replicate_of forms a cycle at '{v}'")
            seen.add(v)
        return v

    groups: dict[str, list[str]] = {}
    for v in variants:
        groups.setdefault(root(v), []).append(v)
    for b, members in groups.items():
        members.sort(key=lambda m: (m != b, variants.index(m)))
    return groups


def critical_shares(
    frames: Any, labels: Sequence[str], threshold_s: float = CRITICAL_THW
) -> dict[str, Any]:
    """Critical share (risk > threshold) of each label column per split and over all frames of
    ``frames`` (frames.csv), with the frame and sequence counts."""
    thr = risk_threshold(threshold_s)
    out: dict[str, Any] = {"threshold_s": float(threshold_s), "splits": {}}
    parts = [(s, frames[frames["split"] == s]) for s in SPLITS] + [("all", frames)]
    for name, f in parts:
        e: dict[str, Any] = {"n_frames": int(len(f))}
        if "scenario" in f.columns:
            e["n_sequences"] = int(f["scenario"].nunique())
        for lab in labels:
            if lab in f.columns and len(f):
                e[lab] = float(np.mean(f[lab].to_numpy(np.float64) > thr))
        out["splits"][name] = e
    return out


def evaluate_suite(
    source: Any,
    models: Mapping[str, Any],
    *,
    primary_label: str,
    region_labels: Sequence[str] = REGION_LABELS,
    thresholds_s: Sequence[float] = THRESHOLDS_S,
    thw_cap: float = 10.0,
    geometric: Any = None,
    batch_size: int = 256,
    split: str = "test",
    main_variant: str | None = None,
    variants: Mapping[str, Mapping[str, Any]] | None = None,
    ci: CIConfig | None = None,
    collapse_std: float = 1e-3,
    rule_params: Mapping[str, Any] | None = None,
    decisions: Mapping[str, Mapping[float, float]] | None = None,
    shipped: str | None = None,
    learned: str | None = None,
    holdout: Mapping[str, Any] | None = None,
) -> tuple[dict[str, Any], Any]:
    """Predict every model and baseline on ``split`` of ``source`` and compute the metrics with
    their sequence-bootstrap intervals, the paired differences, the targets and the breakdowns.

    ``source``: :class:`traffictwin.risk.training.RiskSource`; ``models``: variant →
    :class:`traffictwin.risk.model_io.RiskModel` (``meta["label"]``: the column it is scored
    against); ``geometric``: :class:`~traffictwin.risk.baselines.GeometricParams` (``None`` =
    no geometric baselines); ``main_variant``: the headline (default: the first model);
    ``variants``: ``risk_model.variants`` entries (``replicate_of``, ``objective``,
    ``seed_offset``; missing = none / mse / 0); ``ci``: the bootstrap (default 2000 resamples,
    seed 0, 95 %); ``collapse_std``: a model whose test predictions have a smaller standard
    deviation is collapsed. Choices made on validation (stage ``select_risk``): ``rule_params``:
    rule name (``geometric_sgm``/``geometric_gt``) → its :class:`GeometricParams` (the tuned
    corridor; default ``geometric``); ``decisions``: predictor → {THW threshold s: decision cut
    on its risk} for the primary label; ``shipped``: the model served to users (targets);
    ``learned``: the learned variant group compared with the SGM rule (targets); ``holdout``:
    ``{"templates": [...], "group": runs trained without them, "reference": the same model
    trained on every template}`` — generalisation to unseen road templates (:func:`_holdout_block`).
    Returns ``(metrics, predictions)``: the risk.json dict and a per-frame DataFrame
    (``frame_id``, ``scenario``, labels, ``speed``, ``pred_<variant>``, ``pred_<baseline>`` on
    the primary label, ``geometric_*_distance_m``).
    """
    import pandas as pd

    from traffictwin.risk.training import check_label, input_keys

    if not models:
        raise ValueError("evaluate_suite: no models to evaluate")
    ci = ci or CIConfig()
    variants = variants or {}
    names = list(models)
    main = main_variant or names[0]
    if main not in models:
        raise ValueError(f"main variant '{main}' is not among the evaluated models {names}")
    t0 = thresholds_s[0]
    frames = source.split_frames(split)
    fpath = str(source.risk.root / "frames.csv")
    if len(frames) == 0:
        raise ValueError(f"{source.risk.root}: split '{split}' has no frames after the ORB check")
    if "scenario" not in frames.columns:
        raise ValueError(f"{fpath}: column 'scenario' (the sequence = bootstrap cluster) missing")
    label_of = {v: str(m.meta.get("label") or primary_label) for v, m in models.items()}
    labels = [primary_label]
    labels += [c for c in region_labels if c not in labels and c in frames.columns]
    labels += [lab for lab in label_of.values() if lab not in labels]
    keys: list[str] = sorted(
        {k for m in models.values() for k in input_keys(m.cfg)}
        | ({"disp_sgm", "disp_gt"} if geometric else set())
    )
    preds: dict[str, list[np.ndarray]] = {f"pred_{v}": [] for v in models}
    extra: dict[str, list[np.ndarray]] = {}
    order: list[np.ndarray] = []
    for rows, arr in source.iter_arrays(frames, keys):
        sp = rows["speed"].to_numpy(np.float32)
        shared: dict[Any, np.ndarray] = {}  # hybrid features, once per feature setting
        for v, m in models.items():
            if hasattr(m, "predict_features"):
                fk = (m.config, m.geometric, tuple(sorted(m.camera.items())))
                if fk not in shared:
                    shared[fk] = m.features(arr["disp_sgm"], sp)
                preds[f"pred_{v}"].append(m.predict_features(shared[fk]))
                continue
            preds[f"pred_{v}"].append(
                m.predict(
                    arr.get("left"),
                    arr.get("disp_sgm"),
                    arr.get("disp_gt"),
                    speed=sp,
                    batch_size=batch_size,
                )
            )
        if geometric is not None:
            for name, k in (("geometric_sgm", "disp_sgm"), ("geometric_gt", "disp_gt")):
                gp = (rule_params or {}).get(name, geometric)
                d, _, r = geometric_risk(arr[k], sp, source.camera, gp)
                extra.setdefault(f"{name}_distance_m", []).append(d)
                extra.setdefault(name, []).append(r)
        order.append(rows.index.to_numpy())
    ix = np.concatenate(order)
    frames = frames.loc[ix].reset_index(drop=True)
    out = pd.DataFrame({"frame_id": frames["frame_id"].to_numpy()})
    for c in ("scenario", "situation", "template", "t", "speed", "thw", *labels):
        if c in frames.columns:
            out[c] = frames[c].to_numpy()
    for k, parts in preds.items():
        out[k] = np.concatenate(parts).astype(np.float64)
    geo_pred = {k: np.concatenate(v).astype(np.float64) for k, v in extra.items()}
    ys = {lab: check_label(frames, lab, fpath).astype(np.float64) for lab in labels}
    speed = frames["speed"].to_numpy(np.float64)
    train = source.split_frames("train")
    if len(train) == 0:
        raise ValueError(f"{fpath}: the training split is empty (baselines are fitted on it)")
    train_speed = train["speed"].to_numpy(np.float64)

    # --- baselines per label: fitted on the training split, predicted on the test frames --------
    base_info: dict[str, dict[str, Any]] = {}
    base_pred: dict[str, dict[str, np.ndarray]] = {}
    for lab in labels:
        ty = check_label(train, lab, fpath).astype(np.float64)
        consts = constant_predictions(ty, len(out))
        so = fit_speed_only(train_speed, ty)
        base_pred[lab] = {
            "train_mean": consts["train_mean"].astype(np.float64),
            "train_median": consts["train_median"].astype(np.float64),
            "speed_only": so.predict(speed),
        }
        base_info[lab] = {
            "train_mean": {"value": float(consts["train_mean"][0])},
            "train_median": {"value": float(consts["train_median"][0])},
            "speed_only": {
                "n_knots": int(so.speed_knots.size),
                f"critical_speed_at_{t0:g}s": so.critical_speed(risk_threshold(t0)),
            },
        }
        for g in ("geometric_sgm", "geometric_gt"):
            if g in geo_pred:
                base_pred[lab][g] = geo_pred[g]
                base_info[lab][g] = {"params": dict((rule_params or {}).get(g, geometric).__dict__)}
    out["pred_speed_only"] = base_pred[primary_label]["speed_only"]
    for g in ("geometric_sgm", "geometric_gt"):
        if g in geo_pred:
            out[f"pred_{g}"] = geo_pred[g]
            out[f"{g}_distance_m"] = geo_pred[f"{g}_distance_m"]

    plan = ClusterBootstrap.from_config(out["scenario"].to_numpy(), ci)
    cache: dict[tuple[str, str], dict[str, Stat]] = {}

    def prediction(name: str, lab: str) -> np.ndarray:
        return out[f"pred_{name}"].to_numpy() if name in models else base_pred[lab][name]

    decisions = {
        k: {float(t): float(c) for t, c in v.items()} for k, v in (decisions or {}).items()
    }

    def cuts(name: str, lab: str) -> Mapping[float, float] | None:
        """The decision cuts chosen on validation (primary label only)."""
        return decisions.get(name) if lab == primary_label else None

    def scores(name: str, lab: str) -> dict[str, Stat]:
        """Scores of a model, a baseline or a seed group (``<base>[seed_mean]``) against ``lab``;
        a seed group's interval resamples its seeds as well as the sequences."""
        if (name, lab) not in cache:
            if name.endswith(SEED_MEAN):
                base = name.removesuffix(SEED_MEAN)
                runs = groups_used[base]
                stream = 1 + sorted(groups_used).index(base)
                cache[(name, lab)] = mean_of_scores(
                    [scores(v, lab) for v in runs], seed_draws(len(runs), plan, stream)
                )
            else:
                cache[(name, lab)] = bootstrap_scores(
                    ys[lab], prediction(name, lab), plan, thresholds_s, thw_cap, cuts(name, lab)
                )
        return cache[(name, lab)]

    def ev(y: np.ndarray, p: np.ndarray, name: str = "", lab: str = "") -> dict[str, Any]:
        return evaluate(y, p, thresholds_s, thw_cap, cuts(name, lab))

    # --- models, collapse, seed groups -------------------------------------------------------
    spread = {v: float(np.std(out[f"pred_{v}"].to_numpy())) for v in models}
    collapsed = {v: bool(spread[v] < collapse_std) for v in models}
    groups = _variant_groups(names, {v: (variants.get(v) or {}).get("replicate_of") for v in names})
    group_of = {m: b for b, ms in groups.items() for m in ms}
    groups_used = {b: [m for m in ms if not collapsed[m]] for b, ms in groups.items()}

    def predictor(v: str) -> str:
        """The name a variant's group is compared under: its seed mean when ≥ 2 runs are usable."""
        b = group_of[v]
        return f"{b}{SEED_MEAN}" if len(groups_used[b]) >= 2 else v

    metrics: dict[str, Any] = {
        "paper": PAPER,
        "split": split,
        "primary_label": primary_label,
        "main_variant": main,
        "main_predictor": predictor(main) if group_of[main] == main else main,
        "shipped": shipped,
        "learned": (
            (f"{learned}{SEED_MEAN}" if len(groups_used.get(learned, [])) >= 2 else learned)
            if learned
            else None
        ),
        "decisions": {k: {f"{t:g}": c for t, c in v.items()} for k, v in decisions.items()},
        "thresholds_s": [float(t) for t in thresholds_s],
        "thw_cap_s": float(thw_cap),
        "collapse_std": float(collapse_std),
        "bootstrap": {
            "n_boot": ci.n_boot,
            "seed": ci.seed,
            "level": ci.level,
            "cluster": "driving sequence (frames.csv 'scenario')",
            "n_clusters": plan.n_groups,
        },
        "n_frames": {
            "total": int(source.n_total),
            "orb_outliers_dropped": int(source.n_orb_outliers),
            **{s: int((source.frames["split"] == s).sum()) for s in SPLITS},
        },
        "n_sequences": {
            s: int(source.frames.loc[source.frames["split"] == s, "scenario"].nunique())
            for s in SPLITS
        },
        "models": {},
        "groups": {},
        "baselines": {},
        "baselines_by_label": {},
        "differences": {},
    }
    main_key = metrics["main_predictor"]
    for v, m in models.items():
        lab = label_of[v]
        info = variants.get(v) or {}
        entry: dict[str, Any] = {
            "label": lab,
            "inputs": list(m.cfg.inputs),
            "speed": bool(m.cfg.use_speed),
            "objective": str(m.meta.get("objective") or info.get("objective") or "mse"),
            "seed_offset": int(m.meta.get("seed_offset", info.get("seed_offset", 0)) or 0),
            "replicate_of": info.get("replicate_of"),
            "group": group_of[v],
            "pred_std": spread[v],
            "collapsed": collapsed[v],
            **{
                k: m.meta[k]
                for k in (
                    "n_parameters",
                    "best_val_mse",
                    "best_step",
                    "steps",
                    "n_train",
                )
                if k in m.meta
            },
        }
        entry.update(ev(ys[lab], out[f"pred_{v}"].to_numpy(), v, lab))
        scores_with_ci(scores(v, lab), plan, into=entry)
        entry["vs_paper"] = summarise_paper_comparison(entry)
        metrics["models"][v] = entry
    for b, members in groups.items():
        if len(members) < 2:
            continue
        lab = label_of[b] if b in label_of else label_of[members[0]]
        used = groups_used[b]
        g: dict[str, Any] = {
            "label": lab,
            "members": members,
            "used": used,
            "collapsed": [m for m in members if collapsed[m]],
            "n_seeds": len(used),
        }
        if len(used) >= 2:
            sc = scores(f"{b}{SEED_MEAN}", lab)
            scores_with_ci(sc, plan, into=g)
            g["seed_sd"] = {
                k.replace("|", "."): float(np.std([scores(m, lab)[k][0] for m in used], ddof=1))
                for k in ("test/mse", f"at_{t0:g}s|balanced_accuracy", f"at_{t0:g}s|roc_auc")
            }
        metrics["groups"][b] = g

    # --- baselines (on the primary label; on each other label a model was trained on) --------
    def baseline_entry(name: str, lab: str) -> dict[str, Any]:
        e = {
            "label": lab,
            "oracle": name in ORACLES,
            "uses_gt_disparity": name in GT_INPUT,
            "pred_std": float(np.std(base_pred[lab][name])),
            **base_info[lab][name],
        }
        e.update(ev(ys[lab], base_pred[lab][name], name, lab))
        return scores_with_ci(scores(name, lab), plan, into=e)

    for lab in dict.fromkeys([primary_label, *label_of.values()]):
        entries = {n: baseline_entry(n, lab) for n in BASELINES if n in base_pred[lab]}
        if lab == primary_label:
            metrics["baselines"] = entries
        else:
            metrics["baselines_by_label"][lab] = entries

    # --- paired differences (a − b) ----------------------------------------------------------
    def compare(a: str, b: str, lab: str, kind: str) -> None:
        d = difference_of_scores(scores(a, lab), scores(b, lab))
        metrics["differences"][f"{a}|{b}"] = {
            "a": a,
            "b": b,
            "label": lab,
            "kind": kind,
            "oracle": b in ORACLES,
            "n_frames": plan.n,
            "n_clusters": plan.n_groups,
            **difference_json(d, plan),
        }

    for v in names:  # every run and every seed group vs the speed-only baseline on its label
        compare(v, "speed_only", label_of[v], "vs_speed_only")
    for b in groups:
        if len(groups_used[b]) >= 2:
            compare(f"{b}{SEED_MEAN}", "speed_only", label_of[groups[b][0]], "vs_speed_only")
    main_lab = label_of[main]
    for bname in ("geometric_sgm", "geometric_gt", "train_median"):
        if bname in base_pred[main_lab]:
            compare(main_key, bname, main_lab, "vs_baseline")
    if "geometric_sgm" in base_pred[primary_label]:  # the primary comparisons (issue 31)
        for key, kind in ((metrics["learned"], "learned_vs_rule"), (shipped, "shipped_vs_rule")):
            if key and key != main_key and f"{key}|geometric_sgm" not in metrics["differences"]:
                compare(key, "geometric_sgm", primary_label, kind)
    for v in names:  # the headline vs every other variant scored on the same label
        if group_of[v] == group_of[main] or label_of[v] != main_lab:
            continue
        if predictor(v) != v and v != group_of[v]:
            continue  # a replicate: its group is compared once
        obj_a = metrics["models"][main]["objective"]
        obj_b = metrics["models"][v]["objective"]
        compare(main_key, predictor(v), main_lab, "objective" if obj_a != obj_b else "variant")

    # --- the primary comparisons, and Holm's correction of every other one ---------------------
    primary = [k for k, d in metrics["differences"].items() if d["kind"] in ("learned_vs_rule",)]
    secondary = {
        f"{k}|{m}": _g(d, f"at_{t0:g}s", m, "p")
        for k, d in metrics["differences"].items()
        if k not in primary
        for m in ("roc_auc", "balanced_accuracy")
    }
    metrics["comparisons"] = {
        "primary": primary,
        "primary_metrics": [f"at_{t0:g}s.roc_auc", f"at_{t0:g}s.balanced_accuracy"],
        "secondary_holm": {
            "metrics": [f"at_{t0:g}s.roc_auc", f"at_{t0:g}s.balanced_accuracy"],
            "p_adjusted": holm({k: v for k, v in secondary.items() if v is not None}),
            "note": "every other paired difference (a|b|metric) is exploratory: Holm-adjusted "
            "bootstrap p-values; a claim needs p_adjusted < 1 - level",
        },
    }

    # --- critical share of every region label per split (frames.csv, before the ORB check) ----
    all_frames = source.risk.table("frames.csv")
    share_labels = [c for c in (*region_labels, primary_label) if c in all_frames.columns]
    metrics["critical_share"] = critical_shares(all_frames, list(dict.fromkeys(share_labels)), t0)

    # --- the risk metric region: each predictor against each region label ---------------------
    present = [c for c in region_labels if c in ys]
    if len(present) >= 2:
        metrics["region"] = _region_block(
            present,
            ys,
            plan,
            scores,
            models,
            label_of,
            base_pred,
            t0,
            thresholds_s,
            exclude=[v for v in names if collapsed[v] or group_of[v] != v],
        )

    # --- headline by situation type -----------------------------------------------------------
    if "situation" in out.columns:
        metrics["situations"] = _situations(
            out,
            ys[main_lab],
            main_key,
            groups_used,
            group_of,
            models,
            base_pred[main_lab],
            plan,
            t0,
            thw_cap,
            extra=[metrics["shipped"], metrics["learned"]],
            cut_of=lambda name: cuts(name, main_lab),
        )

    if holdout and holdout.get("templates") and "template" in out.columns:
        metrics["holdout"] = _holdout_block(
            out,
            ys[primary_label],
            plan,
            groups_used,
            holdout,
            lambda name: cuts(name, primary_label),
            scores,
            primary_label,
            thresholds_s,
            thw_cap,
        )

    spreads = {v: spread_stat(out[f"pred_{v}"].to_numpy(), plan) for v in models}
    metrics["targets"] = _targets(metrics, scores, plan, main_key, main_lab, spreads, collapse_std)
    return json_clean(metrics), out


def _region_block(
    present: Sequence[str],
    ys: Mapping[str, np.ndarray],
    plan: ClusterBootstrap,
    scores: Any,
    models: Mapping[str, Any],
    label_of: Mapping[str, str],
    base_pred: Mapping[str, Mapping[str, np.ndarray]],
    t0: float,
    thresholds_s: Sequence[float],
    exclude: Sequence[str] = (),
) -> dict[str, Any]:
    """Label means and critical shares, pairwise label agreement, every predictor's metrics
    against every region label (skill = 1 − MSE / MSE of that label's training mean), and the
    paired skill difference of networks that differ only in their training label's region
    (``skill_differences``, each scored on its own label; ``exclude``: runs left out of those —
    collapsed ones and seed replicates), with CIs."""
    kw = {"n_boot": plan.n_boot, "seed": plan.seed, "level": plan.level}
    thr0 = risk_threshold(t0)
    region: dict[str, Any] = {"labels": {}, "agreement": {}, "predictors": {}}
    for lab in present:
        iv = mean_ci((ys[lab] > thr0).astype(np.float64), plan.clusters, **kw)
        region["labels"][lab] = {
            "mean": float(np.mean(ys[lab])),
            f"critical_fraction_at_{t0:g}s": iv.estimate,
            f"critical_fraction_at_{t0:g}s_ci": _lohi(iv),
        }
    for a, b in combinations(present, 2):
        agree = label_agreement(ys[a], ys[b], thresholds_s)
        for t in thresholds_s:
            thr = risk_threshold(t)
            iv = mean_ci(((ys[a] > thr) == (ys[b] > thr)).astype(np.float64), plan.clusters, **kw)
            agree[f"class_agreement_at_{t:g}s_ci"] = _lohi(iv)
        region["agreement"][f"{a}|{b}"] = agree
    at = f"at_{t0:g}s|"
    keep = {
        "test/mse": "test/mse",
        "test/mae": "test/mae",
        at + "accuracy": "accuracy",
        at + "balanced_accuracy": "balanced_accuracy",
        at + "f1": "f1",
        at + "roc_auc": "roc_auc",
    }

    def skill(name: str, lab: str) -> Stat:
        ref = scores("train_mean", lab)["test/mse"]
        return _lin(
            (1.0, np.ones(plan.n_boot)), _div(scores(name, lab)["test/mse"], ref), 1.0, -1.0
        )

    names = [*models, *(n for n in BASELINES if n in base_pred[present[0]])]
    for name in names:
        for lab in present:
            sc = scores(name, lab)
            flat = {new: sc[old] for old, new in keep.items()}
            flat["skill"] = skill(name, lab)
            region["predictors"].setdefault(name, {})[lab] = scores_with_ci(flat, plan)
    # networks that differ only in the region of their training label: paired skill difference,
    # each scored on its own label (does a region make the risk more learnable?)
    region["skill_differences"] = {}
    for a, b in combinations([v for v in models if v not in exclude], 2):
        ma, mb = models[a], models[b]
        la, lb = label_of[a], label_of[b]
        same = (tuple(ma.cfg.inputs), bool(ma.cfg.use_speed)) == (
            tuple(mb.cfg.inputs),
            bool(mb.cfg.use_speed),
        )
        if not same or la == lb or la not in present or lb not in present:
            continue
        if present.index(la) < present.index(lb):  # the earlier region second: later − earlier
            a, b, la, lb = b, a, lb, la
        iv = plan.interval(_lin(skill(a, la), skill(b, lb), 1.0, -1.0))
        region["skill_differences"][f"{a}|{b}"] = {
            "a": a,
            "b": b,
            "label_a": la,
            "label_b": lb,
            "estimate": iv.estimate,
            "lo": iv.lo,
            "hi": iv.hi,
        }
    return region


def _situations(
    out: Any,
    y: np.ndarray,
    main_key: str,
    groups_used: Mapping[str, list[str]],
    group_of: Mapping[str, str],
    models: Mapping[str, Any],
    base_pred: Mapping[str, np.ndarray],
    plan: ClusterBootstrap,
    t0: float,
    thw_cap: float,
    extra: Sequence[str] = (),
    cut_of: Any = None,
) -> dict[str, Any]:
    """Per situation type: frames, sequences, critical share and, for the headline (seed mean),
    the ``extra`` predictors (models or seed groups: the shipped one, the learned group), the
    speed-only and the geometric SGM baseline, accuracy / recall / specificity / balanced
    accuracy / ROC-AUC at ``t0`` with CIs over that situation's sequences; ``cut_of(name)``: a
    predictor's decision cuts chosen on validation (``None``: the label's threshold)."""
    situation = out["situation"].astype(str).to_numpy()
    cut_of = cut_of or (lambda name: None)

    def runs_of(key: str) -> list[str]:
        return groups_used[key.removesuffix(SEED_MEAN)] if key.endswith(SEED_MEAN) else [key]

    preds = {
        key: [(v, out[f"pred_{v}"].to_numpy()) for v in runs_of(key)]
        for key in dict.fromkeys([main_key, *(e for e in extra if e)])
    }
    for b in ("speed_only", "geometric_sgm"):
        if b in base_pred:
            preds[b] = [(b, base_pred[b])]
    at = f"at_{t0:g}s|"
    keep = ("accuracy", "recall", "specificity", "balanced_accuracy", "roc_auc")
    res: dict[str, Any] = {}
    for s in sorted(set(situation)):
        m = situation == s
        sub = plan.subset(m)
        e: dict[str, Any] = {
            "n_frames": int(m.sum()),
            "n_sequences": sub.n_groups,
            "critical_share": float(np.mean(y[m] > risk_threshold(t0))),
            "predictors": {},
        }
        for name, ps in preds.items():
            sc = mean_of_scores(
                [bootstrap_scores(y[m], p[m], sub, (t0,), thw_cap, cut_of(v)) for v, p in ps]
            )
            e["predictors"][name] = scores_with_ci({k: sc[at + k] for k in keep}, sub)
        res[s] = e
    return res


def _holdout_block(
    out: Any,
    y: np.ndarray,
    plan: ClusterBootstrap,
    groups_used: Mapping[str, list[str]],
    holdout: Mapping[str, Any],
    cut_of: Any,
    scores: Any,
    label: str,
    thresholds_s: Sequence[float],
    thw_cap: float,
) -> dict[str, Any]:
    """Generalisation to road templates never seen in training: the ``group`` (runs trained
    without ``templates``) on the test frames of those templates, the ``reference`` (the same
    model trained on every template) on the same frames and on the whole test split, and the
    drop ``reference on the standard test split − group on the held-out templates`` of the
    balanced accuracy / ROC-AUC at the primary threshold (seeds and sequences resampled; the two
    sides are resampled independently)."""
    t0 = thresholds_s[0]
    at = f"at_{t0:g}s|"
    templates = [str(t) for t in holdout["templates"]]
    mask = out["template"].astype(str).isin(templates).to_numpy()
    res: dict[str, Any] = {
        "templates": templates,
        "group": holdout["group"],
        "reference": holdout["reference"],
        "n_frames": int(mask.sum()),
    }
    if not mask.any():
        return {**res, "why": "no test frame of the held-out templates"}
    sub = plan.subset(mask)
    res["n_sequences"] = sub.n_groups
    keep = ("balanced_accuracy", "roc_auc", "recall", "specificity")

    def on_heldout(g: str, stream: int) -> dict[str, Stat] | None:
        runs = groups_used.get(g) or []
        if not runs:
            return None
        per = [
            bootstrap_scores(
                y[mask], out[f"pred_{v}"].to_numpy()[mask], sub, thresholds_s, thw_cap, cut_of(v)
            )
            for v in runs
        ]
        return mean_of_scores(per, seed_draws(len(runs), sub, stream) if len(runs) > 1 else None)

    held = on_heldout(holdout["group"], 101)
    ref_h = on_heldout(holdout["reference"], 102)
    ref_runs = groups_used.get(holdout["reference"]) or []
    if held is None or not ref_runs:
        return {**res, "why": "held-out or reference runs missing (or collapsed)"}
    ref_key = f"{holdout['reference']}{SEED_MEAN}" if len(ref_runs) > 1 else ref_runs[0]
    ref_std = scores(ref_key, label)
    for name, sc, pl in (
        ("heldout", held, sub),
        ("reference_on_heldout", ref_h, sub),
        ("reference_standard", ref_std, plan),
    ):
        if sc is not None:
            res[name] = scores_with_ci({k: sc[at + k] for k in keep}, pl)
    res["drop"] = {}
    for k in ("balanced_accuracy", "roc_auc"):
        iv = plan.interval(_lin(ref_std[at + k], held[at + k], 1.0, -1.0))
        res["drop"][k] = {"estimate": iv.estimate, "lo": iv.lo, "hi": iv.hi}
    return res


def _targets(
    metrics: Mapping[str, Any],
    scores: Any,
    plan: ClusterBootstrap,
    main_key: str,
    lab: str,
    spreads: Mapping[str, Stat],
    collapse_std: float,
) -> dict[str, Any]:
    """The targets of :data:`TARGETS`: the shipped predictor's (``metrics["shipped"]``; default
    the headline ``main_key``) and the learned group's against the rule (``metrics["learned"]``;
    default the headline), on label ``lab``."""
    thresholds = metrics["thresholds_s"]
    shipped = metrics.get("shipped") or main_key
    learned = metrics.get("learned") or main_key
    out: dict[str, Any] = {}

    def put(
        name: str,
        stat: Stat | Interval,
        predictor: str,
        threshold: float | None = None,
        **extra: Any,
    ) -> None:
        t = TARGETS[name]
        iv = stat if isinstance(stat, Interval) else plan.interval(stat)
        out[name] = {
            "description": t.description,
            "predictor": predictor,
            **judge(iv, t, threshold),
            **extra,
        }

    def missing(name: str, why: str) -> None:
        out[name] = {"description": TARGETS[name].description, "met": False, "why": why}

    sh = scores(shipped, lab)
    for t, key in ((1.5, "shipped_balanced_accuracy_1.5s"), (1.0, "shipped_balanced_accuracy_1s")):
        if any(math.isclose(t, x) for x in thresholds):
            put(key, sh[f"at_{t:g}s|balanced_accuracy"], shipped, threshold_s=t)
        else:
            missing(key, f"THW threshold {t:g} s not evaluated (evaluation.risk.thresholds_s)")
    t0 = thresholds[0]
    put("shipped_roc_auc", sh[f"at_{t0:g}s|roc_auc"], shipped, threshold_s=t0)
    put("shipped_thw_median_error_critical_s", sh["test/thw_median_error_critical_s"], shipped)
    sits = metrics.get("situations") or {}
    for sit, key in (
        ("pedestrian", "shipped_recall_pedestrian"),
        ("cut_in", "shipped_recall_cut_in"),
    ):
        e = (sits.get(sit) or {}).get("predictors", {}).get(shipped)
        if not e:
            missing(key, f"no '{sit}' frames in the test split")
            continue
        ci = e.get("recall_ci") or {}
        iv = Interval(e["recall"], ci.get("lo", math.nan), ci.get("hi", math.nan), plan.level)
        put(key, iv, shipped, threshold_s=t0, n_sequences=sits[sit]["n_sequences"])
    at = f"at_{t0:g}s|"
    ls = scores(learned, lab)
    for name, base, metric in (
        ("learned_vs_rule_auc", "geometric_sgm", "roc_auc"),
        ("learned_vs_rule_balanced_accuracy", "geometric_sgm", "balanced_accuracy"),
        ("auc_vs_speed_only", "speed_only", "roc_auc"),
    ):
        try:
            b = scores(base, lab)
        except KeyError:
            missing(name, f"{base} not evaluated")
            continue
        put(
            name,
            (ls[at + metric][0] - b[at + metric][0], ls[at + metric][1] - b[at + metric][1]),
            learned,
            baseline=base,
        )
    ho = metrics.get("holdout") or {}
    drop = (ho.get("drop") or {}).get("balanced_accuracy")
    if drop:
        put(
            "holdout_balanced_accuracy_drop",
            Interval(drop["estimate"], drop["lo"], drop["hi"], plan.level),
            str(ho.get("group")),
            templates=ho.get("templates"),
            n_sequences=ho.get("n_sequences"),
        )
    else:
        missing(
            "holdout_balanced_accuracy_drop",
            ho.get("why") or "no held-out road templates (risk_hybrid.holdout_templates)",
        )
    worst = min(spreads, key=lambda v: spreads[v][0])
    put(
        "spread",
        spreads[worst],
        worst,
        collapse_std,
        variant=worst,
        collapsed=sorted(v for v, st in spreads.items() if st[0] < collapse_std),
    )
    for key, who in ((shipped, "shipped"), (learned, "learned")):
        if metrics["models"].get(key, {}).get("collapsed"):  # a single run that collapsed
            for name, e in out.items():
                if name != "spread" and e.get("predictor") == key:
                    e.update(met=False, why=f"the {who} predictor ({key}) collapsed")
    return out


def main_series(
    metrics: Mapping[str, Any], pred: Any, variant: str
) -> tuple[str, np.ndarray, np.ndarray]:
    """(label, true risk, predicted risk) of ``variant`` on the test frames of ``pred``
    (:func:`evaluate_suite`'s outputs)."""
    label = metrics["models"][variant]["label"]
    return label, pred[label].to_numpy(), pred[f"pred_{variant}"].to_numpy()


def example_indices(y: np.ndarray, p: np.ndarray, thw_s: float) -> tuple[int, int]:
    """The paper's Fig. 7 frames: the best-predicted critical frame (the best frame when none is
    critical) and the worst-predicted frame (the second worst when that is the same frame)."""
    err = np.abs(p - y)
    crit = np.flatnonzero(y > risk_threshold(thw_s))
    good = int(crit[np.argmin(err[crit])]) if len(crit) else int(np.argmin(err))
    bad = (
        int(np.argsort(err)[-2])
        if int(np.argmax(err)) == good and len(err) > 1
        else int(np.argmax(err))
    )
    return good, bad


def confusion_table(frame_id: Any, y: np.ndarray, p: np.ndarray, thw_s: float) -> Any:
    """``frame_id``, ``actual``, ``predicted`` class per frame (the ``dvc plots`` confusion data)."""
    import pandas as pd

    actual, predicted = confusion_labels(y, p, thw_s)
    return pd.DataFrame({"frame_id": frame_id, "actual": actual, "predicted": predicted})


def tracking_metrics(metrics: Mapping[str, Any], variant: str) -> dict[str, float]:
    """Test metrics of ``variant`` to add to its training run: MSE, MAE, THW MAE and, at the
    primary threshold, accuracy, balanced accuracy, F1 and ROC-AUC (undefined ones left out)."""
    e = metrics["models"][variant]
    vals = {k: e[k] for k in ("test/mse", "test/mae", "test/thw_mae_s") if e.get(k) is not None}
    at = e.get(f"at_{metrics['thresholds_s'][0]:g}s", {})
    for k in ("accuracy", "balanced_accuracy", "f1", "roc_auc"):
        if at.get(k) is not None:
            vals[f"test/{k}"] = at[k]
    return vals
