"""The risk section's tables with 95 % sequence-bootstrap intervals (every predictor on the same
test frames, paired differences, critical shares, situations) and the choices made on the
validation split (``risk_selection.json``, stage select_risk).

Shown when ``risk.json`` has intervals (``bootstrap``): every metric with its interval
(``<metric>_ci``), the paired differences (``differences``: a claim only where the interval
excludes 0), the critical share of every region per split and the situation breakdown (the
targets: the index's acceptance table, :mod:`traffictwin.report.acceptance`).
"""

from __future__ import annotations

from traffictwin.report import model as page
from traffictwin.report.model import NA, Cell, Table, fmt_value
from traffictwin.risk.evaluation import GT_INPUT, SEED_MEAN
from traffictwin.risk.findings_values import beats
from traffictwin.risk.report_tables import (
    RISK_BASELINE_LABELS,
    RISK_FILE,
    SELECTION_FILE,
    ci_cell,
    risk_threshold_key,
    value_cell,
)


def has_intervals(src: page.Sources) -> bool:
    """Whether ``risk.json`` has sequence-bootstrap intervals (``bootstrap``)."""
    return isinstance(src.get(RISK_FILE, "bootstrap"), dict)


def _ci_rows(src: page.Sources) -> list[tuple[str, str, str]]:
    """``(key prefix, row name, status)``: the headline's seed mean (if any), every model (main
    first) and every baseline."""
    models = src.get(RISK_FILE, "models") or {}
    groups = src.get(RISK_FILE, "groups") or {}
    baselines = src.get(RISK_FILE, "baselines") or {}
    main = src.get(RISK_FILE, "main_variant")
    rows = []
    for b in sorted(groups, key=lambda g: (g != main, g)):
        if isinstance(groups[b], dict) and isinstance(groups[b].get("test/mse"), (int, float)):
            n = groups[b].get("n_seeds")
            rows.append((f"groups.{b}", f"{b} (seed mean of {n})", "seed mean"))
    for v in sorted(models, key=lambda v: (v != main, v)):
        e = models[v] if isinstance(models[v], dict) else {}
        status = "collapsed: failed run" if e.get("collapsed") else ("main" if v == main else "")
        rows.append((f"models.{v}", v, status))
    for b in baselines:
        rows.append(
            (
                f"baselines.{b}",
                RISK_BASELINE_LABELS.get(b, b),
                "GT disparity" if b in GT_INPUT else "",
            )
        )
    return rows


def _with_ci_columns(first: list[str], metrics: list[tuple[str, str, str]], last: str) -> list[str]:
    """``first``, then each metric's name (``(key, name, format)``) and its "95 % CI", then ``last``."""
    return [*first, *(c for _, name, _ in metrics for c in (name, "95 % CI")), last]


def risk_ci_table(src: page.Sources) -> Table | None:
    """Every predictor on the same test frames: MSE, balanced accuracy, recall, F1, ROC-AUC at the
    primary threshold, each with its 95 % sequence-bootstrap interval, the prediction spread and
    whether it beats the speed-only baseline (paired ROC-AUC interval)."""
    if not has_intervals(src):
        return None
    at = risk_threshold_key(src)
    metrics = [
        ("test/mse", "MSE", "g4"),
        (f"{at}.balanced_accuracy", "balanced accuracy", "pct"),
        (f"{at}.recall", "recall (critical)", "pct"),
        (f"{at}.f1", "F1", "g4"),
        (f"{at}.roc_auc", "ROC-AUC", "g4"),
    ]
    cols = _with_ci_columns(
        ["predictor", "label", "status", "prediction std"], metrics, "vs speed-only (ROC-AUC)"
    )
    n_boot = src.get(RISK_FILE, "bootstrap.n_boot")
    t = Table(
        "Risk: every predictor on the same test frames, with 95 % sequence-bootstrap intervals "
        f"(critical ⇔ THW < {at[3:-1]} s)",
        cols,
        anchor="risk-ci",
        headline=True,
        note=(
            f"Intervals: {n_boot} resamples of the test sequences (cluster = driving sequence). "
            "Seed mean: the metric averaged over the variant's seeds inside each resample. "
            "Baselines are scored on the headline's label; the GT-disparity rule sees perfect stereo (a "
            "reference, not an oracle: its straight band is not the label's curved corridor). Decision "
            "thresholds and corridors were chosen on the validation split (reports/metrics/risk_selection.json). A "
            "collapsed model gives one output for every frame and is a failed run. Last column: "
            "the paired ROC-AUC difference to the speed-only baseline of the row's own label "
            "('beats' / 'worse' only when its interval excludes 0)."
        ),
    )
    for pre, name, status in _ci_rows(src):
        key_name = pre.split(".", 1)[1]
        if pre.startswith("groups."):
            key_name += SEED_MEAN
        row = [
            Cell(name),
            Cell(str(src.get(RISK_FILE, f"{pre}.label") or NA)),
            Cell(status),
            value_cell(src, f"{pre}.pred_std"),
        ]
        for k, _, fmt in metrics:
            row += [value_cell(src, f"{pre}.{k}", fmt), ci_cell(src, f"{pre}.{k}", fmt)]
        d = src.get(RISK_FILE, f"differences.{key_name}|speed_only")
        if status.startswith("collapsed"):
            row.append(Cell("failed run"))
        elif isinstance(d, dict):
            v = beats(d, f"{at}.roc_auc")
            row.append(Cell({True: "beats", False: "worse"}.get(v, "no significant difference")))
        else:
            row.append(Cell(""))
        t.rows.append(row)
    return t


