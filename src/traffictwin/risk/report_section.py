"""The risk part of the report (Feth et al.): what the results section says, which metrics and
figures it shows, and the paper's numbers beside ours. Entry point: :func:`provider`.

Reads ``risk.json`` (stage evaluate_risk), ``risk_selection.json`` (stage select_risk), plus
``orb.json`` (stage orb_filter), ``disparity.json`` (stage disparity) and ``risk_data.json`` (stage
generate_risk) in the data section. The tables are in :mod:`traffictwin.risk.report_tables`, the
findings in :mod:`traffictwin.risk.findings`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from traffictwin import paper_numbers as P
from traffictwin.interval_rule import HIGHER, LOWER, NO_INTERVAL, interval_side
from traffictwin.nested import lookup
from traffictwin.report import model as page
from traffictwin.report.acceptance import POINTER as ACCEPTANCE_POINTER
from traffictwin.report.claims import ClaimCheck, claim_verdict, fmt_interval, pct
from traffictwin.report.model import fmt_value
from traffictwin.report.summary import Baseline, Headline, headline, strongest
from traffictwin.report.tables import findings_group
from traffictwin.risk.findings import findings
from traffictwin.risk.report_tables import RISK_FILE, prose, risk_tables

TITLE = "Paper 2 — dynamic risk assessment from a stereo camera"

# The figures the risk stages write: file stem -> caption, in the order the section shows them.
FIGURES: dict[str, str] = {
    "stereo_example": "Left image, SGM disparity and exact disparity (mirrors the risk paper's Fig. 2)",
    "risk_metric_example": "Grid-map risk metric: scene and worst-time-headway region (cf. Figs. 3 and 4)",
    "orb_outlier_example": "A stereo pair the ORB check flags (Sec. 3.3)",
    "risk_training_curves": "Training and validation loss per variant, one panel per training objective, and every variant's validation MSE of the normalised risk (mirrors Figs. 5 and 6)",
    "risk_confusion": "Confusion matrix of the main variant at the primary THW threshold (mirrors Table 1)",
    "risk_scatter": "Predicted vs true risk on the test split (symmetric-log axes), the shipped "
    "predictor first, with the critical threshold",
    "risk_examples": "Test scenes with true and predicted risk (mirrors Fig. 7)",
    "risk_roc": "ROC of the shipped predictor and the headline network (each seed) vs the speed-only "
    "baseline and the corridor rule on SGM and on GT disparity (dashed), corridors chosen on "
    "validation, at the primary THW threshold",
}
FIGURE_PATTERN = r"risk|stereo|disparity|orb|camera|thw"
DATA_FILES = tuple(  # the data section's metrics files: all but risk_data.json required
    page.DataFile(f, f"{what} (reports/metrics/{f})", required=f != "risk_data.json")
    for f, what in (
        ("risk_data.json", "Risk data: stereo frames and risk labels"),
        ("disparity.json", "SGM disparity vs exact disparity"),
        ("orb.json", "ORB stereo-pair check vs injected faults"),
    )
)


def section(src: page.Sources, figures: list[page.Figure]) -> page.Section:
    """The risk results section: the paper's data, the tables of
    :func:`~traffictwin.risk.report_tables.risk_tables`, this run's findings and ``figures``."""
    sec = page.Section(TITLE, [f"Reference: {P.RISK_CITATION}."], figures=figures)
    if src.has(RISK_FILE):
        sec.paragraphs += [ACCEPTANCE_POINTER, prose("paper_data", P=P, num=fmt_value)]
        sec.tables = risk_tables(src)
    else:
        sec.paragraphs.append(
            f"`reports/metrics/{RISK_FILE}` is missing: the risk evaluation has not run."
        )
    sec.bullet_groups.append(findings_group(src, RISK_FILE, findings))
    return sec


#: the headline numbers at the primary threshold: (key, key under ``at_<t>s``, quantity)
HEADLINES = (
    ("auc", "roc_auc", "ROC-AUC of critical frames"),
    ("balanced_accuracy", "balanced_accuracy", "balanced accuracy of critical frames"),
    # defined even when the test frames hold one class only (the paper's metric)
    ("accuracy", "accuracy", "accuracy, critical vs uncritical"),
)


def headlines(metrics: Mapping[str, Any]) -> list[Headline]:
    """The shipped predictor (``shipped``: what users get, chosen on validation; else the main
    variant, its seed mean when replicates ran) on the ORB-passed test frames at the first THW
    threshold: ROC-AUC of critical frames (``auc``), balanced accuracy (at its validation-chosen
    decision cut) and accuracy, with their sequence-bootstrap intervals and the strongest
    baseline. (The MSE is no headline: a constant meets it.)"""
    risk = metrics.get(RISK_FILE)
    main, ts, shipped = (lookup(risk, k) for k in ("main_variant", "thresholds_s", "shipped"))
    if not isinstance(main, str) or not isinstance(ts, list) or not ts:
        return []
    ship_from = lookup(risk, "selection.shipped_from") or shipped
    rows = [
        (lookup(risk, f"models.{shipped}"), f"shipped predictor ({ship_from})"),
        (lookup(risk, f"groups.{main}"), f"main predictor {main}"),
        (lookup(risk, f"models.{main}"), f"main predictor {main}"),
    ]
    row, who = next(((r, w) for r, w in rows if isinstance(r, Mapping)), (None, ""))
    if row is None:
        return []
    t = float(ts[0])
    at, where, out = f"at_{t:g}s", f"{who}, test frames", []
    for key, m, quantity in HEADLINES:
        value, ci = lookup(row, f"{at}.{m}"), lookup(row, f"{at}.{m}_ci")
        base = _baseline(risk, shipped, at, m)
        out += headline(key, f"{quantity} (THW < {t:g} s)", where, value, ci, "f3", base)
    return out


