"""What the risk findings state, as a typed record (:class:`RiskFindings`) built from
``reports/metrics/risk.json`` (layout: :mod:`traffictwin.risk.evaluation`).

One record type and one builder per findings group (the shipped predictor, learned model vs
rule, seeds, other labels, the region effect, situations, data); :func:`findings_record`
assembles them. The baselines' scores and the paired differences of the variants are not
restated: the report's tables of every predictor and of the paired differences show them. Python decides *what* is
stated: which predictors and metrics entries, the paired comparisons and their verdicts, the
failed runs. The template ``templates/findings.md.j2`` says it, formatting the numbers of the
entries (:data:`traffictwin.risk.findings.HELPERS`). A group
whose metrics are missing is None / empty, never invented.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, NamedTuple

from traffictwin.nested import lookup
from traffictwin.risk.evaluation import PAPER
from traffictwin.risk.findings_values import (
    Claim,
    FindingsRun,
    as_float,
    beats,
    claim_record,
    diff_text,
    findings_run,
    interval_of,
)
from traffictwin.stats import excludes_zero

#: metrics the comparisons quote, with their names
COMPARED = (("roc_auc", "ROC-AUC"), ("balanced_accuracy", "balanced accuracy"))
P_LABEL, F_LABEL = "risk_thw_paper", "risk_thw_fov"


class Shipped(NamedTuple):
    """The shipped predictor (``m``: its test metrics), as the selection on validation chose it."""

    m: Mapping[str, Any]
    name: Any
    kind: Any
    half_widths: tuple[Any, Any]  #: the SGM and GT corridor rules' half-widths (m)


def _shipped(r: FindingsRun) -> Shipped | None:
    shipped = r.metrics.get("shipped")
    if not shipped or not isinstance(r.models.get(shipped), Mapping):
        return None
    sel = r.metrics.get("selection") or {}
    rules = sel.get("rules") or {}
    return Shipped(
        r.models[shipped],
        sel.get("shipped_from", shipped),
        sel.get("shipped_kind", "?"),
        (rules.get("geometric_sgm", "n/a"), rules.get("geometric_gt", "n/a")),
    )


class Learning(NamedTuple):
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
    holm = lookup(r.metrics, "comparisons.secondary_holm.p_adjusted") or {}
    return Learning(
        learned,
        beats(d, f"{r.at}.roc_auc"),
        [claim_record(d, f"{r.at}.{k}", name, learned, "geometric_sgm") for k, name in COMPARED],
        sum(1 for v in holm.values() if v < 0.05),
        len(holm),
    )


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
class Region:
    """The risk metric region: the paper's against the camera's field of view."""

    agreement: Mapping[str, Any]  #: the two labels' class agreement (with its interval)
    critical: tuple[Any, Any]  #: critical share with the paper's / the camera's label
    nets: list[tuple[str, str, Mapping[str, Any]]]  #: (network, its label, its scores there)
    sgm: tuple[Mapping[str, Any], Mapping[str, Any]] | None  #: SGM corridor rule on (fov, paper)
    fov_net: str | None
    paper_net: str | None
    skill_diff: str | None  #: fov_net − paper_net skill, estimate [lo, hi]
    skill_verdict: str  #: "higher" / "lower" / "none" (the interval covers zero)
    labels: tuple[str, str] = (P_LABEL, F_LABEL)


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
    reg = r.metrics.get("region")
    labels = (reg or {}).get("labels") or {} if isinstance(reg, Mapping) else {}
    if P_LABEL not in labels or F_LABEL not in labels:
        return None
    preds = reg.get("predictors") or {}
    agree = (reg.get("agreement") or {}).get(f"{P_LABEL}|{F_LABEL}") or (reg.get("agreement") or {})
    fov_net, paper_net, sd = _region_nets(r, reg)
    iv = interval_of(sd)
    share = f"critical_fraction_at_{r.t:g}s"
    sgm = preds.get("geometric_sgm") or {}
    return Region(
        agreement=agree,
        critical=(lookup(labels, f"{P_LABEL}.{share}"), lookup(labels, f"{F_LABEL}.{share}")),
        nets=[
            (name, lab, e)
            for name, lab in ((paper_net, P_LABEL), (fov_net, F_LABEL))
            if name is not None and (e := lookup(preds.get(name), lab)) is not None
        ],
        sgm=(sgm.get(F_LABEL), sgm.get(P_LABEL)) if sgm.get(P_LABEL) is not None else None,
        fov_net=fov_net,
        paper_net=paper_net,
        skill_diff=diff_text(iv),
        skill_verdict="none"
        if iv is None or not excludes_zero(iv)
        else ("higher" if iv.estimate > 0 else "lower"),
    )


def _situations(r: FindingsRun) -> list[tuple[str, Mapping, Mapping, Mapping]]:
    """(situation, its entry, the headline's scores there, the speed-only baseline's)."""
    return [
        (
            s,
            e,
            lookup(e, f"predictors.{r.main_key}") or {},
            lookup(e, "predictors.speed_only") or {},
        )
        for s, e in sorted((r.metrics.get("situations") or {}).items())
    ]


@dataclass(frozen=True)
class RiskFindings:
    """Everything the risk findings state, computed from ``risk.json`` (template
    ``templates/findings.md.j2``); a part is None / empty where its metrics are missing."""

    main: str | None  #: the headline variant; None: no risk network was evaluated
    main_key: str = ""
    threshold: str = ""  #: the THW threshold (s)
    at: str = ""  #: its metrics key (``at_1.5s``)
    collapse_std: Any = None
    collapsed: list[tuple[str, Any]] = field(default_factory=list)  #: (run, prediction std)
    model: Mapping[str, Any] = field(default_factory=dict)  #: the headline's metrics entry
    mse_ratio: float | None = None  #: its test MSE / the paper's (None: no test MSE)
    head: Mapping[str, Any] | None = None  #: its seed group (None: a single run)
    seed_runs: list[tuple[str, Any]] = field(default_factory=list)  #: (run, ROC-AUC) of the group
    shipped: Shipped | None = None
    learning: Learning | None = None
    critical_speed: float | None = None  #: the speed-only baseline's critical speed (m/s)
    other_label: list[tuple[str, Any]] = field(default_factory=list)
    region: Region | None = None
    situations: list[tuple[str, Mapping, Mapping, Mapping]] = field(default_factory=list)
    data: Mapping[str, Any] | None = None  #: frames per split (``n_frames``)
    sequences: Mapping[str, Any] = field(default_factory=dict)  #: sequences per split


def findings_record(metrics: Mapping[str, Any]) -> RiskFindings:
    """What the findings of the ``risk.json`` dict state (see module docstring)."""
    r = findings_run(metrics)
    if r is None:
        return RiskFindings(main=None)
    nf, mse = metrics.get("n_frames"), as_float(r.models[r.main].get("test/mse"))
    head = r.head if isinstance(r.head, Mapping) and r.head else None
    return RiskFindings(
        main=r.main,
        main_key=r.main_key,
        threshold=f"{r.t:g}",
        at=r.at,
        collapse_std=metrics.get("collapse_std"),
        collapsed=[(v, r.models[v].get("pred_std")) for v in sorted(r.collapsed)],
        model=r.models[r.main],
        mse_ratio=None if mse is None else mse / PAPER["test/mse"],
        head=head,
        seed_runs=[
            (v, lookup(r.models.get(v), f"{r.at}.roc_auc")) for v in (head or {}).get("members", [])
        ],
        shipped=_shipped(r),
        learning=_learning(r),
        critical_speed=as_float(lookup(r.base.get("speed_only"), f"critical_speed_at_{r.t:g}s")),
        other_label=_other_label(r),
        region=_region(r),
        situations=_situations(r),
        data=nf if isinstance(nf, Mapping) and nf.get("total") else None,
        sequences=metrics.get("n_sequences") or {},
    )