def risk_difference_table(src: page.Sources) -> Table | None:
    """Paired differences a − b (MSE, balanced accuracy, ROC-AUC at the primary threshold) with
    their intervals and the ROC-AUC verdict."""
    diffs = src.get(RISK_FILE, "differences")
    if not isinstance(diffs, dict) or not diffs:
        return None
    at = risk_threshold_key(src)
    metrics = [
        ("test/mse", "Δ MSE", "g4"),
        (f"{at}.balanced_accuracy", "Δ balanced accuracy", "g4"),
        (f"{at}.roc_auc", "Δ ROC-AUC", "g4"),
    ]
    cols = _with_ci_columns(["a", "b", "label", "comparison"], metrics, "verdict (ROC-AUC)")
    t = Table(
        "Risk: paired differences a − b on the same test frames (95 % sequence-bootstrap intervals)",
        cols,
        anchor="risk-diff",
        note=(
            "A difference is a finding only when its interval excludes 0; lower MSE and higher "
            "balanced accuracy / ROC-AUC are better. Both predictors are recomputed on every "
            "resample of the test sequences."
        ),
    )
    for key, d in diffs.items():
        if not isinstance(d, dict):
            continue
        pre = f"differences.{key}"
        b = str(d.get("b"))
        row = [
            Cell(str(d.get("a"))),
            Cell(b + (" (GT disparity)" if b in GT_INPUT else "")),
            Cell(str(d.get("label"))),
            Cell(str(d.get("kind", ""))),
        ]
        for k, _, fmt in metrics:
            row += [value_cell(src, f"{pre}.{k}.estimate", fmt), ci_cell(src, f"{pre}.{k}")]
        v = beats(d, f"{at}.roc_auc")
        row.append(
            Cell(
                {True: "a better", False: "b better"}.get(v, "no significant difference"),
                title="claimed only when the paired 95 % interval excludes 0",
            )
        )
        t.rows.append(row)
    return t


def risk_selection_table(src: page.Sources) -> Table | None:
    """Every choice made on the validation split (select_risk): each candidate's validation
    ROC-AUC and decision cut, the corridor rules' half-widths, the shipped predictor."""
    preds = src.get(SELECTION_FILE, "predictors")
    if not isinstance(preds, dict) or not preds:
        return None
    shipped = src.get(SELECTION_FILE, "shipped.predictor")
    fallback = src.get(SELECTION_FILE, "shipped.note")  # nothing chosen on validation: why
    ts = src.get(SELECTION_FILE, "thresholds_s") or []
    cols = ["predictor", "kind", "group", "validation ROC-AUC"]
    for t in ts:
        cols += [f"cut at THW {t:g} s (risk)", f"validation bal. acc. at {t:g} s"]
    cols.append("role")
    tab = Table(
        "Risk: choices made on the validation split (the test split is read once, afterwards)",
        cols,
        anchor="risk-selection",
        headline=True,
        note=(
            f"{src.get(SELECTION_FILE, 'n_frames')} validation frames in "
            f"{src.get(SELECTION_FILE, 'n_sequences')} sequences. Corridor half-width of the rule "
            f"on SGM disparity: {src.get(SELECTION_FILE, 'rules.geometric_sgm.half_width')} m, on GT "
            f"disparity: {src.get(SELECTION_FILE, 'rules.geometric_gt.half_width')} m (the highest "
            "validation ROC-AUC among evaluation.risk.geometric.half_widths). Each predictor's "
            "decision cut maximises its validation balanced accuracy. Shipped: the highest "
            "validation ROC-AUC among the network runs, the hybrid runs and the SGM rule (ties: the simpler)."
            + (f" Not so here: {fallback}." if fallback else "")
        ),
    )
    for name in sorted(preds, key=lambda n: (n != shipped, n)):
        pre = f"predictors.{name}"
        row = [
            Cell(name),
            Cell(str(src.get(SELECTION_FILE, f"{pre}.kind") or "")),
            Cell(str(src.get(SELECTION_FILE, f"{pre}.group") or "")),
            value_cell(src, f"{pre}.roc_auc", "g4", SELECTION_FILE),
        ]
        for t in ts:
            d = f"{pre}.decision.{t:g}"
            row += [
                value_cell(src, f"{d}.cut", "g4", SELECTION_FILE),
                value_cell(src, f"{d}.balanced_accuracy", "pct", SELECTION_FILE),
            ]
        row.append(Cell("shipped" if name == shipped else ""))
        tab.rows.append(row)
    return tab


