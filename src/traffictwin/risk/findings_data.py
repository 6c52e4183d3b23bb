"""What the risk findings state, as a typed record (:class:`RiskFindings`) built from
``reports/metrics/risk.json`` (layout: :mod:`traffictwin.risk.evaluation`).

One record type and one builder per findings group (the headline against the paper, the shipped
predictor, learned model vs rule, seeds, baselines, variants, critical shares, the region effect,
situations, targets, data); :func:`findings_record` assembles them. Numbers are formatted with their
intervals (:mod:`traffictwin.risk.findings_values`); a group whose metrics are missing is None /
empty, never invented. The sentences are rendered by :mod:`traffictwin.risk.findings`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, NamedTuple

from traffictwin.risk.evaluation import GT_INPUT, PAPER, SEED_MEAN
from traffictwin.risk.findings_values import (
    Claim,
    FindingsRun,
    as_float,
    beats,
    claim_record,
    diff_text,
    dig,
    findings_run,
    formatted,
    interval_of,
    percent,
    with_ci,
)
from traffictwin.stats import excludes_zero

#: how findings name the baselines
BASELINE_NAMES = {
    "train_mean": "training-mean predictor",
    "train_median": "majority class (training median)",
    "speed_only": "speed-only baseline (isotonic fit on the training split)",
    "geometric_sgm": "corridor rule (SGM disparity + speed, corridor chosen on validation)",
    "geometric_learned": "corridor rule on the learned stereo network's disparity (corridor chosen on validation)",
    "geometric_gt": "corridor rule on ground-truth disparity (perfect stereo, straight corridor)",
}
#: baselines the headline is compared with, in the order the findings list them
SHOWN_BASELINES = ("speed_only", "geometric_sgm", "geometric_gt", "train_median")
#: metrics the comparisons quote, with their names
COMPARED = (("roc_auc", "ROC-AUC"), ("balanced_accuracy", "balanced accuracy"))
REGIONS = {
    "risk_thw_corridor": "corridor",
    "risk_thw_paper": "paper",
    "risk_thw_fov": "camera_fov",
}
P_LABEL, F_LABEL = "risk_thw_paper", "risk_thw_fov"


class Variant(NamedTuple):
    """What a variant is (template macro ``describe``): inputs, speed, label, objective."""

    inputs: str
    speed: bool
    label: Any
    objective: Any  #: shown unless it is the default (MSE)


def variant_of(e: Mapping[str, Any]) -> Variant:
    obj = e.get("objective")
    return Variant(
        "+".join(e.get("inputs") or []) or "?",
        bool(e.get("speed")),
        e.get("label"),
        obj if obj and obj != "mse" else None,
    )


@dataclass(frozen=True)
class Paper:
    """The headline against the paper's numbers."""

    main: str
    n_test: Any
    label: Any
    mse: str
    paper_mse: str
    ratio: str  #: test MSE / the paper's
    below: bool  #: test MSE below the paper's
    accuracy: str
    paper_accuracy: str
    wang_kato_accuracy: str
    balanced: str
    f1: str
    roc: str
    seeds: tuple[Any, str, str] | None  #: (n seeds, seed-mean MSE, seed-mean accuracy)
    critical: str
    paper_critical: str
    collapsed: bool


def _paper(r: FindingsRun) -> Paper | None:
    m, at, head = r.models[r.main], r.at, r.head
    mse = as_float(m.get("test/mse"))
    if mse is None:
        return None
    hm = head if isinstance(head, Mapping) else m  # the headline's figures (seed mean if any)
    return Paper(
        main=r.main,
        n_test=m.get("test/n"),
        label=m.get("label"),
        mse=with_ci(m, "test/mse", ".5f"),
        paper_mse=f"{PAPER['test/mse']:.5f}",
        ratio=f"{mse / PAPER['test/mse']:.2f}",
        below=mse < PAPER["test/mse"],
        accuracy=with_ci(m, f"{at}|accuracy", pct=True),
        paper_accuracy=percent(PAPER["accuracy"]),
        wang_kato_accuracy=percent(PAPER["wang_kato_accuracy"]),
        balanced=with_ci(m, f"{at}|balanced_accuracy", pct=True),
        f1=with_ci(m, f"{at}|f1"),
        roc=with_ci(m, f"{at}|roc_auc"),
        seeds=(
            head.get("n_seeds"),
            with_ci(hm, "test/mse", ".5f"),
            with_ci(hm, f"{at}|accuracy", pct=True),
        )
        if head
        else None,
        critical=percent(as_float(dig(m, f"{at}|critical_fraction_true"))),
        paper_critical=percent(76789 / PAPER["n_frames"]),
        collapsed=r.main in r.collapsed,
    )


