"""The pipeline's report: ``reports/README.md`` (GitHub), ``reports/index.html`` (self-contained)
and ``reports/results_table.md`` (the headline tables, included by the project README).

Every number in the report comes from a file: metrics JSON (``reports/metrics/*.json``), stage
timings (``reports/timings/*.json``), ``reports/environment.json``, the run's parameters (passed
in explicitly by the stage) or :mod:`traffictwin.report.paper_numbers` (the papers' reported
values, the only hand-typed numbers). Each table cell that holds a number remembers where it came
from (``Cell.src``, e.g. ``metrics/risk.json#test/mse``); the HTML carries it as ``data-src`` and
the raw value as ``data-value`` so tests can re-check every number against its file.

The report renders whatever metrics files exist: a missing file or key gives an ``n/a`` cell
(and a note naming the file and key), never an error, so a partial pipeline still reports.

Layout of the metrics files this module reads (written by evaluate_fusion / evaluate_risk /
disparity / orb_filter / train_*): see :data:`FUSION_FILE`, :data:`RISK_FILE` and the key
helpers below. Anything else in ``reports/metrics`` still appears in the appendix table.
"""

from __future__ import annotations

import base64
import html
import json
import math
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from traffictwin.report import paper_numbers as P

NA = "n/a"
FUSION_FILE = "fusion.json"
RISK_FILE = "risk.json"
DISPARITY_FILE = "disparity.json"
ORB_FILE = "orb.json"
IMAGE_SUFFIXES = (".png", ".svg", ".jpg", ".jpeg", ".gif")
_MIME = {
    ".png": "image/png",
    ".svg": "image/svg+xml",
    ".jpg": "image/jpeg",
    ".jpeg": "image/jpeg",
    ".gif": "image/gif",
}


# --------------------------------------------------------------------------- formatting
def fmt_value(value: Any, fmt: str = "g4") -> str:
    """Format one number for a table cell.

    ``fmt``: ``g4`` (4 significant digits), ``f<k>`` (k decimals), ``int`` (thousands
    separator ``,``), ``pct`` (a fraction shown as percent, 2 decimals), ``pct_raw`` (already a
    percent, 2 decimals), ``s`` (seconds → ``m:ss`` / ``h:mm:ss``), ``str`` (as is).
    NaN / None → ``n/a``.
    """
    if value is None:
        return NA
    if fmt == "str":
        return str(value)
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, str):
        return value
    v = float(value)
    if math.isnan(v):
        return NA
    if math.isinf(v):
        return "inf" if v > 0 else "-inf"
    if fmt == "g4":
        return f"{v:.4g}"
    if fmt == "int":
        return f"{int(round(v)):,}"
    if fmt == "pct":
        return f"{100.0 * v:.2f} %"
    if fmt == "pct_raw":
        return f"{v:.2f} %"
    if fmt == "s":
        t = int(round(v))
        h, rem = divmod(t, 3600)
        m, s = divmod(rem, 60)
        return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"
    m = re.fullmatch(r"f(\d)", fmt)
    if m:
        return f"{v:.{int(m.group(1))}f}"
    raise ValueError(f"fmt_value: unknown format {fmt!r}")


# --------------------------------------------------------------------------- model
@dataclass
class Cell:
    """One table cell. ``src`` names the file#key a number came from (None for labels/derived text)."""

    text: str
    src: str | None = None
    value: Any = None
    fmt: str | None = None
    title: str = ""  # tooltip (e.g. why a value is n/a)
    derived: str = (
        ""  # how a computed number was derived from sourced cells (e.g. "sum of timings")
    )


@dataclass
class Table:
    title: str
    columns: list[str]
    rows: list[list[Cell]] = field(default_factory=list)
    note: str = ""
    anchor: str = ""


@dataclass
class Figure:
    path: str  # relative to the reports folder, e.g. "figures/fusion_kld_box.png"
    caption: str


@dataclass
class Section:
    title: str
    paragraphs: list[str] = field(default_factory=list)
    tables: list[Table] = field(default_factory=list)
    figures: list[Figure] = field(default_factory=list)
    bullet_groups: list[tuple[str, list[str]]] = field(default_factory=list)  # (heading, bullets)


@dataclass
class Report:
    title: str
    intro: list[str]
    sections: list[Section]
    missing: list[str]


@dataclass
class ReportInputs:
    """Everything the report needs, passed explicitly (the library never reads params.yaml).

    ``reports_dir``: folder with ``metrics/``, ``figures/``, ``plots/``, ``timings/``,
    ``environment.json``; the report files are written there. ``run_params``: flattened
    ``{key: value}`` of the parameters to show (profile sizes, seeds). ``configurations``:
    ``{name: (r m, alpha deg)}``. ``stage_order``: DAG order for the timing table.
    """

    reports_dir: Path
    profile: str
    seed: int
    git_commit: str
    run_params: Mapping[str, Any] = field(default_factory=dict)
    configurations: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    dvc_exp_name: str = ""
    pipeline_run: str = ""
    stage_order: Sequence[str] = ()
    git_dirty: bool = False  # code or config differed from the commit when the report ran