def risk_critical_share_table(src: page.Sources) -> Table | None:
    """Critical share of every region's label per split (frames.csv, all frames)."""
    splits = src.get(RISK_FILE, "critical_share.splits")
    if not isinstance(splits, dict) or not splits:
        return None
    labels = [
        lab
        for lab in ("risk_thw_corridor", "risk_thw_paper", "risk_thw_fov", "risk")
        if any(isinstance(e, dict) and lab in e for e in splits.values())
    ]
    thr = src.get(RISK_FILE, "critical_share.threshold_s")
    t = Table(
        f"Risk: critical share (THW < {fmt_value(thr, 'g4')} s) of every region's label per split",
        ["split", "frames", "sequences", *labels],
        anchor="risk-critical-share",
        note=(
            "All frames of frames.csv (before the ORB check). risk_thw_corridor: objects in the "
            "subject's driving corridor (the headline label); risk_thw_paper: anything ahead under "
            "the pessimistic-turn assumption; risk_thw_fov: the part the camera sees."
        ),
    )
    for split in splits:
        pre = f"critical_share.splits.{split}"
        t.rows.append(
            [
                Cell(split),
                value_cell(src, f"{pre}.n_frames", "int"),
                value_cell(src, f"{pre}.n_sequences", "int"),
                *[value_cell(src, f"{pre}.{lab}", "pct") for lab in labels],
            ]
        )
    return t


def risk_situation_table(src: page.Sources) -> Table | None:
    """The headline's recall / specificity / balanced accuracy per situation type, with the
    speed-only baseline's balanced accuracy beside it."""
    sit = src.get(RISK_FILE, "situations")
    main = (
        src.get(RISK_FILE, "shipped")
        or src.get(RISK_FILE, "main_predictor")
        or src.get(RISK_FILE, "main_variant")
    )
    if not isinstance(sit, dict) or not sit or not isinstance(main, str):
        return None
    cols = ["situation", "sequences", "frames", "critical share"]
    keys = [
        ("recall", "recall"),
        ("specificity", "specificity"),
        ("balanced_accuracy", "bal. acc."),
    ]
    for _, name in keys:
        cols += [f"{main} {name}", "95 % CI"]
    cols += ["speed-only bal. acc.", "95 % CI"]
    t = Table(
        f"Risk: {main} by situation type (primary threshold; intervals over that situation's sequences)",
        cols,
        anchor="risk-situations",
        note="n/a: the situation has no critical (recall) or no uncritical (specificity) test frame.",
    )
    for s in sorted(sit):
        pre = f"situations.{s}"
        row = [
            Cell(s),
            value_cell(src, f"{pre}.n_sequences", "int"),
            value_cell(src, f"{pre}.n_frames", "int"),
            value_cell(src, f"{pre}.critical_share", "pct"),
        ]
        for k, _ in keys:
            p = f"{pre}.predictors.{main}.{k}"
            row += [value_cell(src, p, "pct"), ci_cell(src, p, "pct")]
        p = f"{pre}.predictors.speed_only.balanced_accuracy"
        row += [value_cell(src, p, "pct"), ci_cell(src, p, "pct")]
        t.rows.append(row)
    return t