@dataclass(frozen=True)
class Shipped:
    """The shipped predictor (chosen on validation) on the test split."""

    name: Any
    kind: Any
    sgm_half_width: Any
    gt_half_width: Any
    balanced: str
    balanced_1s: str
    roc: str
    thw_error: str


def _shipped(r: FindingsRun) -> Shipped | None:
    shipped = r.metrics.get("shipped")
    if not shipped or not isinstance(r.models.get(shipped), Mapping):
        return None
    sm, sel, at = r.models[shipped], r.metrics.get("selection") or {}, r.at
    rules = sel.get("rules") or {}
    return Shipped(
        name=sel.get("shipped_from", shipped),
        kind=sel.get("shipped_kind", "?"),
        sgm_half_width=rules.get("geometric_sgm", "n/a"),
        gt_half_width=rules.get("geometric_gt", "n/a"),
        balanced=with_ci(sm, f"{at}|balanced_accuracy", pct=True),
        balanced_1s=with_ci(sm, "at_1s|balanced_accuracy", pct=True),
        roc=with_ci(sm, f"{at}|roc_auc"),
        thw_error=with_ci(sm, "test/thw_median_error_critical_s", ".3f"),
    )


@dataclass(frozen=True)
class Learning:
    """The primary comparison: the learned model against the SGM corridor rule."""

    learned: str
    better: bool | None
    claims: list[Claim]
    held: int  #: secondary differences with Holm-adjusted p < 0.05
    n_secondary: int


def _learning(r: FindingsRun) -> Learning | None:
    learned = r.metrics.get("learned")
    d = r.diffs.get(f"{learned}|geometric_sgm") if learned else None
    if d is None:
        return None
    comparisons = r.metrics.get("comparisons") or {}
    holm = (comparisons.get("secondary_holm") or {}).get("p_adjusted") or {}
    return Learning(
        learned=learned,
        better=beats(d, f"{r.at}|roc_auc"),
        claims=[
            claim_record(d, f"{r.at}|{k}", name, learned, "geometric_sgm") for k, name in COMPARED
        ],
        held=sum(1 for v in holm.values() if v < 0.05),
        n_secondary=len(holm),
    )


@dataclass(frozen=True)
class Seeds:
    """The headline's seeds: ROC-AUC per run, seed means and seed sd."""

    main: str
    per_run: list[tuple[str, str]]
    roc: str
    roc_sd: str
    balanced: str
    balanced_sd: str


def _seeds(r: FindingsRun) -> Seeds | None:
    head, at = r.head, r.at
    if not head:
        return None
    sd = head.get("seed_sd") or {}
    return Seeds(
        main=r.main,
        per_run=[
            (v, formatted(as_float(dig(r.models.get(v), f"{at}|roc_auc")), ".3f"))
            for v in head.get("members", [])
        ],
        roc=with_ci(head, f"{at}|roc_auc"),
        roc_sd=formatted(as_float(sd.get(f"{at}.roc_auc")), ".3f"),
        balanced=with_ci(head, f"{at}|balanced_accuracy", pct=True),
        balanced_sd=percent(as_float(sd.get(f"{at}.balanced_accuracy"))),
    )


class Baseline(NamedTuple):
    name: str
    roc: str
    balanced: str
    mse: str


@dataclass(frozen=True)
class Baselines:
    """The baselines on the headline's frames and the headline against them."""

    scores: list[Baseline]
    critical_speed: str | None  #: the speed-only baseline's critical speed (m/s)
    claims: list[Claim]


