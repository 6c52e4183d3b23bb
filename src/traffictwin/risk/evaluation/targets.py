"""The risk targets (default profile, test split, headline) and how they are judged against their
acceptance thresholds (``acceptance.risk``, :mod:`traffictwin.acceptance`): the shipped
predictor's own scores and the learned group's paired differences to the rules."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from traffictwin.acceptance import Threshold
from traffictwin.acceptance import judge as judge_threshold
from traffictwin.risk.evaluation.bootstrap import ClusterBootstrap, Stat
from traffictwin.risk.evaluation.scorer import Roles, Scorer
from traffictwin.stats import Interval

#: the targets :func:`targets` judges, in order; their thresholds are ``acceptance.risk``
#: (:mod:`traffictwin.acceptance`), whose descriptions hold ``{t}``: the THW threshold (s) the
#: target is judged at (the primary ``evaluation.risk.thresholds_s`` unless said), filled in by
#: :func:`describe`. The two balanced-accuracy targets are judged at the first and second
#: thresholds and reported as ``shipped_balanced_accuracy_<t>s``.
TARGET_NAMES = (
    # the predictor users get (models/risk/shipped, chosen on validation)
    "shipped_balanced_accuracy_primary",
    "shipped_balanced_accuracy_second",
    "shipped_roc_auc",
    "shipped_recall_pedestrian",
    "shipped_recall_cut_in",
    "shipped_thw_median_error_critical_s",
    # the learned model (best group on validation, seeds resampled) vs the validation-tuned rule
    "learned_vs_rule_auc",
    "learned_vs_rule_balanced_accuracy",
    "auc_vs_speed_only",
    "holdout_balanced_accuracy_drop",
    "spread",
)


def describe(target: Threshold, thw_s: float | str) -> str:
    """``target``'s description at THW threshold ``thw_s`` (s; one decimal at least: 1.0, 2.0,
    1.25; a text stands for a threshold that is not there)."""
    if isinstance(thw_s, str):
        return target.description.format(t=thw_s)
    t = f"{thw_s:.1f}" if math.isclose(thw_s, round(thw_s, 1)) else f"{thw_s:g}"
    return target.description.format(t=t)


def judge(iv: Interval, target: Threshold) -> dict[str, Any]:
    """``value``, ``lo``, ``hi``, ``threshold``, ``op``, ``met`` (the estimate — or, for a target
    judged on the interval, its far end — on the target's side; :func:`traffictwin.acceptance.judge`)
    and ``ci_beyond_threshold`` (the whole interval there)."""
    e, lo, hi = iv.estimate, iv.lo, iv.hi
    out: dict[str, Any] = {
        "value": e,
        "lo": lo,
        "hi": hi,
        "threshold": target.value,
        "op": target.operator,
    }
    j = judge_threshold(target, e, lo, hi)
    if j.met is None:
        return {**out, "met": False, "ci_beyond_threshold": False, "why": "undefined"}
    return {**out, "met": bool(j.met), "ci_beyond_threshold": bool(j.ci_passes)}


class _Verdicts:
    """The judged targets, in order (``out``), on the intervals of ``plan``."""

    def __init__(
        self, plan: ClusterBootstrap, t0: float, thresholds: Mapping[str, Threshold]
    ) -> None:
        self.plan = plan
        self.thresholds = thresholds
        self.t0 = t0  # the primary THW threshold (s): the descriptions' default
        self.out: dict[str, Any] = {}

    def put(
        self,
        name: str,
        stat: Stat | Interval,
        predictor: str,
        key: str | None = None,
        thw_s: float | None = None,
        **extra: Any,
    ) -> None:
        """Judge target ``name`` on ``stat`` (a statistic or an interval) of ``predictor``,
        reported as ``key`` (default ``name``), described at THW ``thw_s`` (default the primary)."""
        t = self.thresholds[name]
        iv = stat if isinstance(stat, Interval) else self.plan.interval(stat)
        self.out[key or name] = {
            "description": describe(t, self.t0 if thw_s is None else thw_s),
            "predictor": predictor,
            **judge(iv, t),
            **extra,
        }

    def missing(self, name: str, why: str, thw_s: float | str | None = None) -> None:
        """Target ``name`` (described at THW ``thw_s``, default the primary) could not be
        evaluated (not met)."""
        desc = describe(self.thresholds[name], self.t0 if thw_s is None else thw_s)
        self.out[name] = {"description": desc, "met": False, "why": why}


def _shipped(v: _Verdicts, scorer: Scorer, shipped: str, label: str) -> None:
    """The shipped predictor's balanced accuracy, ROC-AUC and THW error on ``label``."""
    thresholds = [float(t) for t in scorer.settings.thresholds_s]
    sh = scorer.scores(shipped, label)
    for i, name in enumerate(
        ("shipped_balanced_accuracy_primary", "shipped_balanced_accuracy_second")
    ):
        if i < len(thresholds):
            t = thresholds[i]
            key = f"shipped_balanced_accuracy_{t:g}s"
            v.put(
                name, sh[f"at_{t:g}s|balanced_accuracy"], shipped, key=key, thw_s=t, threshold_s=t
            )
        else:
            why = "no second THW threshold (evaluation.risk.thresholds_s)"
            v.missing(name, why, thw_s="<second threshold>")
    t0 = thresholds[0]
    v.put("shipped_roc_auc", sh[f"at_{t0:g}s|roc_auc"], shipped, threshold_s=t0)
    v.put("shipped_thw_median_error_critical_s", sh["test/thw_median_error_critical_s"], shipped)


def _situational(v: _Verdicts, sits: Mapping[str, Any], shipped: str, t0: float) -> None:
    """The shipped predictor's recall in pedestrian and cut-in situations (``sits``: the
    situation breakdown)."""
    for sit, key in (
        ("pedestrian", "shipped_recall_pedestrian"),
        ("cut_in", "shipped_recall_cut_in"),
    ):
        e = (sits.get(sit) or {}).get("predictors", {}).get(shipped)
        if not e:
            v.missing(key, f"no '{sit}' frames in the test split")
            continue
        ci = e.get("recall_ci") or {}
        iv = Interval(e["recall"], ci.get("lo", math.nan), ci.get("hi", math.nan), v.plan.level)
        v.put(key, iv, shipped, threshold_s=t0, n_sequences=sits[sit]["n_sequences"])


def _learned(v: _Verdicts, scorer: Scorer, learned: str, label: str) -> None:
    """The learned group's paired differences to the SGM rule and the speed-only baseline."""
    at = f"at_{scorer.settings.t0:g}s|"
    ls = scorer.scores(learned, label)
    for name, base, metric in (
        ("learned_vs_rule_auc", "geometric_sgm", "roc_auc"),
        ("learned_vs_rule_balanced_accuracy", "geometric_sgm", "balanced_accuracy"),
        ("auc_vs_speed_only", "speed_only", "roc_auc"),
    ):
        try:
            b = scorer.scores(base, label)
        except KeyError:
            v.missing(name, f"{base} not evaluated")
            continue
        diff = (ls[at + metric][0] - b[at + metric][0], ls[at + metric][1] - b[at + metric][1])
        v.put(name, diff, learned, baseline=base)


def _holdout(v: _Verdicts, ho: Mapping[str, Any]) -> None:
    """The balanced-accuracy drop on unseen road templates (``ho``: the holdout block)."""
    drop = (ho.get("drop") or {}).get("balanced_accuracy")
    if drop:
        v.put(
            "holdout_balanced_accuracy_drop",
            Interval(drop["estimate"], drop["lo"], drop["hi"], v.plan.level),
            str(ho.get("group")),
            templates=ho.get("templates"),
            n_sequences=ho.get("n_sequences"),
        )
    else:
        v.missing(
            "holdout_balanced_accuracy_drop",
            ho.get("why") or "no held-out road templates (risk_hybrid.holdout_templates)",
        )


def targets(
    scorer: Scorer,
    roles: Roles,
    spreads: Mapping[str, Stat],
    situations: Mapping[str, Any] | None = None,
    holdout: Mapping[str, Any] | None = None,
    thresholds: Mapping[str, Threshold] | None = None,
) -> dict[str, Any]:
    """The targets of :data:`TARGET_NAMES` against their acceptance thresholds (``thresholds``, default
    ``scorer.settings.acceptance``: ``acceptance.risk``): the shipped predictor's (default the
    headline) and the learned group's against the rule (default the headline), on the headline's
    label; ``spreads``: each model's prediction spread; ``situations`` / ``holdout``: those blocks
    of risk.json (``None``: not evaluated)."""
    thresholds = scorer.settings.acceptance if thresholds is None else thresholds
    absent = [n for n in TARGET_NAMES if n not in thresholds]
    if absent:
        raise ValueError(f"risk targets: no acceptance threshold for {absent} (acceptance.risk)")
    shipped = roles.shipped or roles.main_key
    learned = roles.learned or roles.main_key
    v = _Verdicts(scorer.plan, float(scorer.settings.t0), thresholds)
    _shipped(v, scorer, shipped, roles.main_label)
    _situational(v, situations or {}, shipped, float(scorer.settings.t0))
    _learned(v, scorer, learned, roles.main_label)
    _holdout(v, holdout or {})
    collapse_std = scorer.settings.collapse_std
    worst = min(spreads, key=lambda m: spreads[m][0])
    v.put(
        "spread",
        spreads[worst],
        worst,
        variant=worst,
        collapsed=sorted(m for m, st in spreads.items() if st[0] < collapse_std),
    )
    for key, who in ((shipped, "shipped"), (learned, "learned")):
        if scorer.groups.collapsed.get(key):  # a single run that collapsed
            for name, e in v.out.items():
                if name != "spread" and e.get("predictor") == key:
                    e.update(met=False, why=f"the {who} predictor ({key}) collapsed")
    return v.out
