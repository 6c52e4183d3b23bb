"""The risk part of the report (Feth et al.): what the results section says, which metrics and
figures it shows, and the paper's numbers beside ours.

Reads ``risk.json`` (stage evaluate_risk): ``models[variant]`` and ``baselines[name]`` each with
``test/mse``, ``test/mae``, ``test/thw_mae_s``, ... and ``at_<t>s`` {accuracy, precision, recall,
f1, roc_auc, confusion{tp,fp,fn,tn}, confusion_pct, critical_fraction_true}; ``main_variant``;
``thresholds_s``; ``n_frames``{total, orb_outliers_dropped, train, val, test};
``region``{labels, agreement, predictors[name][label]}; plus ``orb.json`` (stage orb_filter),
``disparity.json`` (stage disparity) and ``risk_data.json`` (stage generate_risk) in the data
section. When the evaluation has intervals (``bootstrap`` in risk.json), every metric is shown with
its 95 % sequence-bootstrap interval (``<metric>_ci``), plus the paired differences
(``differences``), the targets, the critical share of every region per split and the situation
breakdown. Entry point: :func:`provider`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from traffictwin.report import model as page
from traffictwin.report import paper_numbers as P
from traffictwin.report.model import NA, Cell, Table, fmt_value, lookup, paper_cell
from traffictwin.report.summary import Headline, headline
from traffictwin.report.tables import findings_group
from traffictwin.risk.evaluation import GT_INPUT, SEED_MEAN
from traffictwin.risk.findings import findings
from traffictwin.risk.findings_values import beats

RISK_FILE = "risk.json"
ORB_FILE = "orb.json"
TITLE = "Paper 2 — dynamic risk assessment from a stereo camera"

# The figures the risk stages write: file stem -> caption, in the order the section shows them.
FIGURES: dict[str, str] = {
    "stereo_example": "Left image, SGM disparity and exact disparity (mirrors the risk paper's Fig. 2)",
    "risk_metric_example": "Grid-map risk metric: scene and worst-time-headway region (cf. Figs. 3 and 4)",
    "orb_outlier_example": "A stereo pair the ORB check flags (Sec. 3.3)",
    "risk_training_curves": "Training and validation loss per variant, one panel per training objective, and every variant's validation MSE of the normalised risk (mirrors Figs. 5 and 6)",
    "risk_confusion": "Confusion matrix of the main variant at THW 1.5 s (mirrors Table 1)",
    "risk_scatter": "Predicted vs true risk on the test split, with the critical threshold",
    "risk_examples": "Test scenes with true and predicted risk (mirrors Fig. 7)",
    "risk_roc": "ROC of the headline network (each seed) vs the speed-only baseline and the "
    "corridor rule on SGM and on GT disparity (dashed), corridors chosen on validation, at THW 1.5 s",
}
FIGURE_PATTERN = r"risk|stereo|disparity|orb|camera|thw"
DATA_FILES = (
    page.DataFile(
        "risk_data.json",
        "Risk data: stereo frames and risk labels (reports/metrics/risk_data.json)",
    ),
    page.DataFile(
        "disparity.json",
        "SGM disparity vs exact disparity (reports/metrics/disparity.json)",
        required=True,
    ),
    page.DataFile(
        ORB_FILE,
        "ORB stereo-pair check vs injected faults (reports/metrics/orb.json)",
        required=True,
    ),
)
RISK_BASELINE_LABELS = {
    "train_mean": "baseline: train mean",
    "train_median": "baseline: train median",
    "speed_only": "baseline: speed only (isotonic fit on train)",
    "geometric": "baseline: corridor rule (SGM distance / speed)",
    "geometric_sgm": "baseline: corridor rule (SGM distance / speed, corridor chosen on validation)",
    "geometric_gt": "reference: corridor rule on GT disparity (corridor chosen on validation)",
}
PAPER_DASH = "—"


def derived_paper_cell(key: str, fmt: str = "pct_raw") -> Cell:
    """Cell with a number derived from the paper's Table 1 (:func:`paper_numbers.risk_confusion_derived`)."""
    v = P.risk_confusion_derived()[key]
    return Cell(
        fmt_value(v, fmt),
        src=f"paper:derived.{key}",
        value=v,
        fmt=fmt,
        title="derived from Table 1 counts",
    )