def _baselines(r: FindingsRun) -> Baselines | None:
    at = r.at
    scores = [
        Baseline(
            BASELINE_NAMES[b],
            with_ci(e, f"{at}|roc_auc"),
            with_ci(e, f"{at}|balanced_accuracy", pct=True),
            with_ci(e, "test/mse", ".5f"),
        )
        for b in SHOWN_BASELINES
        if isinstance(e := r.base.get(b), Mapping)
    ]
    vmin = as_float((r.base.get("speed_only") or {}).get(f"critical_speed_at_{r.t:g}s"))
    if not scores and vmin is None:
        return None
    claims = []
    for b in SHOWN_BASELINES if r.main_key not in r.collapsed else ():
        d = r.diffs.get(f"{r.main_key}|{b}")
        if d is None:
            continue
        nb = b + (" (GT disparity)" if b in GT_INPUT else "")
        claims += [claim_record(d, f"{at}|{k}", name, r.main_key, nb) for k, name in COMPARED[:1]]
        claims.append(claim_record(d, "test/mse", "MSE", r.main_key, nb))
    return Baselines(scores, None if vmin is None else f"{vmin:.1f}", claims)


class SpeedRow(NamedTuple):
    """A variant against the speed-only baseline of its own label."""

    name: str
    variant: Variant | None  #: None: a failed run (collapsed), not compared
    better: bool | None
    diff: str | None  #: ΔROC-AUC estimate [lo, hi]


def _vs_speed(r: FindingsRun) -> list[SpeedRow]:
    rows = []
    for v in sorted(r.models):
        if v in r.collapsed:
            rows.append(SpeedRow(v, None, None, None))
            continue
        d = r.diffs.get(f"{v}|speed_only")
        if d is not None:
            iv = interval_of(dig(d, f"{r.at}|roc_auc"))
            rows.append(
                SpeedRow(v, variant_of(r.models[v]), beats(d, f"{r.at}|roc_auc"), diff_text(iv))
            )
    return rows


def _vs_speed_groups(r: FindingsRun) -> list[Claim]:
    return [
        claim_record(d, f"{r.at}|roc_auc", "ROC-AUC", f"{b} (seed mean)", "speed_only")
        for b in sorted(r.groups)
        if (d := r.diffs.get(f"{b}{SEED_MEAN}|speed_only")) is not None
    ]


class VariantClaims(NamedTuple):
    """The headline against another variant (or objective) of its label."""

    other: str
    variant: Variant
    claims: list[Claim]


def _variant_claims(r: FindingsRun, kind: str) -> list[VariantClaims]:
    """The headline − each other ``kind`` ("variant" / "objective") on the headline's label."""
    out = []
    for _, d in sorted(r.diffs.items()):
        if d.get("a") != r.main_key or d.get("kind") != kind:
            continue
        b = str(d.get("b"))
        bv = b.removesuffix(SEED_MEAN)
        if bv in r.collapsed or r.main_key in r.collapsed:
            continue
        claims = [claim_record(d, f"{r.at}|{mk}", name, r.main_key, b) for mk, name in COMPARED]
        claims.append(claim_record(d, "test/mse", "MSE", r.main_key, b))
        out.append(VariantClaims(b, variant_of(r.models.get(bv, {})), claims))
    return out


def _other_label(r: FindingsRun) -> list[tuple[str, Any]]:
    """(variant, its label) of the variants trained on another label than the headline's."""
    label = r.models[r.main].get("label")
    return [
        (v, r.models[v].get("label"))
        for v in sorted(
            v
            for v, e in r.models.items()
            if e.get("label") != label and v not in r.collapsed and e.get("group", v) == v
        )
    ]


@dataclass(frozen=True)
class CriticalShare:
    """Critical share per region, train / val / test."""

    threshold: str
    regions: list[tuple[str, list[str]]]


def _critical(r: FindingsRun) -> CriticalShare | None:
    cs = r.metrics.get("critical_share") or {}
    splits = cs.get("splits") or {}
    labs = [lab for lab in REGIONS if any(lab in s for s in splits.values())]
    if not labs:
        return None
    return CriticalShare(
        formatted(as_float(cs.get("threshold_s")), "g"),
        [
            (
                REGIONS[lab],
                [
                    percent(as_float((splits.get(s) or {}).get(lab)))
                    for s in ("train", "val", "test")
                ],
            )
            for lab in labs
        ],
    )