# --------------------------------------------------------------------------- sources
class Sources:
    """Loaded input files with number lookup that records what was missing."""

    def __init__(self, inputs: ReportInputs) -> None:
        self.inputs = inputs
        self.root = Path(inputs.reports_dir)
        self.metrics: dict[str, Any] = {}
        self.missing: list[str] = []
        mdir = self.root / "metrics"
        if mdir.is_dir():
            for p in sorted(mdir.glob("*.json")):
                self.metrics[p.name] = _read_json(p)
        self.timings: dict[str, Any] = {}
        tdir = self.root / "timings"
        if tdir.is_dir():
            for p in sorted(tdir.glob("*.json")):
                self.timings[p.name] = _read_json(p)
        env = self.root / "environment.json"
        self.environment = _read_json(env) if env.exists() else None

    def has(self, file: str) -> bool:
        return file in self.metrics

    def get(self, file: str, key: str, default: Any = None) -> Any:
        """Value at dotted ``key`` in metrics ``file`` (segments may themselves contain '/' or '.')."""
        data = self.metrics.get(file)
        return lookup(data, key, default) if data is not None else default

    def cell(self, file: str, key: str, fmt: str = "g4", *, record: bool = True) -> Cell:
        """Number cell from metrics ``file``#``key``.

        Absent key: ``n/a`` without a source, recorded in :attr:`missing`. JSON ``null`` (the
        writers' spelling of NaN, e.g. precision with no positive prediction): ``n/a`` with its source.
        """
        v = self.get(file, key, ABSENT)
        if v is ABSENT or isinstance(v, (dict, list)):
            if record:
                self.missing.append(f"metrics/{file}#{key}")
            return Cell(NA, title=f"not in reports/metrics/{file}: {key}")
        if v is None:
            return Cell(
                NA,
                src=f"metrics/{file}#{key}",
                value=None,
                fmt=fmt,
                title="undefined (null in the metrics file)",
            )
        return Cell(fmt_value(v, fmt), src=f"metrics/{file}#{key}", value=v, fmt=fmt)

    def param_cell(self, key: str, fmt: str = "str") -> Cell:
        v = self.inputs.run_params.get(key)
        if v is None:
            return Cell(NA, title=f"parameter {key} not set in this run")
        return Cell(fmt_value(v, fmt), src=f"params#{key}", value=v, fmt=fmt)


def paper_cell(table: str, key: str, fmt: str = "g4") -> Cell:
    """Cell with a paper's reported number (``paper_numbers.<table>[key]``)."""
    num = getattr(P, table)[key]
    v = num.value
    fmt = "str" if isinstance(v, str) else fmt
    return Cell(
        fmt_value(v, fmt),
        src=f"paper:{table}.{key}",
        value=v,
        fmt=fmt,
        title=f"{num.source}: {num.unit} {num.note}".strip(),
    )


def derived_paper_cell(key: str, fmt: str = "pct_raw") -> Cell:
    v = P.risk_confusion_derived()[key]
    return Cell(
        fmt_value(v, fmt),
        src=f"paper:derived.{key}",
        value=v,
        fmt=fmt,
        title="derived from Table 1 counts",
    )


ABSENT = object()


def lookup(data: Any, key: str, default: Any = None) -> Any:
    """Nested lookup of ``key`` = segments joined by '.', where a segment may contain '.' or '/'.

    At each level the longest prefix of the remaining key that is a dict key wins, so
    ``"test.A.dnn.kld_fo_mean"``, ``"models.v.at_1.5s.accuracy"`` and a flat
    ``{"test/mse": …}`` all resolve. ``default`` when the key is absent (a JSON ``null`` is
    present and returned as None).
    """
    if key == "":
        return data
    if not isinstance(data, dict):
        return default
    if key in data:
        return data[key]
    parts = key.split(".")
    for i in range(len(parts) - 1, 0, -1):
        head = ".".join(parts[:i])
        if head in data:
            found = lookup(data[head], ".".join(parts[i:]), ABSENT)
            if found is not ABSENT:
                return found
    return default


def flatten_numbers(data: Any, prefix: str = "") -> list[tuple[str, Any]]:
    """``[(dotted key, scalar)]`` for every scalar leaf (numbers, bools, strings) in JSON ``data``."""
    out: list[tuple[str, Any]] = []
    if isinstance(data, dict):
        for k, v in data.items():
            out.extend(flatten_numbers(v, f"{prefix}{k}."))
    elif isinstance(data, list):
        if all(not isinstance(v, (dict, list)) for v in data) and len(data) <= 12:
            out.append((prefix[:-1], data))
        else:
            for i, v in enumerate(data):
                out.extend(flatten_numbers(v, f"{prefix}{i}."))
    else:
        out.append((prefix[:-1], data))
    return out


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not readable JSON ({exc})") from None


# --------------------------------------------------------------------------- fusion section
# fusion.json (stage evaluate_fusion): metrics["test"][cfg][method][metric], methods below;
# metrics["cross"][network cfg][test cfg][metric] for networks evaluated on other configurations.
FUSION_METHOD_LABELS: dict[str, str] = {
    "dnn": "network",
    "naive": "naive (noisy pose + Dempster)",
    "registered": "registered (FM + ECC) + Dempster",
    "naive-yager": "naive + Yager",
    "naive-cautious": "naive + cautious",
    "ego": "ego (map 1 only)",
}
NET, NAIVE = "dnn", "naive"


def fusion_key(cfg: str, method: str, metric: str) -> str:
    """Key of ``metric`` for configuration ``cfg`` and ``method`` in fusion.json."""
    return f"test.{cfg}.{method}.{metric}"


def _fusion_configs(src: Sources) -> list[str]:
    test = lookup(src.metrics.get(FUSION_FILE), "test")
    present = sorted(test) if isinstance(test, dict) else []
    wanted = list(src.inputs.configurations) or list(P.FUSION_CONFIGURATIONS)
    return [c for c in wanted if c in present] + [c for c in present if c not in wanted]


