"""Every choice of the risk evaluation, made on the validation split (stage ``select_risk``).

:func:`select_on_validation` scores every candidate on the validation frames and picks

* the corridor half-width (m) of the SGM rule and of the GT-disparity rule (highest ROC-AUC,
  :func:`~traffictwin.risk.selection.tune_half_width`),
* every predictor's decision cut on the normalised risk at each THW threshold (highest balanced
  accuracy, :func:`~traffictwin.risk.selection.best_cut`),
* the predictor to ship (:func:`~traffictwin.risk.selection.choose`: highest ROC-AUC at the
  primary threshold among the runs of the main network variant, the hybrid runs and the SGM rule;
  a tie goes to the simpler).

When the validation frames hold too few critical or uncritical frames to rank candidates
(:func:`~traffictwin.risk.selection.too_few`: fewer than
:data:`~traffictwin.risk.selection.MIN_CLASS_FRAMES` of either), nothing is chosen on them:
each rule takes the label's own corridor half-width (:func:`label_half_width`), the decision
cuts are the label's thresholds, and the SGM rule ships; the records say why (``note``).

The result is a :class:`Selection` (``to_json``: the layout of
``reports/metrics/risk_selection.json``); the test split is never read here.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import pandas as pd

from traffictwin.io.jsonio import json_clean
from traffictwin.risk.baselines import corridor_distances, fit_speed_only, thw_from_distance
from traffictwin.risk.config import EvalRiskConfig, MetricParams
from traffictwin.risk.metric import RiskConfig, risk_threshold, thw_to_risk
from traffictwin.risk.predictor import RiskFrames
from traffictwin.risk.predictors import GeometricRiskModel, predictor_kind
from traffictwin.risk.selection import best_cut, choose, roc_auc, too_few, tune_half_width
from traffictwin.risk.source import RiskSource, check_label, input_keys

#: the corridor rules and the disparity each reads (a rule runs where its source has the disparity:
#: ``geometric_learned`` needs the learned stereo network's data/stereo_learned); of the rules only
#: the SGM rule competes for shipping (the learned one is evaluated beside it)
RULES = {
    "geometric_sgm": "disp_sgm",
    "geometric_gt": "disp_gt",
    "geometric_learned": "disp_learned",
}
#: the camera intrinsics a shipped corridor rule keeps
CAMERA_KEYS = ("fx", "fy", "cx", "cy", "baseline", "mount_x", "mount_height", "width", "height")
#: the learned group the main variant's runs compete with for shipping
HYBRID_GROUP = "hybrid"
#: the hybrid trained on the learned stereo network's disparity: its runs compete for shipping too
#: (a shipped one carries that network: traffictwin risk computes the disparity it reads)
LEARNED_DISPARITY_GROUP = "hybrid_learned"


@dataclass(frozen=True)
class SelectionSetup:
    """What the choices depend on besides the data and the models."""

    ev: EvalRiskConfig  #: thresholds (s), candidate half-widths, batch size, collapse_std
    subject: MetricParams  #: the subject's footprint (m)
    primary: str  #: the label every candidate is scored on
    settings: Mapping[str, Mapping[str, Any]]  #: run-variant settings (``replicate_of``)
    held_runs: Collection[str]  #: runs trained without the held-out road templates
    holdout: Sequence[str]  #: the held-out road templates


@dataclass(frozen=True)
class ValidationScores:
    """The validation frames (ORB-passed) in one order: label, speed and every candidate's score."""

    rows: pd.DataFrame
    y: np.ndarray  #: the primary label (normalised risk)
    speed: np.ndarray  #: m/s
    scores: dict[str, np.ndarray]  #: predictor → normalised risk score
    distances: dict[str, np.ndarray]  #: rule → (N, K) free distances (m), one per width of
    #: :func:`_rule_widths` (the candidates, then the prior)


@dataclass(frozen=True)
class RuleChoice:
    """A corridor rule's half-width (m) and every candidate's validation figures."""

    half_width: float
    candidates: list[dict[str, float]]  #: :func:`tune_half_width`'s table
    note: str | None = None  #: why the width is the prior, not a validation choice

    def to_json(self) -> dict[str, Any]:
        """Candidates keyed by width, ``"1p25"`` for 1.25 m (dotted report keys)."""
        return {
            "half_width": self.half_width,
            "candidates": {f"{c['half_width']:g}".replace(".", "p"): c for c in self.candidates},
            "note": self.note,
        }