def _risk_threshold_key(src: page.Sources) -> str:
    ts = src.get(RISK_FILE, "thresholds_s")
    t = ts[0] if isinstance(ts, list) and ts else P.RISK["thw_threshold_s"].value
    return f"at_{float(t):g}s"


def risk_predictors(src: page.Sources) -> list[tuple[str, str, str]]:
    """``(key prefix in risk.json, column label, name)``: main variant first, other variants, then baselines."""
    models = src.get(RISK_FILE, "models")
    baselines = src.get(RISK_FILE, "baselines")
    main = src.get(RISK_FILE, "main_variant")
    out = []
    if isinstance(models, dict):
        names = sorted(models, key=lambda v: (v != main, v))
        out += [(f"models.{v}", f"ours: {v}" + (" (main)" if v == main else ""), v) for v in names]
    if isinstance(baselines, dict):
        out += [
            (f"baselines.{b}", RISK_BASELINE_LABELS.get(b, f"baseline: {b}"), b) for b in baselines
        ]
    return out


def risk_tables(src: page.Sources) -> list[Table]:
    """Paper vs our variants vs baselines (MSE, accuracy, …), the confusion matrix, the risk-region check."""
    at = _risk_threshold_key(src)
    preds = risk_predictors(src)
    t = Table(
        "Risk: test results, paper vs this run (critical ⇔ THW < 1.5 s ⇔ risk > 1/30)",
        ["metric", "paper (Feth et al.)", *[label for _, label, _ in preds], "paper source"],
        note=(
            "The paper's accuracy and confusion matrix are over its whole effective data set "
            f"({fmt_value(P.RISK['n_effective'].value, 'int')} frames), "
            "ours over the test split; '—': the paper reports no such number. Wang & Kato (ref. [20] of the "
            "paper) solve a different, 3-class task with subjective labels; the paper quotes their accuracy "
            "as the related work's best."
        ),
        anchor="risk-results",
        headline=True,
    )
    rows = [
        ("MSE (normalised risk)", paper_cell("RISK", "test_mse", "g4"), "test/mse", "g4", "Sec. 4"),
        ("MAE (normalised risk)", None, "test/mae", "g4", ""),
        ("THW abs. error [s] (capped)", None, "test/thw_mae_s", "g4", ""),
        (
            "accuracy",
            paper_cell("RISK", "accuracy", "pct_raw"),
            f"{at}.accuracy",
            "pct",
            "Sec. 4, Table 1",
        ),
        ("balanced accuracy", None, f"{at}.balanced_accuracy", "pct", ""),
        (
            "precision (critical)",
            derived_paper_cell("precision_critical_pct"),
            f"{at}.precision",
            "pct",
            "Table 1 (derived)",
        ),
        (
            "recall (critical)",
            derived_paper_cell("recall_critical_pct"),
            f"{at}.recall",
            "pct",
            "Table 1 (derived)",
        ),
        ("F1 (critical)", None, f"{at}.f1", "g4", ""),
        ("ROC-AUC (risk as score for critical)", None, f"{at}.roc_auc", "g4", ""),
        (
            "critical share (actual)",
            derived_paper_cell("critical_share_pct"),
            f"{at}.critical_fraction_true",
            "pct",
            "Sec. 4 (derived)",
        ),
    ]
    for label, pc, key, fmt, ref in rows:
        t.rows.append(
            [Cell(label), pc or Cell(PAPER_DASH)]
            + [src.cell(RISK_FILE, f"{pre}.{key}", fmt) for pre, _, _ in preds]
            + [Cell(ref)]
        )
    t.rows.append(
        [Cell("accuracy, Wang & Kato [20]"), paper_cell("RISK", "wang_kato_accuracy", "pct_raw")]
        + [Cell(PAPER_DASH) for _ in preds]
        + [Cell("Sec. 4")]
    )
    tables = [t]

    main = src.get(RISK_FILE, "main_variant")
    if isinstance(main, str):
        pre = f"models.{main}.{at}"
        cm = Table(
            f"Risk: confusion matrix, paper Table 1 (whole effective data set) vs this run's test split ({main})",
            [
                "",
                "paper: actual critical",
                "paper: share",
                "paper: actual uncritical",
                "paper: share",
                "ours: actual critical",
                "ours: share",
                "ours: actual uncritical",
                "ours: share",
            ],
            anchor="risk-confusion",
            headline=True,
            note="Rows: predicted class, columns: actual class, as in the paper's Table 1; shares of all frames.",
        )
        for label, (a, b) in (
            ("predicted critical", ("tp", "fp")),
            ("predicted uncritical", ("fn", "tn")),
        ):
            cm.rows.append(
                [
                    Cell(label),
                    paper_cell("RISK_CONFUSION", a, "int"),
                    derived_paper_cell(f"share_{a}_pct"),
                    paper_cell("RISK_CONFUSION", b, "int"),
                    derived_paper_cell(f"share_{b}_pct"),
                    src.cell(RISK_FILE, f"{pre}.confusion.{a}", "int"),
                    src.cell(RISK_FILE, f"{pre}.confusion_pct.{a}", "pct_raw"),
                    src.cell(RISK_FILE, f"{pre}.confusion.{b}", "int"),
                    src.cell(RISK_FILE, f"{pre}.confusion_pct.{b}", "pct_raw"),
                ]
            )
        tables.append(cm)

    region = src.get(RISK_FILE, "region.predictors")
    if isinstance(region, dict) and region:
        primary = src.get(RISK_FILE, "primary_label")
        labels = sorted(
            {lab for d in region.values() if isinstance(d, dict) for lab in d},
            key=lambda x: (x != primary, x),
        )
        rt = Table(
            "Risk: does the label's region explain the errors? Each predictor scored against the paper-style "
            "region label and against a label restricted to the camera's field of view",
            ["predictor", *[f"{m} vs {lab}" for lab in labels for m in ("MSE", "accuracy")]],
            anchor="risk-region",
            note=(
                "The paper blames its errors on the metric's region not matching the camera view (Sec. 4); "
                "risk_thw_paper = the paper's region, risk_thw_fov = only what the camera sees."
            ),
        )
        for name in region:
            rt.rows.append(
                [Cell(name)]
                + [
                    src.cell(RISK_FILE, f"region.predictors.{name}.{lab}.{k}", f)
                    for lab in labels
                    for k, f in (("test/mse", "g4"), ("accuracy", "pct"))
                ]
            )
        tables.append(rt)
    return tables


