"""The risk section's tables: every predictor on the same test frames beside the paper, the
confusion matrix beside the paper's Table 1, the choices made on validation and the paired
differences. The rest of risk.json (each predictor by region label and situation type, the
training of each variant, the data per split) is in the report's appendix.

Reads ``risk.json`` (stage evaluate_risk; layout: :mod:`traffictwin.risk.evaluation`) and
``risk_selection.json`` (stage select_risk). Notes: the macros of ``templates/report.md.j2``.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from pathlib import Path

from traffictwin import paper_numbers as P
from traffictwin.report import model as page
from traffictwin.report.model import NA, Cell, Table, fmt_value, interval_cell, paper_cell
from traffictwin.report.prose import macro_prose
from traffictwin.risk.evaluation import GT_INPUT, SEED_MEAN
from traffictwin.risk.findings import beats
from traffictwin.risk.metric import CLIP

RISK_FILE = "risk.json"
SELECTION_FILE = "risk_selection.json"
DASH = "—"  # the paper reports no such number
CI = "95 % CI"
TEMPLATES = Path(__file__).parent / "templates"


#: one figure of a spec-driven table row: (column header, key under the row's base, format, with
#: its 95 % sequence-bootstrap interval ``<key>_ci`` in a "95 % CI" column beside it)
Column = tuple[str, str, str, bool]


def spec_columns(*specs: Sequence[Column]) -> list[str]:
    """The column headers of ``specs``: each header, and "95 % CI" after those with an interval."""
    return [h for cols in specs for head, _, _, ci in cols for h in ((head, CI) if ci else (head,))]


def spec_cells(
    src: page.Sources, file: str, base: str, specs: Sequence[Column], dash: Collection[str] = ()
) -> list[Cell]:
    """The cells of ``specs`` at ``file``#``<base>.<key>`` (and the interval where a spec has
    one), in the order of :func:`spec_columns`; a key in ``dash`` shows "—" (its interval too)."""
    out: list[Cell] = []
    for _, key, fmt, ci in specs:
        if key in dash:
            out += [Cell(DASH)] * (1 + ci)
            continue
        out.append(src.cell(file, f"{base}.{key}", fmt))
        out += [interval_cell(src, file, f"{base}.{key}", "sequence-bootstrap", fmt)] if ci else []
    return out


#: macro ``name`` of ``templates/report.md.j2`` filled with ``context``, on one line
prose = macro_prose(TEMPLATES, "report.md.j2")


def derived_paper_cell(key: str, fmt: str = "pct_raw") -> Cell:
    """Cell with a number derived from the paper's Table 1 (:func:`paper_numbers.risk_confusion_derived`)."""
    v = P.risk_confusion_derived()[key]
    return Cell(fmt_value(v, fmt), "paper:derived." + key, v, fmt, "derived from Table 1 counts")


def risk_threshold_key(src: page.Sources) -> str:
    """``at_<t>s`` of the primary THW threshold ``t`` (s): risk.json's first, else the paper's."""
    ts = src.get(RISK_FILE, "thresholds_s")
    t = ts[0] if isinstance(ts, list) and ts else P.RISK["thw_threshold_s"].value
    return f"at_{float(t):g}s"


def _first(names: object, first: object) -> list[str]:
    """``names`` sorted, ``first`` first."""
    return sorted(names, key=lambda n: (n != first, n)) if isinstance(names, dict) else []


def _predictors(src: page.Sources) -> list[tuple[str, str, str]]:
    """``(key prefix, row name, status)``: the seed means, every model (main first), every baseline."""
    get = lambda k: src.get(RISK_FILE, k) or {}  # noqa: E731
    main = src.get(RISK_FILE, "main_variant")
    rows = [
        (f"groups.{g}", g + SEED_MEAN, f"seed mean of {get(f'groups.{g}.n_seeds') or NA}")
        for g in _first(get("groups"), main)
        if isinstance(src.get(RISK_FILE, f"groups.{g}.test/mse"), (int, float))
    ]
    for v in _first(get("models"), main):
        failed = get(f"models.{v}.collapsed")
        rows.append(
            (f"models.{v}", v, "collapsed: failed run" if failed else "main" if v == main else "")
        )
    gt = {b: "reference: GT disparity" for b in GT_INPUT}
    return rows + [(f"baselines.{b}", b, gt.get(b, "baseline")) for b in get("baselines")]