@dataclass(frozen=True)
class Decision:
    """A decision cut on the normalised risk and its validation balanced accuracy."""

    cut: float
    balanced_accuracy: float


@dataclass(frozen=True)
class PredictorChoice:
    """One candidate on the validation frames (its own, for a run that held templates out)."""

    kind: str  #: dave2 / hybrid / geometric / speed_only
    group: str  #: its variant group (``replicate_of``, else itself)
    pred_std: float  #: spread of its scores (normalised risk)
    collapsed: bool  #: pred_std below ``collapse_std``: a failed run
    roc_auc: float  #: at the primary threshold (NaN without both classes)
    n_frames: int
    decision: dict[str, Decision]  #: THW threshold (s, as ``f"{t:g}"``) → cut


@dataclass(frozen=True)
class GroupChoice:
    """A learned variant's runs and their seed-averaged validation ROC-AUC."""

    runs: list[str]
    kind: str
    roc_auc_mean: float


@dataclass(frozen=True)
class ShippedChoice:
    """The predictor to ship and the candidates it was chosen among."""

    predictor: str
    kind: str
    roc_auc: float
    candidates: list[str]
    decision: dict[str, Decision]
    note: str | None = None  #: why it is the prior (SGM rule at the label's corridor), not chosen


@dataclass(frozen=True)
class Selection:
    """Every choice made on the validation split (``reports/metrics/risk_selection.json``)."""

    n_frames: int
    n_sequences: int
    label: str
    thresholds_s: list[float]
    criterion: str
    holdout_templates: list[str]
    rules: dict[str, RuleChoice]
    predictors: dict[str, PredictorChoice]
    groups: dict[str, GroupChoice]
    learned: str | None  #: the learned group that competed for shipping (None: none trained)
    shipped: ShippedChoice

    def to_json(self) -> dict[str, Any]:
        """The strict-JSON layout (undefined figures, one class on validation, as null)."""
        return json_clean(
            {
                "split": "val",
                "n_frames": self.n_frames,
                "n_sequences": self.n_sequences,
                "label": self.label,
                "thresholds_s": self.thresholds_s,
                "criterion": self.criterion,
                "holdout_templates": self.holdout_templates,
                "rules": {r: c.to_json() for r, c in self.rules.items()},
                "predictors": {n: asdict(c) for n, c in self.predictors.items()},
                "groups": {g: asdict(c) for g, c in self.groups.items()},
                "learned": self.learned,
                "shipped": asdict(self.shipped),
            }
        )


def label_half_width(subject: MetricParams) -> float:
    """The risk label's own corridor half-width (m): half the nominal lane width
    (:class:`~traffictwin.risk.metric.RiskConfig`'s ``lane_width``, 3.5 m; the simulated lanes
    are 3.2-3.7 m) plus ``risk_data.metric.corridor_margin``. The prior of the rules' width."""
    return float(RiskConfig.lane_width / 2 + subject.corridor_margin)


def _rule_widths(setup: SelectionSetup) -> list[float]:
    """The candidate half-widths (m), then the prior when it is no candidate."""
    widths = [float(w) for w in setup.ev.geometric.half_widths]
    prior = label_half_width(setup.subject)
    return widths if prior in widths else [*widths, prior]


def on_label(models: Mapping[str, Any], label: str) -> dict[str, Any]:
    """The models trained on ``label`` (a model without one in its meta counts as ``label``)."""
    return {v: m for v, m in models.items() if str(m.meta.get("label") or label) == label}


def validation_scores(
    source: RiskSource, models: Mapping[str, Any], setup: SelectionSetup
) -> ValidationScores:
    """Every model's scores and every rule's corridor distances on the validation frames."""
    ev = setup.ev
    frames = source.split_frames("val")
    fpath = str(source.risk.root / "frames.csv")
    if len(frames) == 0:
        raise ValueError(f"{fpath}: the validation split has no frames (after the ORB check)")
    rules = {r: k for r, k in RULES.items() if k in source.disparity_keys}
    keys = sorted({k for m in models.values() for k in input_keys(m.cfg)} | set(rules.values()))
    geo = ev.geometric.params(setup.subject.subject_length, setup.subject.subject_width)
    half_widths = _rule_widths(setup)
    camera = source.camera
    preds: dict[str, list[np.ndarray]] = {v: [] for v in models}
    dists: dict[str, list[np.ndarray]] = {r: [] for r in rules}
    order = []
    for rows, arr in source.iter_arrays(frames, keys):
        sp = rows["speed"].to_numpy(np.float64).astype(np.float32)
        frames = RiskFrames.of_arrays(arr, sp)  # each model reads the disparity it names
        for v, m in models.items():
            preds[v].append(m.predict_frames(frames, ev.batch_size))
        for r, k in rules.items():
            dists[r].append(corridor_distances(arr[k], camera, geo, half_widths))
        order.append(rows)
    rows = pd.concat(order)
    return ValidationScores(
        rows=rows,
        y=check_label(rows, setup.primary, fpath).astype(np.float64),
        speed=rows["speed"].to_numpy(np.float64),
        scores={v: np.concatenate(ps).astype(np.float64) for v, ps in preds.items()},
        distances={r: np.concatenate(d) for r, d in dists.items()},
    )