def _num(v: Any) -> float | None:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else None


def _ci_cell(src: page.Sources, key: str, fmt: str = "g4") -> Cell:
    """``[lo, hi]`` of ``<key>_ci`` (or of ``key`` itself when it holds ``lo``/``hi``) in format
    ``fmt``, a derived cell; ``n/a`` when there is no interval."""
    base = key if isinstance(src.get(RISK_FILE, f"{key}.lo"), (int, float)) else f"{key}_ci"
    lo, hi = _num(src.get(RISK_FILE, f"{base}.lo")), _num(src.get(RISK_FILE, f"{base}.hi"))
    if lo is None or hi is None or math.isnan(lo) or math.isnan(hi):
        return Cell(NA, title=f"no interval in reports/metrics/{RISK_FILE}: {base}")
    return Cell(
        f"[{fmt_value(lo, fmt)}, {fmt_value(hi, fmt)}]",
        value=[lo, hi],
        derived=f"95 % sequence-bootstrap interval, metrics/{RISK_FILE}#{base}",
    )


def _value_cell(src: page.Sources, key: str, fmt: str = "g4") -> Cell:
    """``key`` when present (a JSON null → n/a with its source), else n/a without recording it
    as missing (a metric that does not apply to this row)."""
    if src.get(RISK_FILE, key, page.ABSENT) is page.ABSENT:
        return Cell(NA, title=f"not applicable: {key}")
    return src.cell(RISK_FILE, key, fmt)


def _has_intervals(src: page.Sources) -> bool:
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


