"""The whole evaluation: networks and baselines on the same test frames (:func:`evaluate_suite`),
in named steps — predict, group the seeds, score each model / group / baseline, compare pairs,
break down, judge the targets — and readers of its outputs."""

from __future__ import annotations

from collections.abc import Collection, Mapping
from typing import Any

import numpy as np

from traffictwin.io.jsonio import json_clean
from traffictwin.risk.evaluation.bootstrap import (
    ClusterBootstrap,
    difference_json,
    difference_of_scores,
    holm,
    scores_with_ci,
    spread_stat,
)
from traffictwin.risk.evaluation.breakdowns import (
    critical_shares,
    holdout_block,
    region_block,
    situations,
)
from traffictwin.risk.evaluation.predictions import SuitePredictions, predict_suite
from traffictwin.risk.evaluation.scorer import Roles, Scorer, VariantGroups
from traffictwin.risk.evaluation.scoring import PAPER, summarise_paper_comparison
from traffictwin.risk.evaluation.settings import (
    BASELINES,
    GT_INPUT,
    ORACLES,
    SEED_MEAN,
    SuiteSettings,
)
from traffictwin.risk.evaluation.targets import targets
from traffictwin.risk.stereo_shards import SPLITS

#: what risk.json keeps of a model's training metadata (when present)
_MODEL_META = ("n_parameters", "best_val_mse", "best_step", "steps", "n_train")


def _header(source: Any, settings: SuiteSettings, roles: Roles, scorer: Scorer) -> dict[str, Any]:
    """risk.json's settings part: what was evaluated, how, and the data's size."""
    ci, plan, frames = settings.ci, scorer.plan, source.frames
    return {
        "paper": PAPER,
        "split": settings.split,
        "primary_label": settings.primary_label,
        "main_variant": roles.main,
        "main_predictor": roles.main_key,
        "shipped": roles.shipped,
        "learned": roles.learned,
        "decisions": {k: {f"{t:g}": c for t, c in v.items()} for k, v in scorer.decisions.items()},
        "thresholds_s": [float(t) for t in settings.thresholds_s],
        "thw_cap_s": float(settings.thw_cap),
        "collapse_std": float(settings.collapse_std),
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
            **{s: int((frames["split"] == s).sum()) for s in SPLITS},
        },
        "n_sequences": {
            s: int(frames.loc[frames["split"] == s, "scenario"].nunique()) for s in SPLITS
        },
    }


def _model_entry(scorer: Scorer, v: str, model: Any) -> dict[str, Any]:
    """One run: its settings, spread, collapse flag, metrics with intervals, and the paper gap."""
    lab = scorer.pred.label_of[v]
    info = scorer.settings.variants.get(v) or {}
    groups = scorer.groups
    entry: dict[str, Any] = {
        "label": lab,
        "inputs": list(model.cfg.inputs),
        "speed": bool(model.cfg.use_speed),
        "objective": str(model.meta.get("objective") or info.get("objective") or "mse"),
        "seed_offset": int(model.meta.get("seed_offset", info.get("seed_offset", 0)) or 0),
        "replicate_of": info.get("replicate_of"),
        "group": groups.group_of[v],
        "pred_std": groups.spread[v],
        "collapsed": groups.collapsed[v],
        **{k: model.meta[k] for k in _MODEL_META if k in model.meta},
    }
    entry.update(scorer.point(v, lab))
    scores_with_ci(scorer.scores(v, lab), scorer.plan, into=entry)
    entry["vs_paper"] = summarise_paper_comparison(entry, scorer.settings.t0)
    return entry


def _group_entries(scorer: Scorer) -> dict[str, Any]:
    """Each seed group of ≥ 2 runs: members, usable runs and (≥ 2 usable) the seed-averaged
    metrics with intervals and the seed-to-seed standard deviation of three headline metrics."""
    groups, label_of, t0 = scorer.groups, scorer.pred.label_of, scorer.settings.t0
    out: dict[str, Any] = {}
    for b, members in groups.members.items():
        if len(members) < 2:
            continue
        lab = label_of[b] if b in label_of else label_of[members[0]]
        used = groups.used[b]
        g: dict[str, Any] = {
            "label": lab,
            "members": members,
            "used": used,
            "collapsed": [m for m in members if groups.collapsed[m]],
            "n_seeds": len(used),
        }
        if len(used) >= 2:
            scores_with_ci(scorer.scores(f"{b}{SEED_MEAN}", lab), scorer.plan, into=g)
            g["seed_sd"] = {
                k.replace("|", "."): float(
                    np.std([scorer.scores(m, lab)[k][0] for m in used], ddof=1)
                )
                for k in ("test/mse", f"at_{t0:g}s|balanced_accuracy", f"at_{t0:g}s|roc_auc")
            }
        out[b] = g
    return out