def _tune_rules(val: ValidationScores, setup: SelectionSetup) -> dict[str, RuleChoice]:
    """Each rule's half-width (the prior when validation cannot rank); its score at that width
    joins ``val.scores``."""
    t0 = setup.ev.thresholds_s[0]
    half_widths = [float(w) for w in setup.ev.geometric.half_widths]
    widths = _rule_widths(setup)
    prior = label_half_width(setup.subject)
    positive = val.y > risk_threshold(t0)
    reason = too_few(positive)
    note = None if reason is None else f"{reason}: the label's corridor half-width {prior:g} m"
    rules = {}
    for r in val.distances:
        d = val.distances[r]
        w, table = tune_half_width(
            d[:, : len(half_widths)], val.speed, positive, half_widths, t0, prior=prior
        )
        k = widths.index(w)
        val.scores[r] = thw_to_risk(thw_from_distance(d[:, k], val.speed)).astype(np.float64)
        rules[r] = RuleChoice(w, table, note)
    return rules


def _speed_only(source: RiskSource, val: ValidationScores, primary: str) -> None:
    """The speed-only baseline (fitted on train) joins ``val.scores`` to get its cut too."""
    train = source.split_frames("train")
    if len(train):
        fpath = str(source.risk.root / "frames.csv")
        so = fit_speed_only(
            train["speed"].to_numpy(np.float64),
            check_label(train, primary, fpath).astype(np.float64),
        )
        val.scores["speed_only"] = so.predict(val.speed)


def _predictor(
    s: np.ndarray, y: np.ndarray, kind: str, group: str, ev: EvalRiskConfig
) -> PredictorChoice:
    """Scores ``s`` against the label ``y`` (both on the frames the predictor is tuned on); a
    threshold with too few frames of either class keeps the label's own cut."""
    spread = float(np.std(s))
    decision = {}
    for t in ev.thresholds_s:
        pos = y > risk_threshold(t)
        if too_few(pos) is None:
            cut, ba = best_cut(pos, s, risk_threshold(t))
        else:
            cut, ba = risk_threshold(t), float("nan")
        decision[f"{t:g}"] = Decision(cut, ba)
    return PredictorChoice(
        kind=kind,
        group=group,
        pred_std=spread,
        collapsed=bool(spread < ev.collapse_std),
        roc_auc=roc_auc(y > risk_threshold(ev.thresholds_s[0]), s),
        n_frames=int(s.size),
        decision=decision,
    )


def _predictors(
    val: ValidationScores, models: Mapping[str, Any], setup: SelectionSetup
) -> dict[str, PredictorChoice]:
    """Every scored candidate's validation figures and decision cuts."""

    def kind_of(name: str) -> str:
        if name in RULES:
            return "geometric"
        return "speed_only" if name == "speed_only" else predictor_kind(models[name])

    def group_of(name: str) -> str:
        """A run's variant group: its ``replicate_of`` (settings or model meta), else itself."""
        if name not in models:
            return name
        rep = (setup.settings.get(name) or {}).get("replicate_of")
        return str(rep or models[name].meta.get("replicate_of") or name)

    holdout = list(setup.holdout)
    seen = ~val.rows["template"].isin(holdout).to_numpy() if holdout else np.ones(len(val.y), bool)
    out = {}
    for name, s in val.scores.items():
        # a run trained without the held-out templates is tuned on the validation frames of
        # the templates it saw (so its held-out test frames stay unseen)
        m = seen if name in setup.held_runs else np.ones(len(val.y), bool)
        out[name] = _predictor(s[m], val.y[m], kind_of(name), group_of(name), setup.ev)
    return out