def results_table(src: page.Sources, at: str) -> Table:
    """The paper beside every predictor on the same test frames at the primary threshold ``at``
    (``at_<t>s``), with the 95 % sequence-bootstrap intervals where risk.json has them."""
    ci = isinstance(src.get(RISK_FILE, "bootstrap"), dict)
    metrics: list[Column] = [
        ("MSE (normalised risk)", "test/mse", "g4", ci),
        ("MAE (normalised risk)", "test/mae", "g4", False),
        ("THW abs. error [s] (capped)", "test/thw_mae_s", "g4", False),
        ("accuracy", f"{at}.accuracy", "pct", ci),
        ("balanced accuracy", f"{at}.balanced_accuracy", "pct", ci),
        ("precision (critical)", f"{at}.precision", "pct", False),
        ("recall (critical)", f"{at}.recall", "pct", ci),
        ("F1 (critical)", f"{at}.f1", "g4", ci),
        ("ROC-AUC", f"{at}.roc_auc", "g4", ci),
        ("critical share", f"{at}.critical_fraction_true", "pct", False),
    ]
    paper = {  # the paper's cells: printed in Sec. 4 or derived from its Table 1
        "test/mse": paper_cell("RISK", "test_mse", "g4"),
        f"{at}.accuracy": paper_cell("RISK", "accuracy", "pct_raw"),
        f"{at}.precision": derived_paper_cell("precision_critical_pct"),
        f"{at}.recall": derived_paper_cell("recall_critical_pct"),
        f"{at}.critical_fraction_true": derived_paper_cell("critical_share_pct"),
    }
    thw = float(at[3:-1])
    t = Table(
        f"Risk: test results, paper vs every predictor on the same test frames (critical ⇔ THW < "
        f"{thw:g} s ⇔ risk > 1/{CLIP * thw:g})",
        ["predictor", "label", "status", "prediction std", *spec_columns(metrics)],
        anchor="risk-results",
        headline=True,
        note=prose(
            "results",
            n_effective=fmt_value(P.RISK["n_effective"].value, "int"),
            n_boot=src.get(RISK_FILE, "bootstrap.n_boot"),
        ),
    )
    wang_kato = {f"{at}.accuracy": paper_cell("RISK", "wang_kato_accuracy", "pct_raw")}
    for name, cells in (("paper (Feth et al.)", paper), ("Wang & Kato [20]", wang_kato)):
        row = [Cell(name), Cell(DASH), Cell("paper"), Cell(DASH)]
        for _, k, _, has_ci in metrics:
            row += [cells.get(k) or Cell(DASH)] + [Cell(DASH)] * has_ci
        t.rows.append(row)
    for pre, name, status in _predictors(src):
        label = Cell(str(src.get(RISK_FILE, f"{pre}.label") or NA))
        std = src.cell(RISK_FILE, f"{pre}.pred_std", record=False)
        row = [Cell(name), label, Cell(status), std]
        t.rows.append(row + spec_cells(src, RISK_FILE, pre, metrics))
    return t


def confusion_table(src: page.Sources, main: str, at: str) -> Table:
    """The main variant's confusion matrix beside the paper's Table 1 (rows: predicted class)."""
    pre = f"models.{main}.{at}"
    actual = ("actual critical", "share", "actual uncritical", "share")
    cm = Table(
        "Risk: confusion matrix, paper Table 1 (whole effective data set) vs this run's test "
        f"split ({main})",
        ["", *(f"{who}: {c}" for who in ("paper", "ours") for c in actual)],
        anchor="risk-confusion",
        headline=True,
        note=prose("confusion"),
    )
    for label, pair in (("predicted critical", "tp fp"), ("predicted uncritical", "fn tn")):
        row = [Cell(label)]
        for k in pair.split():
            row += [paper_cell("RISK_CONFUSION", k, "int"), derived_paper_cell(f"share_{k}_pct")]
        for k in pair.split():
            row.append(src.cell(RISK_FILE, f"{pre}.confusion.{k}", "int"))
            row.append(src.cell(RISK_FILE, f"{pre}.confusion_pct.{k}", "pct_raw"))
        cm.rows.append(row)
    return cm