def risk_ci_table(src: page.Sources) -> Table | None:
    """Every predictor on the same test frames: MSE, balanced accuracy, recall, F1, ROC-AUC at the
    primary threshold, each with its 95 % sequence-bootstrap interval, the prediction spread and
    whether it beats the speed-only baseline (paired ROC-AUC interval)."""
    if not _has_intervals(src):
        return None
    at = _risk_threshold_key(src)
    metrics = [
        ("test/mse", "MSE", "g4"),
        (f"{at}.balanced_accuracy", "balanced accuracy", "pct"),
        (f"{at}.recall", "recall (critical)", "pct"),
        (f"{at}.f1", "F1", "g4"),
        (f"{at}.roc_auc", "ROC-AUC", "g4"),
    ]
    cols = ["predictor", "label", "status", "prediction std"]
    for _, name, _ in metrics:
        cols += [name, "95 % CI"]
    cols.append("vs speed-only (ROC-AUC)")
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
            _value_cell(src, f"{pre}.pred_std"),
        ]
        for k, _, fmt in metrics:
            row += [_value_cell(src, f"{pre}.{k}", fmt), _ci_cell(src, f"{pre}.{k}", fmt)]
        d = src.get(RISK_FILE, f"differences.{key_name}|speed_only")
        if status.startswith("collapsed"):
            row.append(Cell("failed run"))
        elif isinstance(d, dict):
            v = beats(d, f"{at}|roc_auc")
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
    at = _risk_threshold_key(src)
    metrics = [
        ("test/mse", "Δ MSE", "g4"),
        (f"{at}.balanced_accuracy", "Δ balanced accuracy", "g4"),
        (f"{at}.roc_auc", "Δ ROC-AUC", "g4"),
    ]
    cols = ["a", "b", "label", "comparison"]
    for _, name, _ in metrics:
        cols += [name, "95 % CI"]
    cols.append("verdict (ROC-AUC)")
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
            row += [_value_cell(src, f"{pre}.{k}.estimate", fmt), _ci_cell(src, f"{pre}.{k}")]
        v = beats(d, f"{at}|roc_auc")
        row.append(
            Cell(
                {True: "a better", False: "b better"}.get(v, "no significant difference"),
                title="claimed only when the paired 95 % interval excludes 0",
            )
        )
        t.rows.append(row)
    return t


def risk_targets_table(src: page.Sources) -> Table | None:
    """The issue-31 targets: value, interval, threshold, met."""
    targets = src.get(RISK_FILE, "targets")
    if not isinstance(targets, dict) or not targets:
        return None
    t = Table(
        "Risk: targets (default profile, test split: the shipped predictor, and the learned model vs the corridor rule)",
        ["target", "predictor", "value", "95 % CI", "op", "threshold", "met", "description"],
        anchor="risk-targets",
        headline=True,
    )
    for name, e in targets.items():
        if not isinstance(e, dict):
            continue
        pre = f"targets.{name}"
        t.rows.append(
            [
                Cell(name),
                Cell(str(e.get("predictor", ""))),
                _value_cell(src, f"{pre}.value"),
                _ci_cell(src, pre),
                Cell(str(e.get("op", ""))),
                _value_cell(src, f"{pre}.threshold", "g4"),
                Cell("yes" if e.get("met") else "no", title=str(e.get("why", ""))),
                Cell(str(e.get("description", ""))),
            ]
        )
    return t


SELECTION_FILE = "risk_selection.json"


def _sel_cell(src: page.Sources, key: str, fmt: str) -> Cell:
    """``key`` of the selection file with its source; n/a (not recorded as missing) when absent."""
    if src.get(SELECTION_FILE, key, page.ABSENT) is page.ABSENT:
        return Cell(NA, title=f"not applicable: {key}")
    return src.cell(SELECTION_FILE, key, fmt)