def _baseline_entries(scorer: Scorer) -> tuple[dict[str, Any], dict[str, Any]]:
    """The baselines on the primary label, and on each other label a model was trained on."""
    pred, primary = scorer.pred, scorer.settings.primary_label

    def entry(name: str, lab: str) -> dict[str, Any]:
        e = {
            "label": lab,
            "oracle": name in ORACLES,
            "uses_gt_disparity": name in GT_INPUT,
            "pred_std": float(np.std(pred.baselines[lab][name])),
            **pred.baseline_info[lab][name],
        }
        e.update(scorer.point(name, lab))
        return scores_with_ci(scorer.scores(name, lab), scorer.plan, into=e)

    main: dict[str, Any] = {}
    by_label: dict[str, Any] = {}
    for lab in dict.fromkeys([primary, *pred.label_of.values()]):
        entries = {n: entry(n, lab) for n in BASELINES if n in pred.baselines[lab]}
        if lab == primary:
            main = entries
        else:
            by_label[lab] = entries
    return main, by_label


class _Differences:
    """Paired differences (a − b) of the suite's predictors, in order (``out``)."""

    def __init__(self, scorer: Scorer) -> None:
        self.scorer = scorer
        self.out: dict[str, Any] = {}

    def compare(self, a: str, b: str, lab: str, kind: str) -> None:
        plan = self.scorer.plan
        d = difference_of_scores(self.scorer.scores(a, lab), self.scorer.scores(b, lab))
        self.out[f"{a}|{b}"] = {
            "a": a,
            "b": b,
            "label": lab,
            "kind": kind,
            "oracle": b in ORACLES,
            "n_frames": plan.n,
            "n_clusters": plan.n_groups,
            **difference_json(d, plan),
        }


def _differences(
    scorer: Scorer,
    roles: Roles,
    objective: Mapping[str, str],
    on_learned_disparity: Collection[str] = (),
) -> dict[str, Any]:
    """Every run and seed group vs the speed-only baseline on its label; the headline vs the
    baselines; the learned group and the shipped model vs the SGM rule (the primary comparisons);
    the rule and the predictors ``on_learned_disparity`` (their seed groups once) on the learned
    stereo network's disparity vs the SGM rule; the headline vs every other variant on its label
    (``objective``: run → its training objective, telling an objective comparison from a variant
    one)."""
    groups, label_of, primary = scorer.groups, scorer.pred.label_of, scorer.settings.primary_label
    base_main, base_primary = (
        scorer.pred.baselines[roles.main_label],
        scorer.pred.baselines[primary],
    )
    diff = _Differences(scorer)
    for v in label_of:
        diff.compare(v, "speed_only", label_of[v], "vs_speed_only")
    for b, members in groups.members.items():
        if groups.seed_mean(b):
            diff.compare(f"{b}{SEED_MEAN}", "speed_only", label_of[members[0]], "vs_speed_only")
    for bname in ("geometric_sgm", "geometric_gt", "train_median"):
        if bname in base_main:
            diff.compare(roles.main_key, bname, roles.main_label, "vs_baseline")
    if "geometric_sgm" in base_primary and "geometric_learned" in base_primary:
        # the same corridor rule on the learned stereo network's disparity vs on SGM's
        diff.compare("geometric_learned", "geometric_sgm", primary, "disparity_source")
    if "geometric_sgm" in base_primary:
        # predictors reading the learned stereo network's disparity (seed groups once) vs the rule
        for v in label_of:
            if v not in on_learned_disparity:
                continue
            key = groups.predictor(v)
            if label_of[v] == primary and f"{key}|geometric_sgm" not in diff.out:
                diff.compare(key, "geometric_sgm", primary, "disparity_source")
    if "geometric_sgm" in base_primary:
        for key, kind in ((roles.learned, "learned_vs_rule"), (roles.shipped, "shipped_vs_rule")):
            if key and key != roles.main_key and f"{key}|geometric_sgm" not in diff.out:
                diff.compare(key, "geometric_sgm", primary, kind)
    for v in label_of:
        if groups.group_of[v] == groups.group_of[roles.main] or label_of[v] != roles.main_label:
            continue
        if groups.predictor(v) != v and v != groups.group_of[v]:
            continue  # a replicate: its group is compared once
        kind = "objective" if objective[roles.main] != objective[v] else "variant"
        diff.compare(roles.main_key, groups.predictor(v), roles.main_label, kind)
    return diff.out


def _g(d: Any, *keys: str) -> Any:
    """``d[k0][k1]...`` or ``None``."""
    for k in keys:
        if not isinstance(d, Mapping) or k not in d:
            return None
        d = d[k]
    return d