def _fusion_methods(src: Sources, cfgs: Sequence[str]) -> list[str]:
    found: list[str] = []
    for c in cfgs:
        d = lookup(src.metrics.get(FUSION_FILE), f"test.{c}")
        if isinstance(d, dict):
            found += [m for m in d if m not in found]
    order = list(FUSION_METHOD_LABELS)
    return sorted(found, key=lambda m: (order.index(m) if m in order else len(order), m))


def _config_cells(src: Sources, c: str) -> list[Cell]:
    conf = src.inputs.configurations or P.FUSION_CONFIGURATIONS
    r, a = conf.get(c, (float("nan"), float("nan")))
    base = (
        f"params#configurations.{c}"
        if c in src.inputs.configurations
        else f"paper:FUSION_CONFIGURATIONS.{c}"
    )
    return [
        Cell(c),
        Cell(fmt_value(r, "g4"), src=f"{base}.r", value=r, fmt="g4"),
        Cell(fmt_value(a, "g4"), src=f"{base}.alpha", value=a, fmt="g4"),
    ]


def fusion_tables(src: Sources) -> list[Table]:
    """KLD per configuration and method (+ our ranking vs the paper's Fig. 5), P/R/Dice, cross table."""
    cfgs = _fusion_configs(src)
    methods = _fusion_methods(src, cfgs)
    labels = [FUSION_METHOD_LABELS.get(m, m) for m in methods]
    tables = []
    for metric, name, extra in (
        (
            "kld_fo_mean",
            "KLD(a) mean",
            "KL(label‖pred) over (m_F, m_O), clipped to [1e-7, 1], averaged over cells "
            "(the definition in the authors' public code), then averaged over test pairs.",
        ),
        (
            "kld_fo_median",
            "KLD(a) median",
            "Median over test pairs (the line in the paper's Fig. 5 boxes).",
        ),
        (
            "kld_fou_mean",
            "KLD(b) mean",
            "KL over the full vector (m_F, m_O, u), averaged over cells and test pairs.",
        ),
    ):
        cols = ["config", "r [m]", "α [deg]", *labels]
        head = metric == "kld_fo_mean"
        if head:
            cols += ["network vs naive (ours)", "network vs naive (paper, Fig. 5)"]
        t = Table(
            f"Fusion: {name} per pose-noise configuration and method (test split; lower is better)",
            cols,
            note=extra
            + (
                " Paper column: which of the two Fig. 5 of van Kempen et al. shows lower; the paper "
                "prints no KLD values."
                if head
                else ""
            ),
            anchor="fusion-kld" if head else f"fusion-{metric}",
        )
        for c in cfgs:
            cells = [src.cell(FUSION_FILE, fusion_key(c, m, metric)) for m in methods]
            row = _config_cells(src, c) + cells
            if head:
                n = src.get(FUSION_FILE, fusion_key(c, NET, metric))
                b = src.get(FUSION_FILE, fusion_key(c, NAIVE, metric))
                ok = (
                    isinstance(n, (int, float))
                    and isinstance(b, (int, float))
                    and not (math.isnan(n) or math.isnan(b))
                )
                row.append(Cell(("network lower" if n < b else "naive lower") if ok else NA))
                paper = P.FUSION_KLD_WINNER.get(c)
                row.append(
                    Cell(
                        {"network": "network lower", "baseline": "naive lower"}.get(paper or "", NA)
                    )
                )
            t.rows.append(row)
        tables.append(t)

    scores = Table(
        "Fusion: precision / recall / Dice per class (test split, pooled over cells; higher is better)",
        [
            "config",
            "method",
            "precision occ",
            "recall occ",
            "Dice occ",
            "precision free",
            "recall free",
            "Dice free",
        ],
        note=(
            "A cell is predicted occupied where p_O > 0.5 and free where p_O < 0.5 (DESIGN.md; the paper's "
            "sentence swaps the words); only label-known cells count. The paper shows these as Figs. 6 and 7 "
            "without printed values."
        ),
        anchor="fusion-scores",
    )
    for c in cfgs:
        for m, label in zip(methods, labels):
            scores.rows.append(
                [Cell(c), Cell(label)]
                + [
                    src.cell(FUSION_FILE, fusion_key(c, m, f"{k}_{cls}"))
                    for cls in ("occ", "free")
                    for k in ("precision", "recall", "dice")
                ]
            )
    tables.append(scores)

    cross = lookup(src.metrics.get(FUSION_FILE), "cross")
    if isinstance(cross, dict) and cross:
        nets = sorted(cross)
        tcfgs = sorted({tc for n in nets if isinstance(cross[n], dict) for tc in cross[n]})
        t = Table(
            "Fusion: cross table, KLD(a) mean of the network trained on one configuration (rows) tested on "
            "another (columns)",
            ["network trained on", *[f"test {tc}" for tc in tcfgs]],
            anchor="fusion-cross",
            note="A subset of the test pairs (evaluation.fusion.cross_max_pairs).",
        )
        for n in nets:
            t.rows.append(
                [Cell(n)] + [src.cell(FUSION_FILE, f"cross.{n}.{tc}.kld_fo_mean") for tc in tcfgs]
            )
        tables.append(t)
    return tables