def risk_selection_table(src: page.Sources) -> Table | None:
    """Every choice made on the validation split (select_risk): each candidate's validation
    ROC-AUC and decision cut, the corridor rules' half-widths, the shipped predictor."""
    preds = src.get(SELECTION_FILE, "predictors")
    if not isinstance(preds, dict) or not preds:
        return None
    shipped = src.get(SELECTION_FILE, "shipped.predictor")
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
        ),
    )
    for name in sorted(preds, key=lambda n: (n != shipped, n)):
        pre = f"predictors.{name}"
        row = [
            Cell(name),
            Cell(str(src.get(SELECTION_FILE, f"{pre}.kind") or "")),
            Cell(str(src.get(SELECTION_FILE, f"{pre}.group") or "")),
            _sel_cell(src, f"{pre}.roc_auc", "g4"),
        ]
        for t in ts:
            d = f"{pre}.decision.{t:g}"
            row += [
                _sel_cell(src, f"{d}.cut", "g4"),
                _sel_cell(src, f"{d}.balanced_accuracy", "pct"),
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
                _value_cell(src, f"{pre}.n_frames", "int"),
                _value_cell(src, f"{pre}.n_sequences", "int"),
                *[_value_cell(src, f"{pre}.{lab}", "pct") for lab in labels],
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
            _value_cell(src, f"{pre}.n_sequences", "int"),
            _value_cell(src, f"{pre}.n_frames", "int"),
            _value_cell(src, f"{pre}.critical_share", "pct"),
        ]
        for k, _ in keys:
            p = f"{pre}.predictors.{main}.{k}"
            row += [_value_cell(src, p, "pct"), _ci_cell(src, p, "pct")]
        p = f"{pre}.predictors.speed_only.balanced_accuracy"
        row += [_value_cell(src, p, "pct"), _ci_cell(src, p, "pct")]
        t.rows.append(row)
    return t


def risk_training_table(src: page.Sources) -> Table | None:
    """Per variant: inputs, label, parameters, steps and best validation MSE (risk.json models;
    training times are in the run records, reports/timings)."""
    models = src.get(RISK_FILE, "models")
    if not isinstance(models, dict) or not models:
        return None
    cols = [
        ("n_parameters", "parameters", "int"),
        ("n_train", "train frames", "int"),
        ("steps", "steps", "int"),
        ("best_step", "best step", "int"),
        ("best_val_mse", "best val MSE", "g4"),
    ]
    t = Table(
        "Risk: training of each variant (DAVE-2-like net; paper: "
        f"{P.RISK['epochs'].value} epochs, batch {P.RISK['batch_size'].value}, Adam)",
        ["variant", "inputs", "label", *[c[1] for c in cols]],
        anchor="risk-training",
    )
    main = src.get(RISK_FILE, "main_variant")
    for v in sorted(models, key=lambda v: (v != main, v)):
        m = models[v] if isinstance(models[v], dict) else {}
        inputs = "+".join(m.get("inputs", [])) + (" + speed" if m.get("speed") else "")
        t.rows.append(
            [Cell(v), Cell(inputs or NA), Cell(str(m.get("label", NA)))]
            + [_value_cell(src, f"models.{v}.{k}", f) for k, _, f in cols]
        )
    return t


def risk_data_table(src: page.Sources) -> Table | None:
    """Frames recorded / dropped by ORB / per split, paper vs this run."""
    if src.get(RISK_FILE, "n_frames") is None:
        return None
    t = Table(
        "Risk: data, paper vs this run",
        ["quantity", "paper", "this run", "paper source"],
        anchor="risk-data",
        note=f"Paper split {P.RISK['split'].value} (random frames); ours by scenario (neighbouring frames are near-duplicates).",
    )
    t.rows.append(
        [
            Cell("stereo frames"),
            paper_cell("RISK", "n_frames", "int"),
            src.cell(RISK_FILE, "n_frames.total", "int"),
            Cell("Sec. 3.3"),
        ]
    )
    t.rows.append(
        [
            Cell("dropped by the stereo-pair check"),
            derived_paper_cell("n_dropped", "int"),
            src.cell(RISK_FILE, "n_frames.orb_outliers_dropped", "int"),
            Cell("Sec. 3.3, 3.5 (derived)"),
        ]
    )
    for split in ("train", "val", "test"):
        t.rows.append(
            [
                Cell(f"{split} frames"),
                Cell(PAPER_DASH),
                src.cell(RISK_FILE, f"n_frames.{split}", "int"),
                Cell(""),
            ]
        )
    if src.has(ORB_FILE):
        t.rows.append(
            [
                Cell("share of pairs dropped by ORB"),
                paper_cell("RISK", "orb_outlier_pct", "pct_raw"),
                src.cell(ORB_FILE, "all/dropped_share", "pct"),
                Cell("Sec. 3.3 ('around 3.5 %')"),
            ]
        )
    return t