def _groups(
    predictors: Mapping[str, PredictorChoice], models: Mapping[str, Any]
) -> dict[str, GroupChoice]:
    """The groups: seed-averaged validation AUC of every learned variant on the primary label."""
    runs_of: dict[str, list[str]] = {}
    for name, e in predictors.items():
        if name in models:
            runs_of.setdefault(e.group, []).append(name)
    return {
        g: GroupChoice(
            runs=runs,
            kind=predictors[runs[0]].kind,
            roc_auc_mean=float(np.mean([predictors[r].roc_auc for r in runs])),
        )
        for g, runs in runs_of.items()
    }


def _ship(
    predictors: Mapping[str, PredictorChoice],
    groups: Mapping[str, GroupChoice],
    main_group: str,
    rule: RuleChoice,
    reason: str | None,
) -> tuple[str | None, ShippedChoice]:
    """(the learned group that competes, the shipped predictor): the main variant's group or the
    hybrid (higher mean AUC), its runs, the runs of the hybrid on the learned stereo network's
    disparity (:data:`LEARNED_DISPARITY_GROUP`) and the SGM rule; collapsed learned runs are failed runs
    (the rule is no trained model: a constant output only says nothing was in its corridor).
    With ``reason`` (why validation cannot rank: :func:`too_few`) or without a finite validation
    AUC among them, the SGM rule ``rule`` ships at its width (the prior) with a note saying so."""
    learned = [g for g in (main_group, HYBRID_GROUP) if g in groups]
    best = max(learned, key=lambda g: groups[g].roc_auc_mean) if learned else None
    competing = [*learned, *(g for g in (LEARNED_DISPARITY_GROUP,) if g in groups)]
    candidates = {
        n: predictors[n]
        for n in [*(r for g in competing for r in groups[g].runs), "geometric_sgm"]
        if n in RULES or not predictors[n].collapsed
    }
    note = None
    if reason is not None or not any(np.isfinite(c.roc_auc) for c in candidates.values()):
        shipped = "geometric_sgm"
        width = "the label's corridor half-width" if rule.note else "its validation half-width"
        note = (
            f"{reason or 'no candidate has a validation ROC-AUC'}: the corridor rule at "
            f"{width} {rule.half_width:g} m, not chosen on validation"
        )
    else:
        shipped = choose({n: {"roc_auc": c.roc_auc, "kind": c.kind} for n, c in candidates.items()})
    c = predictors[shipped]
    return best, ShippedChoice(shipped, c.kind, c.roc_auc, sorted(candidates), c.decision, note)


def select_on_validation(
    source: RiskSource, models: Mapping[str, Any], setup: SelectionSetup
) -> Selection:
    """Every choice on ``source``'s validation frames among ``models`` (trained runs; those on
    another label than ``setup.primary`` are left out), the two corridor rules and the
    speed-only baseline (see the module docstring)."""
    ev = setup.ev
    on_primary = on_label(models, setup.primary)
    val = validation_scores(source, on_primary, setup)
    rules = _tune_rules(val, setup)
    _speed_only(source, val, setup.primary)
    predictors = _predictors(val, models, setup)
    groups = _groups(predictors, models)
    main_group = (setup.settings.get(ev.main_variant) or {}).get("replicate_of")
    t0 = ev.thresholds_s[0]
    learned, shipped = _ship(
        predictors,
        groups,
        main_group or ev.main_variant,
        rules["geometric_sgm"],
        too_few(val.y > risk_threshold(t0)),
    )
    return Selection(
        n_frames=int(len(val.rows)),
        n_sequences=int(val.rows["scenario"].nunique()),
        label=setup.primary,
        thresholds_s=[float(t) for t in ev.thresholds_s],
        criterion=f"ROC-AUC of critical (THW < {t0:g} s) on the validation split",
        holdout_templates=list(setup.holdout),
        rules=rules,
        predictors=predictors,
        groups=groups,
        learned=learned,
        shipped=shipped,
    )


def shipped_rule(
    selection: Selection, setup: SelectionSetup, camera: Mapping[str, Any]
) -> GeometricRiskModel:
    """The shipped corridor rule at its chosen half-width (m) with the ``camera`` intrinsics."""
    geo = setup.ev.geometric.params(
        setup.subject.subject_length,
        setup.subject.subject_width,
        selection.rules[selection.shipped.predictor].half_width,
    )
    return GeometricRiskModel(geo, {k: float(camera[k]) for k in CAMERA_KEYS})
