"""Breakdowns of the suite: critical shares per split, the risk metric's region (each predictor
against each region label), the headline per situation type and the unseen road templates."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from itertools import combinations
from typing import Any

import numpy as np

from traffictwin.risk.evaluation.bootstrap import (
    ClusterBootstrap,
    Stat,
    bootstrap_scores,
    lin,
    lohi,
    mean_of_scores,
    ratio,
    scores_with_ci,
    seed_draws,
)
from traffictwin.risk.evaluation.scorer import Roles, Scorer
from traffictwin.risk.evaluation.scoring import label_agreement
from traffictwin.risk.evaluation.settings import BASELINES, SEED_MEAN, Holdout
from traffictwin.risk.metric import risk_threshold
from traffictwin.risk.stereo_shards import SPLITS
from traffictwin.stats import mean_ci


def critical_shares(frames: Any, labels: Sequence[str], threshold_s: float) -> dict[str, Any]:
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


def _label_summary(scorer: Scorer, present: Sequence[str]) -> tuple[dict, dict]:
    """Each region label's mean and critical share, and the pairwise agreement of the labels."""
    plan, ys = scorer.plan, scorer.pred.labels
    t0, thresholds = scorer.settings.t0, scorer.settings.thresholds_s
    kw = {"n_boot": plan.n_boot, "seed": plan.seed, "level": plan.level}
    labels: dict[str, Any] = {}
    for lab in present:
        iv = mean_ci((ys[lab] > risk_threshold(t0)).astype(np.float64), plan.clusters, **kw)
        labels[lab] = {
            "mean": float(np.mean(ys[lab])),
            f"critical_fraction_at_{t0:g}s": iv.estimate,
            f"critical_fraction_at_{t0:g}s_ci": lohi(iv),
        }
    agreement: dict[str, Any] = {}
    for a, b in combinations(present, 2):
        agree = label_agreement(ys[a], ys[b], thresholds)
        for t in thresholds:
            thr = risk_threshold(t)
            iv = mean_ci(((ys[a] > thr) == (ys[b] > thr)).astype(np.float64), plan.clusters, **kw)
            agree[f"class_agreement_at_{t:g}s_ci"] = lohi(iv)
        agreement[f"{a}|{b}"] = agree
    return labels, agreement


def _skill(scorer: Scorer, name: str, label: str) -> Stat:
    """1 − MSE / MSE of the label's training mean."""
    ref = scorer.scores("train_mean", label)["test/mse"]
    one = (1.0, np.ones(scorer.plan.n_boot))
    return lin(one, ratio(scorer.scores(name, label)["test/mse"], ref), 1.0, -1.0)


def _skill_differences(
    scorer: Scorer, models: Mapping[str, Any], present: Sequence[str], exclude: Sequence[str]
) -> dict[str, Any]:
    """Networks that differ only in the region of their training label: paired skill difference,
    each scored on its own label (does a region make the risk more learnable?)."""
    label_of = scorer.pred.label_of
    out: dict[str, Any] = {}
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
        iv = scorer.plan.interval(lin(_skill(scorer, a, la), _skill(scorer, b, lb), 1.0, -1.0))
        out[f"{a}|{b}"] = {
            "a": a,
            "b": b,
            "label_a": la,
            "label_b": lb,
            "estimate": iv.estimate,
            "lo": iv.lo,
            "hi": iv.hi,
        }
    return out


def region_block(
    scorer: Scorer, models: Mapping[str, Any], present: Sequence[str], exclude: Sequence[str] = ()
) -> dict[str, Any]:
    """Label means and critical shares, pairwise label agreement, every predictor's metrics
    against every region label in ``present`` (skill = 1 − MSE / MSE of that label's training
    mean), and the paired skill difference of networks that differ only in their training label's
    region (``skill_differences``, each scored on its own label; ``exclude``: runs left out of
    those — collapsed ones and seed replicates), with CIs."""
    labels, agreement = _label_summary(scorer, present)
    region: dict[str, Any] = {"labels": labels, "agreement": agreement, "predictors": {}}
    at = f"at_{scorer.settings.t0:g}s|"
    keep = {
        "test/mse": "test/mse",
        "test/mae": "test/mae",
        at + "accuracy": "accuracy",
        at + "balanced_accuracy": "balanced_accuracy",
        at + "f1": "f1",
        at + "roc_auc": "roc_auc",
    }
    base = scorer.pred.baselines[present[0]]
    for name in [*models, *(n for n in BASELINES if n in base)]:
        for lab in present:
            sc = scorer.scores(name, lab)
            flat = {new: sc[old] for old, new in keep.items()}
            flat["skill"] = _skill(scorer, name, lab)
            region["predictors"].setdefault(name, {})[lab] = scores_with_ci(flat, scorer.plan)
    region["skill_differences"] = _skill_differences(scorer, models, present, exclude)
    return region