# --------------------------------------------------------------------------- risk section
# risk.json (stage evaluate_risk): models[variant] and baselines[name] each with test/mse, test/mae,
# test/thw_mae_s, ... and at_<t>s {accuracy, precision, recall, f1, roc_auc, confusion{tp,fp,fn,tn},
# confusion_pct, critical_fraction_true}; main_variant; thresholds_s; n_frames{total,
# orb_outliers_dropped, train, val, test}; region{labels, agreement, predictors[name][label]}.
RISK_BASELINE_LABELS = {
    "train_mean": "baseline: train mean",
    "train_median": "baseline: train median",
    "geometric": "baseline: geometric (SGM distance / speed)",
}
PAPER_DASH = "—"


def _risk_threshold_key(src: Sources) -> str:
    ts = src.get(RISK_FILE, "thresholds_s")
    t = ts[0] if isinstance(ts, list) and ts else P.RISK["thw_threshold_s"].value
    return f"at_{float(t):g}s"


def risk_predictors(src: Sources) -> list[tuple[str, str, str]]:
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


def risk_tables(src: Sources) -> list[Table]:
    """Paper vs our variants vs baselines (MSE, accuracy, …), the confusion matrix, the risk-region check."""
    at = _risk_threshold_key(src)
    preds = risk_predictors(src)
    t = Table(
        "Risk: test results, paper vs this run (critical ⇔ THW < 1.5 s ⇔ risk > 1/30)",
        ["metric", "paper (Feth et al.)", *[label for _, label, _ in preds], "paper source"],
        note=(
            "The paper's accuracy and confusion matrix are over its whole effective data set (106,170 frames), "
            "ours over the test split; '—': the paper reports no such number. Wang & Kato (ref. [20] of the "
            "paper) solve a different, 3-class task with subjective labels; the paper quotes their accuracy "
            "as the related work's best."
        ),
        anchor="risk-results",
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


def risk_training_table(src: Sources) -> Table | None:
    """Per variant: inputs, label, parameters, training time and best validation MSE (risk.json models)."""
    models = src.get(RISK_FILE, "models")
    if not isinstance(models, dict) or not models:
        return None
    cols = [
        ("n_parameters", "parameters", "int"),
        ("n_train", "train frames", "int"),
        ("steps", "steps", "int"),
        ("best_step", "best step", "int"),
        ("best_val_mse", "best val MSE", "g4"),
        ("train_seconds", "train time [s]", "f1"),
    ]
    t = Table(
        "Risk: training of each variant (DAVE-2-like net; paper: 30 epochs, batch 10, Adam)",
        ["variant", "inputs", "label", *[c[1] for c in cols]],
        anchor="risk-training",
    )
    main = src.get(RISK_FILE, "main_variant")
    for v in sorted(models, key=lambda v: (v != main, v)):
        m = models[v] if isinstance(models[v], dict) else {}
        inputs = "+".join(m.get("inputs", [])) + (" + speed" if m.get("speed") else "")
        t.rows.append(
            [Cell(v), Cell(inputs or NA), Cell(str(m.get("label", NA)))]
            + [src.cell(RISK_FILE, f"models.{v}.{k}", f) for k, _, f in cols]
        )
    return t


def files_table(src: Sources, pattern: str, title: str, anchor: str) -> Table | None:
    """Metrics files matching ``pattern`` (a regex with one group naming the column) side by side:
    rows = keys (union, first file's order), columns = files."""
    files = [(m.group(1), f) for f in src.metrics if (m := re.fullmatch(pattern, f))]
    if not files:
        return None
    keys: list[str] = []
    for _, f in files:
        keys += [k for k, v in flatten_numbers(src.metrics[f]) if k not in keys]
    t = Table(title, ["key", *[name for name, _ in files]], anchor=anchor)
    for k in keys:
        row = [Cell(k)]
        for _, f in files:
            v = src.get(f, k, ABSENT)
            if v is ABSENT:
                row.append(Cell(""))
            elif isinstance(v, (str, list, bool)):
                row.append(Cell(str(v)))
            else:
                row.append(src.cell(f, k, "int" if isinstance(v, int) else "g4"))
        t.rows.append(row)
    return t


def risk_data_table(src: Sources) -> Table | None:
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
            Cell("dropped by the ORB check"),
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


def generic_table(src: Sources, file: str, title: str, anchor: str = "") -> Table | None:
    """Every scalar in metrics ``file`` as a key/value table (None if the file is absent)."""
    data = src.metrics.get(file)
    if data is None:
        return None
    t = Table(title, ["key", "value"], anchor=anchor)
    for key, v in flatten_numbers(data):
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            fmt = "int" if isinstance(v, int) else "g4"
            t.rows.append(
                [Cell(key), Cell(fmt_value(v, fmt), src=f"metrics/{file}#{key}", value=v, fmt=fmt)]
            )
        else:
            t.rows.append(
                [
                    Cell(key),
                    Cell(
                        fmt_value(v, "str") if not isinstance(v, list) else ", ".join(map(str, v))
                    ),
                ]
            )
    return t


def pivot_table(src: Sources, file: str, title: str, anchor: str = "") -> Table | None:
    """Metrics ``file`` as a grid: flat ``"<group>/<metric>"`` keys → rows = groups, columns = metrics.

    Falls back to :func:`generic_table` when the keys are not of that form. None if the file is absent.
    """
    data = src.metrics.get(file)
    if data is None:
        return None
    flat = [(k, v) for k, v in flatten_numbers(data)]
    if not flat or not all("/" in k and "." not in k for k, _ in flat):
        return generic_table(src, file, title, anchor)
    groups: list[str] = []
    metrics: list[str] = []
    for k, _ in flat:
        g, m = k.split("/", 1)
        groups += [g] if g not in groups else []
        metrics += [m] if m not in metrics else []

    def cell(g: str, m: str) -> Cell:
        key = f"{g}/{m}"
        if key not in data:
            return Cell("")
        v = data[key]
        if isinstance(v, (str, list, bool)):
            return Cell(str(v))
        return src.cell(file, key, "int" if isinstance(v, int) else "g4")

    if len(metrics) <= len(groups):  # the narrower orientation: groups as rows
        t = Table(title, ["group", *metrics], anchor=anchor)
        t.rows = [[Cell(g)] + [cell(g, m) for m in metrics] for g in groups]
    else:
        t = Table(title, ["metric", *groups], anchor=anchor)
        t.rows = [[Cell(m)] + [cell(g, m) for g in groups] for m in metrics]
    return t


# --------------------------------------------------------------------------- run section
def timing_table(src: Sources, order: Sequence[str] = ()) -> Table:
    t = Table(
        "Stage wall times (this run)", ["stage", "wall time [s]", "wall time"], anchor="timings"
    )
    items = []
    for name, d in src.timings.items():
        if not isinstance(d, dict) or "seconds" not in d:
            continue
        stage = str(d.get("stage", name.removesuffix(".json")))
        if stage == "report":  # written after this report; would always be one run stale
            continue
        items.append((stage, name, d["seconds"]))
    rank = {s: i for i, s in enumerate(order)}

    def key(it: tuple[str, str, Any]) -> tuple[int, str]:
        base = it[0].split("@")[0]
        return (rank.get(it[0], rank.get(base, len(rank))), it[0])

    total = 0.0
    for stage, name, secs in sorted(items, key=key):
        total += float(secs)
        t.rows.append(
            [
                Cell(stage),
                Cell(fmt_value(secs, "f1"), src=f"timings/{name}#seconds", value=secs, fmt="f1"),
                Cell(fmt_value(secs, "s"), src=f"timings/{name}#seconds", value=secs, fmt="s"),
            ]
        )
    if items:
        d = "sum of the wall times above"
        t.rows.append(
            [
                Cell("total (sum)"),
                Cell(fmt_value(total, "f1"), value=total, fmt="f1", derived=d),
                Cell(fmt_value(total, "s"), value=total, fmt="s", derived=d),
            ]
        )
    t.note = "Sum of the stages' own wall times as recorded by each stage (reports/timings); DVC overhead not included."
    return t


def environment_table(src: Sources) -> Table | None:
    env = src.environment
    if not isinstance(env, dict):
        return None
    t = Table("Machine and software of this run", ["item", "value"], anchor="environment")
    for k in ("cpu", "cpu_count", "memory_gb", "gpu", "cuda_available", "python", "platform"):
        if k in env:
            v = env[k]
            if isinstance(v, (int, float)) and not isinstance(v, bool):
                t.rows.append(
                    [
                        Cell(k),
                        Cell(fmt_value(v, "g4"), src=f"environment.json#{k}", value=v, fmt="g4"),
                    ]
                )
            else:
                t.rows.append([Cell(k), Cell(fmt_value(v, "str"))])
    for pkg, ver in (env.get("packages") or {}).items():
        t.rows.append([Cell(pkg), Cell(str(ver))])
    return t


def params_table(src: Sources) -> Table:
    t = Table(
        "Parameters of this run (scale and seeds)",
        ["parameter", "value"],
        anchor="params",
        note="The parameters the profiles override (their sizes) and every seed, from params.yaml.",
    )
    for k in sorted(src.inputs.run_params):
        t.rows.append([Cell(k), src.param_cell(k)])
    return t


# --------------------------------------------------------------------------- figures
# The figures the stages write (file stem → section, caption), in the order the report shows them.
KNOWN_FIGURES: list[tuple[str, str, str]] = [
    (
        "fusion_data_samples",
        "fusion",
        "Input maps and label of sample pairs from our simulator (cf. the paper's Fig. 2)",
    ),
    (
        "fusion_qualitative",
        "fusion",
        "Label, naive fusion and network per configuration (mirrors the paper's Fig. 4)",
    ),
    (
        "fusion_kld_boxplot",
        "fusion",
        "KLD distribution over the test set per configuration and method (mirrors Fig. 5)",
    ),
    (
        "fusion_scores_occupied",
        "fusion",
        "Precision / recall / Dice of occupied cells per configuration (mirrors Fig. 6)",
    ),
    (
        "fusion_scores_free",
        "fusion",
        "Precision / recall / Dice of free cells per configuration (mirrors Fig. 7)",
    ),
    (
        "stereo_example",
        "risk",
        "Left image, SGM disparity and exact disparity (mirrors the risk paper's Fig. 2)",
    ),
    (
        "risk_metric_example",
        "risk",
        "Grid-map risk metric: scene and worst-time-headway region (cf. Figs. 3 and 4)",
    ),
    ("orb_outlier_example", "risk", "A stereo pair the ORB check flags (Sec. 3.3)"),
    (
        "risk_training_curves",
        "risk",
        "Training and validation average error per variant (mirrors Figs. 5 and 6)",
    ),
    (
        "risk_confusion",
        "risk",
        "Confusion matrix of the main variant at THW 1.5 s (mirrors Table 1)",
    ),
    (
        "risk_scatter",
        "risk",
        "Predicted vs true risk on the test split, with the critical threshold",
    ),
    ("risk_examples", "risk", "Test scenes with true and predicted risk (mirrors Fig. 7)"),
]
_SECTION_PATTERNS = (
    (r"fusion|prealign|pose|ogm", "fusion"),
    (r"risk|stereo|disparity|orb|camera|thw", "risk"),
)


def collect_figures(reports_dir: Path) -> dict[str, list[Figure]]:
    """Images under ``reports/figures``: the known ones in :data:`KNOWN_FIGURES` order with their captions,
    then any other image, put into 'fusion' / 'risk' by its name or into 'other'."""
    out: dict[str, list[Figure]] = {"fusion": [], "risk": [], "other": []}
    fdir = Path(reports_dir) / "figures"
    if not fdir.is_dir():
        return out
    files = {
        p.relative_to(reports_dir).as_posix(): p
        for p in sorted(fdir.rglob("*"))
        if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
    }
    done: set[str] = set()
    for stem, section, caption in KNOWN_FIGURES:
        for rel, p in files.items():
            if p.stem == stem and rel not in done:
                out[section].append(Figure(rel, f"{caption} — `{rel}`"))
                done.add(rel)
    for rel, p in files.items():
        if rel in done:
            continue
        section = next(
            (sec for pat, sec in _SECTION_PATTERNS if re.search(pat, p.stem.lower())), "other"
        )
        out[section].append(Figure(rel, f"`{rel}`"))
    return out


# --------------------------------------------------------------------------- findings
def findings(kind: str, metrics_dir: Path) -> tuple[list[str], str]:
    """Bullet points from ``traffictwin.<kind>.findings`` (written by the evaluation owners).

    Returns ``(bullets, note)``; a missing generator or metrics file gives no bullets and a note.
    """
    import importlib

    try:
        mod = importlib.import_module(f"traffictwin.{kind}.findings")
    except ModuleNotFoundError as exc:
        if exc.name and exc.name.endswith(f"{kind}.findings"):
            return [], f"(findings generator traffictwin.{kind}.findings not available)"
        raise
    fn: Callable[..., Any] | None = getattr(mod, "findings", None) or getattr(
        mod, f"{kind}_findings", None
    )
    if fn is None:
        return [], f"(traffictwin.{kind}.findings has no findings() function)"
    file = metrics_dir / f"{kind}.json"
    if not file.exists():
        return [], f"(no {file.name}: findings need the evaluation metrics)"
    res = fn(json.loads(file.read_text()))
    if isinstance(res, str):
        return markdown_bullets(res), ""
    bullets = []
    for item in res:
        if isinstance(item, str):
            bullets.append(item)
        elif isinstance(item, Mapping):
            bullets.append(str(item.get("text") or item.get("finding") or item))
        else:
            bullets.append(str(getattr(item, "text", item)))
    return bullets, ""


def markdown_bullets(text: str) -> list[str]:
    """Statements of a markdown findings text: bullets and paragraph lines; headings and tables dropped
    (the report's own tables show those numbers with their sources)."""
    out: list[str] = []
    for ln in text.splitlines():
        t = ln.strip()
        if not t or t.startswith("#") or t.startswith("|"):
            continue
        if t[:2] in ("- ", "* "):
            out.append(t[2:].strip())
        elif ln.startswith((" ", "\t")) and out:  # continuation of a bullet
            out[-1] += " " + t
        else:
            out.append(t)
    return out


# --------------------------------------------------------------------------- assemble
DATA_FILES = (
    ("fusion_data.json", "Fusion data (reports/metrics/fusion_data.json)"),
    ("risk_data.json", "Risk data: stereo frames and risk labels (reports/metrics/risk_data.json)"),
    (DISPARITY_FILE, "SGM disparity vs exact disparity (reports/metrics/disparity.json)"),
    (ORB_FILE, "ORB stereo-pair check vs injected faults (reports/metrics/orb.json)"),
)


def build_report(inputs: ReportInputs) -> Report:
    """Assemble the report model from the files under ``inputs.reports_dir``."""
    src = Sources(inputs)
    figs = collect_figures(src.root)
    root = src.root

    intro = [
        "Generated by the DVC stage `report` from the metrics, figures and timings of one pipeline run; "
        "do not edit by hand. Every number below comes from a file: `reports/metrics/*.json`, "
        "`reports/timings/*.json`, `reports/environment.json`, the run's `params.yaml`, or — for the "
        "papers' values — `src/traffictwin/report/paper_numbers.py` (with the section they are printed in).",
        "**The data differs from the papers'.** Both papers used commercial simulators (VTD, GTA V) at full "
        "scale; this run uses traffictwin's own simulator (synthetic road templates, ray-cast lidar, rendered "
        f"stereo camera) at the `{inputs.profile}` profile's scale. Compare trends and rankings, not absolute values.",
    ]
    run = Section("This run")
    commit = inputs.git_commit or "unknown"
    run.paragraphs.append(
        f"Profile `{inputs.profile}`, seed `{inputs.seed}`, git commit `{commit}`"
        + (" (with uncommitted changes to code or configuration)" if inputs.git_dirty else "")
        + (f", DVC experiment `{inputs.dvc_exp_name}`" if inputs.dvc_exp_name else "")
        + (
            f", pipeline run `{inputs.pipeline_run}` (MLflow tag `pipeline_run`)"
            if inputs.pipeline_run
            else ""
        )
        + "."
    )
    run.tables.append(params_table(src))
    run.tables.append(timing_table(src, inputs.stage_order))
    env_t = environment_table(src)
    if env_t:
        run.tables.append(env_t)

    fusion = Section("Paper 1 — cooperative evidential occupancy-grid fusion")
    fusion.paragraphs.append(
        f"Reference: {P.FUSION_CITATION}. Baseline: the second map transformed by the noisy "
        "relative pose, then Dempster's rule (the paper's 'naive fusion')."
    )
    if src.has(FUSION_FILE):
        fusion.tables.extend(fusion_tables(src))
    tt = files_table(
        src,
        r"train_fusion_(\w+)\.json",
        "Fusion: training per configuration (validation split; "
        "`_naive` = the naive fusion on the same pairs)",
        "fusion-training",
    )
    if tt:
        fusion.tables.append(tt)
    else:
        fusion.paragraphs.append(
            f"`reports/metrics/{FUSION_FILE}` is missing: the fusion evaluation has not run."
        )
    bullets, note = findings("fusion", root / "metrics")
    fusion.bullet_groups.append(("Findings of this run", bullets or [note]))
    fusion.bullet_groups.append(
        (
            "What the paper reports (qualitatively; it prints no numbers)",
            [f"{c.text} ({c.source})" for c in P.FUSION_CLAIMS.values()],
        )
    )
    fusion.figures = figs["fusion"]

    risk = Section("Paper 2 — dynamic risk assessment from a stereo camera")
    risk.paragraphs.append(f"Reference: {P.RISK_CITATION}.")
    if src.has(RISK_FILE):
        risk.tables.extend(risk_tables(src))
        rt = risk_training_table(src)
        if rt:
            risk.tables.append(rt)
    else:
        risk.paragraphs.append(
            f"`reports/metrics/{RISK_FILE}` is missing: the risk evaluation has not run."
        )
    dt = risk_data_table(src)
    if dt:
        risk.tables.append(dt)
    bullets, note = findings("risk", root / "metrics")
    risk.bullet_groups.append(("Findings of this run", bullets or [note]))
    risk.figures = figs["risk"]

    data = Section("Data and disparity statistics")
    for file, title in DATA_FILES:
        t = pivot_table(src, file, title, anchor=f"data-{Path(file).stem}")
        if t:
            data.tables.append(t)
        elif file in (DISPARITY_FILE, ORB_FILE):
            data.paragraphs.append(f"`reports/metrics/{file}` is missing.")

    appendix = Section("Appendix — every metrics file")
    shown = {f for f, _ in DATA_FILES} | {
        f for f in src.metrics if re.fullmatch(r"train_fusion_\w+\.json", f)
    }
    for file in src.metrics:
        if file in shown:
            continue
        t = generic_table(src, file, f"reports/metrics/{file}", anchor=f"m-{Path(file).stem}")
        if t:
            appendix.tables.append(t)
    if figs["other"]:
        appendix.figures = figs["other"]

    return Report(
        "traffictwin — results report",
        intro,
        [run, fusion, risk, data, appendix],
        sorted(set(src.missing)),
    )


def results_tables(report: Report) -> list[Table]:
    """The headline tables (for results_table.md / the project README)."""
    wanted = {"fusion-kld", "risk-results", "risk-confusion"}
    return [t for s in report.sections for t in s.tables if t.anchor in wanted]


# --------------------------------------------------------------------------- markdown
def _md_cell(c: Cell) -> str:
    return c.text.replace("|", "\\|").replace("\n", " ")


def table_markdown(t: Table) -> str:
    lines = [
        f"**{t.title}**",
        "",
        "| " + " | ".join(x.replace("|", "\\|") for x in t.columns) + " |",
        "|" + "|".join(" --- " for _ in t.columns) + "|",
    ]
    for row in t.rows:
        lines.append("| " + " | ".join(_md_cell(c) for c in row) + " |")
    if t.note:
        lines += ["", f"<sub>{t.note}</sub>"]
    return "\n".join(lines)


def render_markdown(report: Report) -> str:
    out = [f"# {report.title}", ""]
    for p in report.intro:
        out += [p, ""]
    out += [
        "Contents: " + " · ".join(f"[{s.title}](#{_slug(s.title)})" for s in report.sections),
        "",
    ]
    for s in report.sections:
        out += [f"## {s.title}", ""]
        for p in s.paragraphs:
            out += [p, ""]
        for head, bullets in s.bullet_groups:
            out += [f"### {head}", ""] + [f"- {b}" for b in bullets] + [""]
        for t in s.tables:
            out += [table_markdown(t), ""]
        for f in s.figures:
            out += [f"![{_alt(f.caption)}]({f.path})", "", f"*{f.caption}*", ""]
    if report.missing:
        out += [
            "## Missing values",
            "",
            "These metrics were looked for and not found (shown as `n/a`):",
            "",
        ]
        out += [f"- `{m}`" for m in report.missing] + [""]
    return "\n".join(out).rstrip() + "\n"


def render_results_markdown(report: Report, link: str = "README.md") -> str:
    out = ["<!-- generated by the DVC stage `report`; do not edit -->", ""]
    for t in results_tables(report):
        out += [table_markdown(t), ""]
    out.append(f"Full report: [{link}]({link}).")
    return "\n".join(out) + "\n"


def _slug(title: str) -> str:
    s = re.sub(r"[^\w\- ]", "", title.lower()).strip()
    return re.sub(r"\s", "-", s)


def _alt(caption: str) -> str:
    return re.sub(r"[`\[\]]", "", caption)


# --------------------------------------------------------------------------- html
CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;max-width:1200px;margin:2em auto;padding:0 1em;color:#222}
table{border-collapse:collapse;margin:.5em 0 1.5em 0;font-size:.9em}
th,td{border:1px solid #ccc;padding:.25em .6em;text-align:right}
th{background:#f3f3f3} td:first-child,th:first-child{text-align:left}
td.na{color:#999} caption{text-align:left;font-weight:600;margin-bottom:.3em}
figure{margin:1em 0} figure img{max-width:100%;border:1px solid #eee}
figcaption{font-size:.9em;color:#555} p.note{font-size:.85em;color:#555;margin-top:-1em}
code{background:#f5f5f5;padding:0 .2em}
"""


def _inline(text: str) -> str:
    s = html.escape(text, quote=False)
    s = re.sub(r"`([^`]+)`", r"<code>\1</code>", s)
    s = re.sub(r"\*\*([^*]+)\*\*", r"<strong>\1</strong>", s)
    s = re.sub(
        r"\[([^\]]+)\]\(([^)\s]+)\)",
        lambda m: f'<a href="{html.escape(m.group(2))}">{m.group(1)}</a>',
        s,
    )
    return s


def table_html(t: Table) -> str:
    attrs = f' id="{html.escape(t.anchor)}"' if t.anchor else ""
    out = [
        f"<table{attrs}>",
        f"<caption>{_inline(t.title)}</caption>",
        "<thead><tr>" + "".join(f"<th>{html.escape(c)}</th>" for c in t.columns) + "</tr></thead>",
        "<tbody>",
    ]
    for row in t.rows:
        tds = []
        for c in row:
            a = []
            if c.src:
                a.append(f'data-src="{html.escape(c.src)}"')
                a.append(f'data-value="{html.escape(json.dumps(c.value))}"')
                a.append(f'data-fmt="{html.escape(c.fmt or "")}"')
            if c.derived:
                a.append(f'data-derived="{html.escape(c.derived)}"')
                a.append(f'data-value="{html.escape(json.dumps(c.value))}"')
            if c.title:
                a.append(f'title="{html.escape(c.title)}"')
            if c.text == NA:
                a.append('class="na"')
            tds.append(f"<td{' ' + ' '.join(a) if a else ''}>{_inline(c.text)}</td>")
        out.append("<tr>" + "".join(tds) + "</tr>")
    out.append("</tbody></table>")
    if t.note:
        out.append(f'<p class="note">{_inline(t.note)}</p>')
    return "\n".join(out)


def figure_html(f: Figure, reports_dir: Path, embed: bool = True) -> str:
    p = Path(reports_dir) / f.path
    if embed:
        data = base64.b64encode(p.read_bytes()).decode("ascii")
        srcattr = f"data:{_MIME.get(p.suffix.lower(), 'application/octet-stream')};base64,{data}"
    else:
        srcattr = html.escape(f.path)
    return (
        f'<figure><img src="{srcattr}" alt="{html.escape(_alt(f.caption))}" data-file="{html.escape(f.path)}"/>'
        f"<figcaption>{_inline(f.caption)}</figcaption></figure>"
    )


def render_html(report: Report, reports_dir: Path, embed: bool = True) -> str:
    """Self-contained HTML (figures embedded as base64 unless ``embed=False``)."""
    out = [
        "<!DOCTYPE html>",
        '<html lang="en">',
        "<head>",
        '<meta charset="utf-8"/>',
        f"<title>{html.escape(report.title)}</title>",
        f"<style>{CSS}</style>",
        "</head>",
        "<body>",
        f"<h1>{html.escape(report.title)}</h1>",
    ]
    out += [f"<p>{_inline(p)}</p>" for p in report.intro]
    out.append(
        "<nav><ul>"
        + "".join(
            f'<li><a href="#{_slug(s.title)}">{html.escape(s.title)}</a></li>'
            for s in report.sections
        )
        + "</ul></nav>"
    )
    for s in report.sections:
        out.append(f'<section id="{_slug(s.title)}"><h2>{html.escape(s.title)}</h2>')
        out += [f"<p>{_inline(p)}</p>" for p in s.paragraphs]
        for head, bullets in s.bullet_groups:
            out.append(f"<h3>{html.escape(head)}</h3>")
            out.append("<ul>" + "".join(f"<li>{_inline(b)}</li>" for b in bullets) + "</ul>")
        out += [table_html(t) for t in s.tables]
        out += [figure_html(f, reports_dir, embed) for f in s.figures]
        out.append("</section>")
    if report.missing:
        out.append(
            '<section id="missing"><h2>Missing values</h2><ul>'
            + "".join(f"<li><code>{html.escape(m)}</code></li>" for m in report.missing)
            + "</ul></section>"
        )
    out += ["</body>", "</html>"]
    return "\n".join(out) + "\n"


# --------------------------------------------------------------------------- write
def write_report(
    inputs: ReportInputs,
    readme: Path | None = None,
    index_html: Path | None = None,
    results_md: Path | None = None,
) -> Report:
    """Build the report and write README.md, index.html and results_table.md (atomically)."""
    from traffictwin.io.atomic import write_text_atomic

    root = Path(inputs.reports_dir)
    report = build_report(inputs)
    md = render_markdown(report)
    page = render_html(report, root, embed=True)
    res = render_results_markdown(report)
    write_text_atomic(readme or root / "README.md", md)
    write_text_atomic(index_html or root / "index.html", page)
    write_text_atomic(results_md or root / "results_table.md", res)
    return report