def _comparisons(differences: Mapping[str, Any], t0: float) -> dict[str, Any]:
    """The primary comparisons, and Holm's correction of every other one."""
    primary = [k for k, d in differences.items() if d["kind"] in ("learned_vs_rule",)]
    secondary = {
        f"{k}|{m}": _g(d, f"at_{t0:g}s", m, "p")
        for k, d in differences.items()
        if k not in primary
        for m in ("roc_auc", "balanced_accuracy")
    }
    return {
        "primary": primary,
        "primary_metrics": [f"at_{t0:g}s.roc_auc", f"at_{t0:g}s.balanced_accuracy"],
        "secondary_holm": {
            "metrics": [f"at_{t0:g}s.roc_auc", f"at_{t0:g}s.balanced_accuracy"],
            "p_adjusted": holm({k: v for k, v in secondary.items() if v is not None}),
            "note": "every other paired difference (a|b|metric) is exploratory: Holm-adjusted "
            "bootstrap p-values; a claim needs p_adjusted < 1 - level",
        },
    }


def _breakdowns(
    source: Any, models: Mapping[str, Any], scorer: Scorer, roles: Roles
) -> dict[str, Any]:
    """Critical shares per split (frames.csv, before the ORB check), the risk metric's region,
    the headline by situation type and the unseen road templates (those that apply)."""
    s, pred, groups = scorer.settings, scorer.pred, scorer.groups
    all_frames = source.risk.table("frames.csv")
    share_labels = [c for c in (*s.region_labels, s.primary_label) if c in all_frames.columns]
    out = {"critical_share": critical_shares(all_frames, list(dict.fromkeys(share_labels)), s.t0)}
    present = [c for c in s.region_labels if c in pred.labels]
    if len(present) >= 2:
        exclude = [v for v in models if groups.collapsed[v] or groups.group_of[v] != v]
        out["region"] = region_block(scorer, models, present, exclude)
    if "situation" in pred.table.columns:
        out["situations"] = situations(scorer, roles)
    if s.holdout and s.holdout.templates and "template" in pred.table.columns:
        out["holdout"] = holdout_block(scorer, s.holdout)
    return out


def evaluate_suite(
    source: Any, models: Mapping[str, Any], settings: SuiteSettings
) -> tuple[dict[str, Any], Any]:
    """Predict every model and baseline on ``settings.split`` of ``source`` and compute the
    metrics with their sequence-bootstrap intervals, the paired differences, the targets and the
    breakdowns.

    ``source``: :class:`traffictwin.risk.training.RiskSource`; ``models``: variant →
    :class:`traffictwin.risk.model_io.RiskModel` (``meta["label"]``: the column it is scored
    against). Returns ``(metrics, predictions)``: the risk.json dict and a per-frame DataFrame
    (:class:`~traffictwin.risk.evaluation.predictions.SuitePredictions` ``table``).
    """
    if not models:
        raise ValueError("evaluate_suite: no models to evaluate")
    if (settings.main_variant or next(iter(models))) not in models:
        raise ValueError(
            f"main variant '{settings.main_variant}' is not among the evaluated models "
            f"{list(models)}"
        )
    pred: SuitePredictions = predict_suite(source, models, settings)
    plan = ClusterBootstrap.from_config(pred.table["scenario"].to_numpy(), settings.ci)
    groups = VariantGroups.of(pred, settings)
    scorer = Scorer(pred, groups, plan, settings)
    roles = Roles.of(groups, pred, settings)
    metrics = _header(source, settings, roles, scorer)
    metrics["models"] = {v: _model_entry(scorer, v, m) for v, m in models.items()}
    metrics["groups"] = _group_entries(scorer)
    metrics["baselines"], metrics["baselines_by_label"] = _baseline_entries(scorer)
    objective = {v: e["objective"] for v, e in metrics["models"].items()}
    on_learned = [
        v
        for v, m in models.items()
        if "disp_learned" in getattr(getattr(m, "cfg", None), "inputs", ())
    ]
    metrics["differences"] = _differences(scorer, roles, objective, on_learned)
    metrics["comparisons"] = _comparisons(metrics["differences"], settings.t0)
    metrics.update(_breakdowns(source, models, scorer, roles))
    spreads = {v: spread_stat(pred.table[f"pred_{v}"].to_numpy(), plan) for v in models}
    metrics["targets"] = targets(
        scorer, roles, spreads, metrics.get("situations"), metrics.get("holdout")
    )
    return json_clean(metrics), pred.table


def main_series(
    metrics: Mapping[str, Any], pred: Any, variant: str
) -> tuple[str, np.ndarray, np.ndarray]:
    """(label, true risk, predicted risk) of ``variant`` on the test frames of ``pred``
    (:func:`evaluate_suite`'s outputs)."""
    label = metrics["models"][variant]["label"]
    return label, pred[label].to_numpy(), pred[f"pred_{variant}"].to_numpy()


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