def _baseline(risk: Any, shipped: Any, at: str, key: str) -> Baseline | None:
    """The best of ``risk.json``'s ``baselines`` on ``<at>.<key>`` (higher is better) on the same
    test frames: no oracle, none on exact (GT) disparity, not the shipped predictor itself (when
    select_risk shipped a rule)."""
    rows = lookup(risk, "baselines")
    rows = rows if isinstance(rows, Mapping) else {}
    where = f"metrics/{RISK_FILE}#baselines.{{}}.{at}.{key}"
    candidates = {
        name: (lookup(row, f"{at}.{key}"), lookup(row, f"{at}.{key}_ci"), where.format(name))
        for name, row in rows.items()
        if isinstance(row, Mapping)
        and not (row.get("oracle") or row.get("uses_gt_disparity") or name == shipped)
    }
    return strongest(candidates, higher_better=True)


PAPER = "Paper 2 — risk"
#: risk.json models.<name>: the DAVE-2-like network on the paper's inputs and label
PAPER_MODEL = "paper"


def claims(metrics: Mapping[str, Any]) -> list[ClaimCheck]:
    """The paper's numbers (:data:`~traffictwin.paper_numbers.RISK`) against this run's
    network trained as in the paper (``models.paper`` of ``risk.json``; else the main variant)
    on the test frames, with their 95 % sequence-bootstrap intervals: accuracy at the paper's THW
    (reproduced when our interval reaches 72.87 % or lies above it), the test MSE of the
    normalised risk (when it reaches 0.0147 or lies below), the paper's lead over Wang & Kato's
    70.77 % (a difference: our interval must lie above it), and the share of pairs the ORB check
    drops (no interval: not comparable). Empty when ``risk.json`` names no such model."""
    risk = metrics.get(RISK_FILE)
    name = PAPER_MODEL if isinstance(lookup(risk, f"models.{PAPER_MODEL}"), Mapping) else None
    name = name or lookup(risk, "main_variant")
    row = lookup(risk, f"models.{name}") if isinstance(name, str) else None
    if not isinstance(row, Mapping):
        return []
    t, paper = P.RISK["thw_threshold_s"].value, P.RISK
    acc, wk = paper["accuracy"].value, paper["wang_kato_accuracy"].value
    specs = (  # (paper number, its scale, this run's key, the paper's side, what, format)
        ("accuracy", 100.0, f"at_{t:g}s.accuracy", HIGHER, "accuracy", pct),
        ("test_mse", 1.0, "test/mse", LOWER, "test MSE", "{:.3g}"),
        ("wang_kato_accuracy", 100.0, f"at_{t:g}s.accuracy", HIGHER, "accuracy", pct),
    )
    texts = (
        f"The CNN classifies critical vs uncritical (THW < {t:g} s) with {acc:.2f} % accuracy.",
        f"Testing average error (MSE of the normalised risk) {paper['test_mse'].value:g}.",
        f"Its accuracy beats Wang & Kato's {wk:.2f} % (another task and data).",
    )
    out = []
    for (key, scale, metric, side, what, fmt), claim in zip(specs, texts):
        ci = lookup(row, f"{metric}_ci") or {}
        sides = [interval_side(ci.get("lo"), ci.get("hi"), paper[key].value / scale)]
        # the paper's lead over Wang & Kato is a difference, the others numbers it prints
        verdict = claim_verdict(sides, side, value=key != "wang_kato_accuracy")
        seen = fmt_interval(lookup(row, metric), ci.get("lo"), ci.get("hi"), fmt)
        seen += f" (network `{name}`, test frames)"
        out.append(ClaimCheck(PAPER, claim, paper[key].source, f"{what} {seen}", verdict))
    dropped, total = lookup(risk, "n_frames.orb_outliers_dropped"), lookup(risk, "n_frames.total")
    ok = isinstance(dropped, int) and isinstance(total, int) and total > 0
    share = f"{pct(dropped / total)} of {total:,} pairs dropped" if ok else "n/a"
    orb = paper["orb_outlier_pct"]
    claim = f"The ORB check drops about {orb.value:g} % of the stereo pairs."
    measured = f"{share} (a count without an interval)"
    verdict = claim_verdict([NO_INTERVAL], LOWER)
    return [*out, ClaimCheck(PAPER, claim, orb.source, measured, verdict)]


def provider() -> page.SectionProvider:
    """The risk section's provider for the report."""
    return page.SectionProvider(
        name="risk",
        headlines=headlines,
        claims=claims,
        section=section,
        figures=FIGURES,
        figure_pattern=FIGURE_PATTERN,
        data_files=DATA_FILES,
    )