def selection_table(src: page.Sources) -> Table | None:
    """Every choice made on the validation split (select_risk): each candidate's validation
    ROC-AUC and decision cut per THW threshold, the shipped one."""
    preds = src.get(SELECTION_FILE, "predictors")
    if not isinstance(preds, dict) or not preds:
        return None
    sel = lambda k: src.get(SELECTION_FILE, k)  # noqa: E731
    shipped, ts = sel("shipped.predictor"), sel("thresholds_s") or []
    keys, cols = [("roc_auc", "g4")], []
    for t in ts:
        keys += [(f"decision.{t:g}.cut", "g4"), (f"decision.{t:g}.balanced_accuracy", "pct")]
        cols += [f"cut at THW {t:g} s (risk)", f"validation bal. acc. at {t:g} s"]
    tab = Table(
        "Risk: choices made on the validation split (the test split is read once, afterwards)",
        ["predictor", "kind", "group", "validation ROC-AUC", *cols, "role"],
        anchor="risk-selection",
        headline=True,
        note=prose("selection", sel=sel),
    )
    for name in _first(preds, shipped):
        pre = f"predictors.{name}"
        row = [Cell(name), *(Cell(str(sel(f"{pre}.{k}") or "")) for k in ("kind", "group"))]
        row += [src.cell(SELECTION_FILE, f"{pre}.{k}", f, record=False) for k, f in keys]
        tab.rows.append(row + [Cell("shipped" if name == shipped else "")])
    return tab


def difference_table(src: page.Sources, at: str) -> Table | None:
    """Paired differences a − b (MSE, balanced accuracy, ROC-AUC at ``at``) with their intervals
    and the ROC-AUC verdict (a claim only where the interval excludes 0)."""
    diffs = src.get(RISK_FILE, "differences")
    if not isinstance(diffs, dict) or not diffs:
        return None
    metrics = {"test/mse": "MSE", f"{at}.balanced_accuracy": "balanced accuracy"}
    metrics[f"{at}.roc_auc"] = "ROC-AUC"
    t = Table(
        "Risk: paired differences a − b on the same test frames (95 % sequence-bootstrap intervals)",
        ["a", "b", "label", "comparison", *(c for n in metrics.values() for c in (f"Δ {n}", CI))]
        + ["verdict (ROC-AUC)"],
        anchor="risk-diff",
        note=prose("differences"),
    )
    why = "claimed only when the paired 95 % interval excludes 0"
    for key, d in ((k, d) for k, d in diffs.items() if isinstance(d, dict)):
        b = str(d.get("b"))
        row = [Cell(str(d.get("a"))), Cell(b + (" (GT disparity)" if b in GT_INPUT else ""))]
        row += [Cell(str(d.get("label"))), Cell(str(d.get("kind", "")))]
        for pre in (f"differences.{key}.{k}" for k in metrics):
            row.append(src.cell(RISK_FILE, f"{pre}.estimate", record=False))
            row.append(interval_cell(src, RISK_FILE, pre, "sequence-bootstrap"))
        verdict = {True: "a better", False: "b better"}.get(beats(d, f"{at}.roc_auc"))
        t.rows.append(row + [Cell(verdict or "no significant difference", title=why)])
    return t


def risk_tables(src: page.Sources) -> list[Table]:
    """Every table of the risk section, in the order it shows them (those without data left out)."""
    at = risk_threshold_key(src)
    main = src.get(RISK_FILE, "main_variant")
    tables = [
        results_table(src, at),
        confusion_table(src, main, at) if isinstance(main, str) else None,
        selection_table(src),
        difference_table(src, at),
    ]
    return [t for t in tables if t is not None]
