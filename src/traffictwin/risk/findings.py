"""Findings of the risk evaluation as markdown bullets, generated from ``reports/metrics/risk.json``
(layout: :mod:`traffictwin.risk.evaluation`); the report stage calls :func:`findings`.

:func:`findings_record` computes what is stated (the metrics entries to quote, verdicts, flags,
names; a part whose metrics are missing is None or empty, never invented); the sentences and the
formats of their numbers are in ``templates/findings.md.j2``. What the section's tables show
(every predictor's scores with their intervals) is not restated.

Rules: a paired difference is a finding only when its 95 % sequence-bootstrap interval excludes
zero (:func:`beats`, the interval rule of :mod:`traffictwin.interval_rule`). A collapsed model
(one output for every frame) is listed as a failed run and never interpreted. The corridor rule on
ground-truth disparity sees perfect stereo but a straight corridor: a reference, not an oracle.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from traffictwin.interval_rule import HIGHER, LOWER, NO_INTERVAL, finite, interval_side
from traffictwin.nested import lookup
from traffictwin.report.claims import fmt_interval
from traffictwin.report.model import fmt_value
from traffictwin.report.prose import render_prose
from traffictwin.risk.evaluation import LOWER_IS_BETTER, PAPER, SEED_MEAN

TEMPLATES = Path(__file__).parent / "templates"
P_LABEL, F_LABEL = "risk_thw_paper", "risk_thw_fov"


def with_ci(d: Any, key: str, fmt: str = "f3") -> str:
    """``value [lo, hi]`` of ``d``'s dotted ``key`` and ``key + "_ci"`` in the report's number
    format ``fmt`` (:func:`~traffictwin.report.model.fmt_value`; the value alone without an
    interval, "n/a" for a missing number)."""
    ci = lookup(d, f"{key}_ci") or {}
    return fmt_interval(lookup(d, key), ci.get("lo"), ci.get("hi"), lambda x: fmt_value(x, fmt))


def signed(d: Mapping[str, Any] | None) -> str:
    """A paired difference ``{estimate, lo, hi}`` as ``+0.012 [−0.003, +0.027]`` (minus as −)."""
    return fmt_interval(*((d or {}).get(k) for k in ("estimate", "lo", "hi")), "{:+.3f}").replace(
        "-", "−"
    )


def beats(diff: Mapping[str, Any] | None, metric: str) -> bool | None:
    """True / False when the paired interval ``{lo, hi}`` of dotted ``metric`` of ``diff`` (a − b;
    ``at_1.5s.roc_auc``, ``test/mse``) says a is better / worse than b; None when it does not
    exclude zero (or there is none)."""
    d = lookup(diff, metric)
    side = interval_side(d.get("lo"), d.get("hi")) if isinstance(d, Mapping) else None
    if side not in (LOWER, HIGHER):
        return None
    return (side == LOWER) == (metric.rsplit(".", 1)[-1] in LOWER_IS_BETTER)


def _learning(m: Mapping[str, Any], at: str) -> dict[str, Any] | None:
    """The primary comparison: the learned model against the SGM corridor rule (paired ROC-AUC;
    ``better`` None: no significant difference), and how many of the secondary differences keep
    a Holm-adjusted p < 0.05."""
    learned = m.get("learned")
    d = lookup(m, f"differences.{learned}|geometric_sgm") if learned else None
    if d is None:
        return None
    holm = lookup(m, "comparisons.secondary_holm.p_adjusted") or {}
    return dict(
        learned=learned,
        better=beats(d, f"{at}.roc_auc"),
        held=sum(v < 0.05 for v in holm.values()),
        n_secondary=len(holm),
    )


def _region(m: Mapping[str, Any], t: float, collapsed: set[str]) -> dict[str, Any] | None:
    """The risk metric region, the paper's against the camera's field of view: the two labels'
    class agreement and critical shares, and the paired skill difference of the first
    camera-region network (not collapsed) to the paper-region one (``skill``, None without an
    interval; ``verdict`` higher / lower / none: the interval covers zero)."""
    reg = m.get("region") if isinstance(m.get("region"), Mapping) else {}
    labels = reg.get("labels") or {}
    if P_LABEL not in labels or F_LABEL not in labels:
        return None
    fov = sorted(v for v, e in m["models"].items() if e.get("label") == F_LABEL)
    fov_net = next((v for v in fov if v not in collapsed), None)
    pair = (F_LABEL, P_LABEL, fov_net)
    diffs = (reg.get("skill_differences") or {}).values()
    sd = next((d for d in diffs if (d.get("label_a"), d.get("label_b"), d.get("a")) == pair), {})
    complete = finite(sd.get("estimate")) is not None
    side = interval_side(sd.get("lo"), sd.get("hi")) if complete else NO_INTERVAL
    agreement = reg.get("agreement") or {}
    share = f"critical_fraction_at_{t:g}s"
    return dict(
        agreement=agreement.get(f"{P_LABEL}|{F_LABEL}") or agreement,
        critical=[lookup(labels, f"{lab}.{share}") for lab in (P_LABEL, F_LABEL)],
        skill=None if side == NO_INTERVAL else (sd.get("a"), sd.get("b"), signed(sd)),
        verdict={HIGHER: "higher", LOWER: "lower"}.get(side, "none"),
    )


def findings_record(m: Mapping[str, Any]) -> dict[str, Any]:
    """What the findings of the ``risk.json`` dict ``m`` state (see the module docstring):
    ``main`` None when no risk network was evaluated."""
    models: Mapping[str, Any] = m.get("models", {})
    main = m.get("main_variant") or next(iter(models), None)
    if main is None or main not in models:
        return dict(main=None)
    t = (m.get("thresholds_s") or [PAPER["threshold_s"]])[0]
    collapsed = {v for v, e in models.items() if e.get("collapsed")}
    mse = finite(models[main].get("test/mse"))
    seeds = str(m.get("main_predictor")).endswith(SEED_MEAN) and lookup(m, f"groups.{main}.seed_sd")
    label = models[main].get("label")
    return dict(
        main=main,
        label=label,
        threshold=f"{t:g}",
        at=f"at_{t:g}s",
        mse_ratio=None if mse is None else mse / PAPER["test/mse"],
        collapse_std=m.get("collapse_std"),
        collapsed=[(v, models[v].get("pred_std")) for v in sorted(collapsed)],
        seed_sd=seeds if isinstance(seeds, Mapping) else None,
        learning=_learning(m, f"at_{t:g}s"),
        critical_speed=finite(lookup(m, f"baselines.speed_only.critical_speed_at_{t:g}s")),
        other_label=[
            (v, e.get("label"))
            for v, e in sorted(models.items())
            if e.get("label") != label and v not in collapsed and e.get("group", v) == v
        ],
        region=_region(m, t, collapsed),
    )


def findings(metrics: Mapping[str, Any]) -> str:
    """Markdown bullet list: the paper comparison, learned model vs rule
    (a claim only where the interval excludes zero), failed runs, seeds, the speed-only
    baseline's critical speed, variants on other labels, the region effect."""
    record = findings_record(metrics)
    text = render_prose(TEMPLATES, "findings.md.j2", f=record, ci=with_ci, num=fmt_value)
    return text.rstrip("\n")