class RegionNet(NamedTuple):
    name: str
    label: str
    skill: str
    balanced: str
    roc: str


@dataclass(frozen=True)
class Region:
    """The risk metric region: the paper's against the camera's field of view."""

    paper: str  #: the two labels' names
    fov: str
    agreement: str
    critical_paper: str
    critical_fov: str
    nets: list[RegionNet]
    sgm_skill: tuple[str, str] | None  #: the SGM corridor rule's skill on (fov, paper)
    fov_net: str | None
    paper_net: str | None
    skill_diff: str | None  #: fov_net − paper_net skill, estimate [lo, hi]
    skill_verdict: str  #: "higher" / "lower" / "none" (the interval covers zero)


def _region_nets(r: FindingsRun, reg: Mapping[str, Any]) -> tuple[Any, Any, Any]:
    """(the camera-region network, the paper-region network, their paired skill difference)."""

    def first(label: str) -> str | None:
        ok = (v for v, e in sorted(r.models.items()) if e.get("label") == label)
        return next((v for v in ok if v not in r.collapsed), None)

    fov_net = first(F_LABEL)
    sd = next(
        (
            d
            for d in (reg.get("skill_differences") or {}).values()
            if d.get("label_a") == F_LABEL and d.get("label_b") == P_LABEL and d.get("a") == fov_net
        ),
        None,
    )
    return fov_net, (sd or {}).get("b") or first(P_LABEL), sd


def _region(r: FindingsRun) -> Region | None:
    reg, t = r.metrics.get("region"), r.t
    labels = (reg or {}).get("labels") or {} if isinstance(reg, Mapping) else {}
    if P_LABEL not in labels or F_LABEL not in labels:
        return None
    preds = reg.get("predictors") or {}
    agree = (reg.get("agreement") or {}).get(f"{P_LABEL}|{F_LABEL}") or (reg.get("agreement") or {})
    fov_net, paper_net, sd = _region_nets(r, reg)
    iv = interval_of(sd)
    sgm = lambda lab: with_ci(dig(preds, f"geometric_sgm|{lab}"), "skill", ".2f")  # noqa: E731
    return Region(
        paper=P_LABEL,
        fov=F_LABEL,
        agreement=with_ci(agree, f"class_agreement_at_{t:g}s", pct=True),
        critical_paper=percent(as_float(dig(labels, f"{P_LABEL}|critical_fraction_at_{t:g}s"))),
        critical_fov=percent(as_float(dig(labels, f"{F_LABEL}|critical_fraction_at_{t:g}s"))),
        nets=[
            RegionNet(
                name,
                lab,
                with_ci(e, "skill", ".2f"),
                with_ci(e, "balanced_accuracy", pct=True),
                with_ci(e, "roc_auc"),
            )
            for name, lab in ((paper_net, P_LABEL), (fov_net, F_LABEL))
            if name is not None and (e := dig(preds, f"{name}|{lab}")) is not None
        ],
        sgm_skill=(sgm(F_LABEL), sgm(P_LABEL))
        if dig(preds, f"geometric_sgm|{P_LABEL}") is not None
        else None,
        fov_net=fov_net,
        paper_net=paper_net,
        skill_diff=diff_text(iv),
        skill_verdict="none"
        if iv is None or not excludes_zero(iv)
        else ("higher" if iv.estimate > 0 else "lower"),
    )


class Situation(NamedTuple):
    """The headline (and the speed-only baseline) on one situation type."""

    name: str
    n_sequences: Any
    critical: str
    recall: str
    specificity: str
    speed_recall: str
    speed_specificity: str


def _situations(r: FindingsRun) -> list[Situation]:
    out = []
    for s, e in sorted((r.metrics.get("situations") or {}).items()):
        p = dig(e, f"predictors|{r.main_key}") or {}
        sp = dig(e, "predictors|speed_only") or {}
        out.append(
            Situation(
                s,
                e.get("n_sequences"),
                percent(as_float(e.get("critical_share"))),
                with_ci(p, "recall", pct=True),
                with_ci(p, "specificity", pct=True),
                percent(as_float(sp.get("recall"))),
                percent(as_float(sp.get("specificity"))),
            )
        )
    return out