def situations(scorer: Scorer, roles: Roles) -> dict[str, Any]:
    """Per situation type: frames, sequences, critical share and, for the headline (seed mean),
    the shipped predictor, the learned group, the speed-only and the geometric SGM baseline,
    accuracy / recall / specificity / balanced accuracy / ROC-AUC at the primary threshold with
    CIs over that situation's sequences, on the headline's label (each run with its decision
    cuts chosen on validation)."""
    table, label, t0 = scorer.pred.table, roles.main_label, scorer.settings.t0
    y = scorer.pred.labels[label]
    situation = table["situation"].astype(str).to_numpy()
    preds = {
        key: [(v, table[f"pred_{v}"].to_numpy()) for v in _runs_of(scorer, key)]
        for key in dict.fromkeys(
            [roles.main_key, *(e for e in (roles.shipped, roles.learned) if e)]
        )
    }
    base_pred = scorer.pred.baselines[label]
    for b in ("speed_only", "geometric_sgm"):
        if b in base_pred:
            preds[b] = [(b, base_pred[b])]
    at = f"at_{t0:g}s|"
    keep = ("accuracy", "recall", "specificity", "balanced_accuracy", "roc_auc")
    res: dict[str, Any] = {}
    for s in sorted(set(situation)):
        m = situation == s
        sub = scorer.plan.subset(m)
        e: dict[str, Any] = {
            "n_frames": int(m.sum()),
            "n_sequences": sub.n_groups,
            "critical_share": float(np.mean(y[m] > risk_threshold(t0))),
            "predictors": {},
        }
        for name, ps in preds.items():
            runs = [
                bootstrap_scores(
                    y[m], p[m], sub, (t0,), scorer.settings.thw_cap, scorer.cuts(v, label)
                )
                for v, p in ps
            ]
            sc = mean_of_scores(runs)
            e["predictors"][name] = scores_with_ci({k: sc[at + k] for k in keep}, sub)
        res[s] = e
    return res


def _runs_of(scorer: Scorer, key: str) -> list[str]:
    """The runs behind a predictor key (a seed mean's usable runs, else the key itself)."""
    if key.endswith(SEED_MEAN):
        return scorer.groups.used[key.removesuffix(SEED_MEAN)]
    return [key]


def _on_heldout(
    scorer: Scorer, group: str, mask: np.ndarray, sub: ClusterBootstrap, stream: int
) -> dict[str, Stat] | None:
    """Scores of ``group``'s usable runs (their mean, seeds resampled from ``stream``) on the
    frames where ``mask`` holds (plan ``sub``), on the primary label; ``None`` without runs."""
    runs = scorer.groups.used.get(group) or []
    if not runs:
        return None
    s = scorer.settings
    label = s.primary_label
    table, y = scorer.pred.table, scorer.pred.labels[label]
    per = [
        bootstrap_scores(
            y[mask],
            table[f"pred_{v}"].to_numpy()[mask],
            sub,
            s.thresholds_s,
            s.thw_cap,
            scorer.cuts(v, label),
        )
        for v in runs
    ]
    return mean_of_scores(per, seed_draws(len(runs), sub, stream) if len(runs) > 1 else None)


def holdout_block(scorer: Scorer, holdout: Holdout) -> dict[str, Any]:
    """Generalisation to road templates never seen in training: the ``group`` (runs trained
    without ``templates``) on the test frames of those templates, the ``reference`` (the same
    model trained on every template) on the same frames and on the whole test split, and the
    drop ``reference on the standard test split − group on the held-out templates`` of the
    balanced accuracy / ROC-AUC at the primary threshold (seeds and sequences resampled; the two
    sides are resampled independently), on the primary label."""
    at = f"at_{scorer.settings.t0:g}s|"
    templates = [str(t) for t in holdout.templates]
    mask = scorer.pred.table["template"].astype(str).isin(templates).to_numpy()
    res: dict[str, Any] = {
        "templates": templates,
        "group": holdout.group,
        "reference": holdout.reference,
        "n_frames": int(mask.sum()),
    }
    if not mask.any():
        return {**res, "why": "no test frame of the held-out templates"}
    sub = scorer.plan.subset(mask)
    res["n_sequences"] = sub.n_groups
    keep = ("balanced_accuracy", "roc_auc", "recall", "specificity")
    held = _on_heldout(scorer, holdout.group, mask, sub, 101)
    ref_h = _on_heldout(scorer, holdout.reference, mask, sub, 102)
    ref_runs = scorer.groups.used.get(holdout.reference) or []
    if held is None or not ref_runs:
        return {**res, "why": "held-out or reference runs missing (or collapsed)"}
    ref_key = f"{holdout.reference}{SEED_MEAN}" if len(ref_runs) > 1 else ref_runs[0]
    ref_std = scorer.scores(ref_key, scorer.settings.primary_label)
    for name, sc, pl in (
        ("heldout", held, sub),
        ("reference_on_heldout", ref_h, sub),
        ("reference_standard", ref_std, scorer.plan),
    ):
        if sc is not None:
            res[name] = scores_with_ci({k: sc[at + k] for k in keep}, pl)
    res["drop"] = {}
    for k in ("balanced_accuracy", "roc_auc"):
        iv = scorer.plan.interval(lin(ref_std[at + k], held[at + k], 1.0, -1.0))
        res["drop"][k] = {"estimate": iv.estimate, "lo": iv.lo, "hi": iv.hi}
    return res