def section(src: page.Sources, figures: list[page.Figure]) -> page.Section:
    """The risk results section: paper vs variants vs baselines, confusion matrix, region check,
    training and data tables, this run's findings and ``figures``."""
    sec = page.Section(TITLE)
    sec.paragraphs.append(f"Reference: {P.RISK_CITATION}.")
    if src.has(RISK_FILE):
        sec.tables.extend(risk_tables(src))
        for extra in (
            risk_selection_table(src),
            risk_ci_table(src),
            risk_difference_table(src),
            risk_targets_table(src),
            risk_critical_share_table(src),
            risk_situation_table(src),
        ):
            if extra is not None:
                sec.tables.append(extra)
        training = risk_training_table(src)
        if training:
            sec.tables.append(training)
    else:
        sec.paragraphs.append(
            f"`reports/metrics/{RISK_FILE}` is missing: the risk evaluation has not run."
        )
    data = risk_data_table(src)
    if data:
        sec.tables.append(data)
    sec.bullet_groups.append(findings_group(src, RISK_FILE, findings))
    sec.figures = figures
    return sec


def headlines(metrics: Mapping[str, Any]) -> list[Headline]:
    """The shipped predictor (``shipped``: what users get, chosen on validation; else the main
    variant, its seed mean when replicates ran) on the ORB-passed test frames: ROC-AUC of critical
    frames at the first THW threshold (``auc``) and the balanced accuracy there
    (``balanced_accuracy``, at its validation-chosen decision cut) and the accuracy (``accuracy``),
    with their sequence-bootstrap intervals. (The MSE is no headline: a constant meets it, issue 31.)"""
    risk = metrics.get(RISK_FILE)
    main = lookup(risk, "main_variant")
    ts = lookup(risk, "thresholds_s")
    if not isinstance(main, str) or not isinstance(ts, list) or not ts:
        return []
    shipped = lookup(risk, "shipped")
    row = lookup(risk, f"models.{shipped}") if isinstance(shipped, str) else None
    who = f"shipped predictor ({lookup(risk, 'selection.shipped_from') or shipped})"
    if not isinstance(row, Mapping):
        row = lookup(risk, f"groups.{main}")
        who = f"main predictor {main}"
    if not isinstance(row, Mapping):
        row = lookup(risk, f"models.{main}")
    if not isinstance(row, Mapping):
        return []
    t = float(ts[0])
    cls = row.get(f"at_{t:g}s")
    cls = cls if isinstance(cls, Mapping) else {}
    where = f"{who}, test frames"
    return (
        headline(
            "auc",
            f"ROC-AUC of critical frames (THW < {t:g} s)",
            where,
            cls.get("roc_auc"),
            cls.get("roc_auc_ci"),
            "f3",
        )
        + headline(
            "balanced_accuracy",
            f"balanced accuracy of critical frames (THW < {t:g} s)",
            where,
            cls.get("balanced_accuracy"),
            cls.get("balanced_accuracy_ci"),
            "f3",
        )
        + headline(  # defined even when the test frames hold one class only (the paper's metric)
            "accuracy",
            f"accuracy, critical vs uncritical (THW < {t:g} s)",
            where,
            cls.get("accuracy"),
            cls.get("accuracy_ci"),
            "f3",
        )
    )


def provider() -> page.SectionProvider:
    """The risk section's provider for the report."""
    return page.SectionProvider(
        name="risk",
        headlines=headlines,
        section=section,
        figures=FIGURES,
        figure_pattern=FIGURE_PATTERN,
        data_files=DATA_FILES,
    )