class Target(NamedTuple):
    """One risk target: the value (with its interval) against the threshold."""

    name: str
    predictor: Any  #: shown when set
    value: str
    lo: str | None
    hi: str | None
    op: Any
    threshold: str
    met: bool
    why: Any  #: shown when set


def _targets(r: FindingsRun) -> list[Target]:
    out = []
    for name, e in (r.metrics.get("targets") or {}).items():
        lo, hi = as_float(e.get("lo")), as_float(e.get("hi"))
        both = lo is not None and hi is not None
        out.append(
            Target(
                name,
                e.get("predictor") or None,
                formatted(as_float(e.get("value")), ".4g"),
                f"{lo:.4g}" if both else None,
                f"{hi:.4g}" if both else None,
                e.get("op", ""),
                formatted(as_float(e.get("threshold")), "g"),
                bool(e.get("met")),
                e.get("why") or None,
            )
        )
    return out


@dataclass(frozen=True)
class Data:
    """Frames (and the stereo-pair check's drops) and sequences per split."""

    total: Any
    dropped: Any
    dropped_share: str
    paper_dropped_share: str
    frames: tuple[Any, Any, Any]  #: train / val / test
    sequences: tuple[Any, Any, Any] | None


def _data(r: FindingsRun) -> Data | None:
    nf = r.metrics.get("n_frames")
    if not (isinstance(nf, Mapping) and nf.get("total")):
        return None
    ns = r.metrics.get("n_sequences") or {}
    return Data(
        total=nf.get("total"),
        dropped=nf.get("orb_outliers_dropped", 0),
        dropped_share=percent(nf.get("orb_outliers_dropped", 0) / nf["total"]),
        paper_dropped_share=percent(1 - PAPER["n_frames"] / 110152),
        frames=(nf.get("train"), nf.get("val"), nf.get("test")),
        sequences=(ns.get("train"), ns.get("val"), ns.get("test")) if ns else None,
    )


@dataclass(frozen=True)
class RiskFindings:
    """Everything the risk findings state, computed from ``risk.json`` (template
    ``templates/findings.md.j2``); a part is None / empty where its metrics are missing."""

    main: str | None  #: the headline variant; None: no risk network was evaluated
    main_key: str = ""
    threshold: str = ""  #: the THW threshold (s)
    collapse_std: str = ""
    collapsed: list[tuple[str, str]] = field(default_factory=list)  #: (run, prediction std)
    paper: Paper | None = None
    shipped: Shipped | None = None
    learning: Learning | None = None
    seeds: Seeds | None = None
    baselines: Baselines | None = None
    vs_speed: list[SpeedRow] = field(default_factory=list)
    vs_speed_groups: list[Claim] = field(default_factory=list)
    variants: list[VariantClaims] = field(default_factory=list)
    objectives: list[VariantClaims] = field(default_factory=list)
    other_label: list[tuple[str, Any]] = field(default_factory=list)
    critical_share: CriticalShare | None = None
    region: Region | None = None
    situations: list[Situation] = field(default_factory=list)
    targets: list[Target] = field(default_factory=list)
    data: Data | None = None


def findings_record(metrics: Mapping[str, Any]) -> RiskFindings:
    """What the findings of the ``risk.json`` dict state (see module docstring)."""
    r = findings_run(metrics)
    if r is None:
        return RiskFindings(main=None)
    return RiskFindings(
        main=r.main,
        main_key=r.main_key,
        threshold=f"{r.t:g}",
        collapse_std=formatted(as_float(metrics.get("collapse_std")), "g"),
        collapsed=[
            (v, formatted(as_float(r.models[v].get("pred_std")), ".2g"))
            for v in sorted(r.collapsed)
        ],
        paper=_paper(r),
        shipped=_shipped(r),
        learning=_learning(r),
        seeds=_seeds(r),
        baselines=_baselines(r),
        vs_speed=_vs_speed(r),
        vs_speed_groups=_vs_speed_groups(r),
        variants=_variant_claims(r, "variant"),
        objectives=_variant_claims(r, "objective"),
        other_label=_other_label(r),
        critical_share=_critical(r),
        region=_region(r),
        situations=_situations(r),
        targets=_targets(r),
        data=_data(r),
    )
