"""The risk section's tables against the paper (results, confusion matrix, region check, training,
data) and the cells every risk table uses (values and 95 % intervals of ``risk.json``).

Reads ``risk.json`` (stage evaluate_risk): ``models[variant]`` and ``baselines[name]`` each with
``test/mse``, ``test/mae``, ``test/thw_mae_s``, ... and ``at_<t>s`` {accuracy, precision, recall,
f1, roc_auc, confusion{tp,fp,fn,tn}, confusion_pct, critical_fraction_true}; ``main_variant``;
``thresholds_s``; ``n_frames``{total, orb_outliers_dropped, train, val, test};
``region``{labels, agreement, predictors[name][label]}; and ``orb.json`` (stage orb_filter).
The interval tables are in :mod:`traffictwin.risk.report_intervals`.
"""

from __future__ import annotations

from typing import Any

from traffictwin import paper_numbers as P
from traffictwin.report import model as page
from traffictwin.report.model import NA, Cell, Table, fmt_value, interval_cell, paper_cell
from traffictwin.risk.metric import CLIP

RISK_FILE = "risk.json"
ORB_FILE = "orb.json"
SELECTION_FILE = "risk_selection.json"
RISK_BASELINE_LABELS = {
    "train_mean": "baseline: train mean",
    "train_median": "baseline: train median",
    "speed_only": "baseline: speed only (isotonic fit on train)",
    "geometric": "baseline: corridor rule (SGM distance / speed)",
    "geometric_sgm": "baseline: corridor rule (SGM distance / speed, corridor chosen on validation)",
    "geometric_learned": "corridor rule on the learned stereo network's disparity (corridor chosen on validation)",
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


def risk_threshold_key(src: page.Sources) -> str:
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


def _result_rows(at: str) -> list[tuple[str, Cell | None, str, str, str]]:
    """The results table's rows: (name, the paper's cell or None, key under each predictor,
    format, paper source); ``at`` is the primary threshold's key (``at_<t>s``)."""
    derived = "Table 1 (derived)"
    return [
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
            derived,
        ),
        (
            "recall (critical)",
            derived_paper_cell("recall_critical_pct"),
            f"{at}.recall",
            "pct",
            derived,
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


def _results_table(src: page.Sources, at: str) -> Table:
    """Paper vs our variants vs baselines: MSE, accuracy, … at the primary threshold ``at``."""
    preds = risk_predictors(src)
    thw = float(at.removeprefix("at_").removesuffix("s"))
    t = Table(
        f"Risk: test results, paper vs this run (critical ⇔ THW < {thw:g} s ⇔ risk > "
        f"1/{CLIP * thw:g})",
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
    for label, pc, key, fmt, ref in _result_rows(at):
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
    return t


def _confusion_table(src: page.Sources, main: str, at: str) -> Table:
    """The main variant's confusion matrix beside the paper's Table 1 (rows: predicted class)."""
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
    return cm


def _region_table(src: page.Sources, region: dict[str, Any]) -> Table:
    """Each predictor's MSE and accuracy against every region's label (``region.predictors``)."""
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
    return rt


def risk_tables(src: page.Sources) -> list[Table]:
    """Paper vs our variants vs baselines (MSE, accuracy, …), the confusion matrix, the risk-region check."""
    at = risk_threshold_key(src)
    tables = [_results_table(src, at)]
    main = src.get(RISK_FILE, "main_variant")
    if isinstance(main, str):
        tables.append(_confusion_table(src, main, at))
    region = src.get(RISK_FILE, "region.predictors")
    if isinstance(region, dict) and region:
        tables.append(_region_table(src, region))
    return tables


def ci_cell(src: page.Sources, key: str, fmt: str = "g4") -> Cell:
    """``[lo, hi]`` of ``<key>_ci`` (or of ``key`` itself when it holds ``lo``/``hi``) in risk.json,
    in format ``fmt``: the sequence-bootstrap interval cell
    (:func:`~traffictwin.report.model.interval_cell`)."""
    return interval_cell(src, RISK_FILE, key, "sequence-bootstrap", fmt)


def value_cell(src: page.Sources, key: str, fmt: str = "g4", file: str = RISK_FILE) -> Cell:
    """``key`` of ``file`` when present (a JSON null → n/a with its source), else n/a without
    recording it as missing (a metric that does not apply to this row)."""
    if src.get(file, key, page.ABSENT) is page.ABSENT:
        return Cell(NA, title=f"not applicable: {key}")
    return src.cell(file, key, fmt)


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
            + [value_cell(src, f"models.{v}.{k}", f) for k, _, f in cols]
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
