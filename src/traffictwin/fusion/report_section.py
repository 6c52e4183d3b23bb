"""The fusion part of the report (van Kempen et al.): what the results section says, which
metrics and figures it shows, and the paper's claims beside them.

Reads ``fusion.json`` (stage evaluate_fusion; layout in :mod:`traffictwin.fusion.evaluation`):
``test.<cfg>.<row>.<metric>`` with its 95 % interval ``<metric>_ci``, rows in
:data:`FUSION_METHOD_LABELS` plus the ``fusion_variants`` network rows (``dnn[<loss>]``, …);
``diff.<cfg>.<row>.vs_<base>.<metric>`` (paired differences); ``label.<cfg>.u_mean``;
``targets``; ``cross.dnn-<net>.<cfg>.<metric>``. Also ``train_fusion_<name>.json`` (stage
train_fusion) and ``fusion_data.json`` (stage generate_fusion), and the learning-curve figures
``figures/train_fusion_<name>.png`` that train_fusion writes (captioned here). Entry point:
:func:`provider`.

The headline is KLD(b) ``kld_fou_mean`` (KL over the full mass vector); KLD(a) ``kld_fo_mean``
is kept as a table "for comparison with the paper". An interval cell is *derived* (its
``derived`` names the ``_ci`` key it was read from); a "lower" / "higher" verdict is shown only
when the paired interval of the difference excludes 0.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from traffictwin.fusion.findings import fusion_findings, verdict
from traffictwin.report import model as page
from traffictwin.report import paper_numbers as P
from traffictwin.report.model import NA, Cell, Table, fmt_value, lookup
from traffictwin.report.summary import Headline, headline
from traffictwin.report.tables import files_table, findings_group

FUSION_FILE = "fusion.json"
TRAINING_FILES = r"train_fusion_(\w+)\.json"  # the one network and each variant, side by side
TITLE = "Paper 1 — cooperative evidential occupancy-grid fusion"

# The figures the fusion stages write: file stem -> caption, in the order the section shows them.
FIGURES: dict[str, str] = {
    "fusion_data_samples": "Input maps and label of sample pairs from our simulator (cf. the paper's Fig. 2)",
    "fusion_qualitative": "Label, naive fusion and network per configuration (mirrors the paper's Fig. 4)",
    "fusion_kld_boxplot": "KLD(b) distribution over the test set per configuration and method (cf. Fig. 5, which shows KLD(a))",
    "fusion_scores_occupied_zoomed": "Precision / recall / Dice of occupied cells per configuration, each "
    "panel's score axis zoomed to its data (mirrors Fig. 6; drawn by the report stage)",
    "fusion_scores_free_zoomed": "Precision / recall / Dice of free cells per configuration, each panel's "
    "score axis zoomed to its data (mirrors Fig. 7; drawn by the report stage)",
    "fusion_scores_occupied": "Precision / recall / Dice of occupied cells per configuration (mirrors Fig. 6)",
    "fusion_scores_free": "Precision / recall / Dice of free cells per configuration (mirrors Fig. 7)",
}
# figures the report stage redraws (:func:`draw_score_figures`): shown instead of evaluate_fusion's
REPLACES = {
    "fusion_scores_occupied_zoomed": "fusion_scores_occupied",
    "fusion_scores_free_zoomed": "fusion_scores_free",
}
SCORE_METRICS = ("precision", "recall", "Dice")
FIGURE_PATTERN = r"fusion|prealign|pose|ogm|registration"
DATA_FILES = (page.DataFile("fusion_data.json", "Fusion data (reports/metrics/fusion_data.json)"),)

FUSION_METHOD_LABELS: dict[str, str] = {
    "dnn": "network",
    "naive": "naive (noisy pose + Dempster)",
    "registered": "registered (FM + ECC) + Dempster",
    "naive-yager": "naive + Yager",
    "naive-cautious": "naive + cautious",
    "ego": "ego (map 1 only)",
    "registered+network": "registered + network",
    "learned": "learned registration + Dempster",
    "learned+network": "learned registration + network",
}
PER_CONFIG_ROW = "dnn[per-config]"  # the ablation's networks trained on one configuration each
POSE_ROWS = ("registered", "learned")  # rows with their own pose estimate (the hybrids reuse them)
REGISTRATION_FILES = r"train_(registration)\.json"  # the one learned registration
NET, NAIVE, REG = "dnn", "naive", "registered"
HEADLINE = "kld_fou_mean"
LEARNING_CURVE = re.compile(
    r"train_(fusion|registration)_?(\w*)"
)  # figures/train_fusion_<name>.png (train_fusion and its variants), train_registration.png
CI_NOTE = (
    "Brackets: 95 % cluster-bootstrap interval (scenario = pair_id // 1000 resampled; "
    "evaluation.fusion_ci)."
)


def fusion_key(cfg: str, method: str, metric: str) -> str:
    """Key of ``metric`` for configuration ``cfg`` and ``method`` in fusion.json."""
    return f"test.{cfg}.{method}.{metric}"


def _fusion_configs(
    src: page.Sources, configurations: Mapping[str, tuple[float, float]]
) -> list[str]:
    test = lookup(src.metrics.get(FUSION_FILE), "test")
    present = sorted(test) if isinstance(test, dict) else []
    wanted = list(configurations) or list(P.FUSION_CONFIGURATIONS)
    return [c for c in wanted if c in present] + [c for c in present if c not in wanted]


def _fusion_methods(src: page.Sources, cfgs: Sequence[str]) -> list[str]:
    found: list[str] = []
    for c in cfgs:
        d = lookup(src.metrics.get(FUSION_FILE), f"test.{c}")
        if isinstance(d, dict):
            found += [m for m in d if m not in found]
    order = list(FUSION_METHOD_LABELS)
    return sorted(found, key=lambda m: (order.index(m) if m in order else len(order), m))


def _config_cells(configurations: Mapping[str, tuple[float, float]], c: str) -> list[Cell]:
    conf = configurations or P.FUSION_CONFIGURATIONS
    r, a = conf.get(c, (float("nan"), float("nan")))
    base = (
        f"params#configurations.{c}" if c in configurations else f"paper:FUSION_CONFIGURATIONS.{c}"
    )
    return [
        Cell(c),
        Cell(fmt_value(r, "g4"), src=f"{base}.r", value=r, fmt="g4"),
        Cell(fmt_value(a, "g4"), src=f"{base}.alpha", value=a, fmt="g4"),
    ]


def _num(v: Any) -> float | None:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else None


def _ci_cell(src: page.Sources, key: str, file: str = FUSION_FILE) -> Cell:
    """``[lo, hi]`` of ``<key>_ci`` (or of ``key`` itself when it holds ``lo``/``hi``) in metrics
    file ``file``, a derived cell."""
    base = key if isinstance(src.get(file, f"{key}.lo"), (int, float)) else f"{key}_ci"
    path = src.paths.get(file, f"metrics/{file}")
    lo, hi = _num(src.get(file, f"{base}.lo")), _num(src.get(file, f"{base}.hi"))
    if lo is None or hi is None or math.isnan(lo) or math.isnan(hi):
        return Cell(NA, title=f"no interval in reports/{path}: {base}")
    return Cell(
        f"[{fmt_value(lo, 'g4')}, {fmt_value(hi, 'g4')}]",
        value=[lo, hi],
        derived=f"95 % cluster-bootstrap interval, {path}#{base}",
    )


def _has(src: page.Sources, c: str, m: str) -> bool:
    """Row ``m`` was evaluated at configuration ``c``."""
    return isinstance(src.get(FUSION_FILE, f"test.{c}.{m}"), dict)


def _row_cell(src: page.Sources, c: str, m: str, metric: str) -> Cell:
    """``test.<c>.<m>.<metric>``; a row not evaluated at ``c`` (a variant elsewhere) is n/a, not missing."""
    if not _has(src, c, m):
        return Cell(NA, title=f"{m} not evaluated at configuration {c}")
    return src.cell(FUSION_FILE, fusion_key(c, m, metric))


def _diff_key(c: str, row: str, base: str, metric: str) -> str:
    return f"diff.{c}.{row}.vs_{base}.{metric}"


def _verdict_cell(src: page.Sources, c: str, row: str, base: str, metric: str) -> Cell:
    d = src.get(FUSION_FILE, _diff_key(c, row, base, metric))
    v = verdict(d if isinstance(d, dict) else None)
    return Cell(v, title="claimed only when the paired 95 % interval excludes 0")


def _network_rows(src: page.Sources, cfgs: Sequence[str], prefix: str = "dnn[") -> list[str]:
    return [m for m in _fusion_methods(src, cfgs) if m.startswith(prefix)]


def _kld_table(
    src: page.Sources,
    configurations: Mapping[str, tuple[float, float]],
    cfgs: Sequence[str],
    methods: Sequence[str],
    metric: str,
    title: str,
    note: str,
    anchor: str,
    headline: bool,
    paper: bool,
) -> Table:
    """One KLD table: config, r, α, each method's mean, the network − naive difference with its
    interval and verdict (and, for KLD(a), the paper's Fig. 5 ranking)."""
    labels = [FUSION_METHOD_LABELS.get(m, m) for m in methods]
    cols = ["config", "r [m]", "α [deg]", *labels]
    cols += ["network − naive", "95 % CI", "network vs naive (ours)"]
    if paper:
        cols.append("network vs naive (paper, Fig. 5)")
    t = Table(title, cols, note=note, anchor=anchor, headline=headline)
    for c in cfgs:
        row = _config_cells(configurations, c)
        row += [_row_cell(src, c, m, metric) for m in methods]
        dk = _diff_key(c, NET, NAIVE, metric)
        if isinstance(src.get(FUSION_FILE, dk), dict):
            v = verdict(src.get(FUSION_FILE, dk))
            row += [src.cell(FUSION_FILE, f"{dk}.estimate"), _ci_cell(src, dk)]
            row.append(
                Cell(
                    {"lower": "network lower", "higher": "naive lower"}.get(v, v),
                    title="claimed only when the paired 95 % interval excludes 0",
                )
            )
        else:
            row += [Cell(NA), Cell(NA), Cell(NA)]
        if paper:
            w = P.FUSION_KLD_WINNER.get(c)
            row.append(
                Cell({"network": "network lower", "baseline": "naive lower"}.get(w or "", NA))
            )
        t.rows.append(row)
    return t


def fusion_tables(
    src: page.Sources, configurations: Mapping[str, tuple[float, float]]
) -> list[Table]:
    """KLD(b) (headline) and KLD(a) per configuration and method with the network − naive
    difference, intervals per row, paired differences, P/R/Dice, targets, the loss ablation and
    the cross table."""
    cfgs = _fusion_configs(src, configurations)
    methods = _fusion_methods(src, cfgs)
    tables = [
        _kld_table(
            src,
            configurations,
            cfgs,
            methods,
            HEADLINE,
            "Fusion: KLD(b) mean per pose-noise configuration and method (test split; lower is better)",
            "KLD(b): KL(label‖pred) over the full mass vector (m_F, m_O, u), clipped to [1e-7, 1], "
            "averaged over cells, then over test pairs — a divergence of distributions (≥ 0). "
            "network − naive: paired over the same pairs; 'no difference shown' when its interval "
            "contains 0. " + CI_NOTE,
            "fusion-kld",
            headline=True,
            paper=False,
        ),
        _kld_table(
            src,
            configurations,
            cfgs,
            methods,
            "kld_fo_mean",
            "Fusion: KLD(a) mean per configuration and method, for comparison with the paper "
            "(test split)",
            "KLD(a): KL(label‖pred) over (m_F, m_O) only (the definition in the authors' public "
            "code); the two masses do not sum to 1, so it can be negative and rewards "
            "over-confidence. Paper column: which of the two Fig. 5 of van Kempen et al. shows "
            "lower; the paper prints no KLD values. " + CI_NOTE,
            "fusion-kld-a",
            headline=False,
            paper=True,
        ),
    ]
    median = Table(
        "Fusion: KLD(a) median per configuration and method (test split)",
        ["config", "r [m]", "α [deg]", *[FUSION_METHOD_LABELS.get(m, m) for m in methods]],
        note="Median over test pairs (the line in the paper's Fig. 5 boxes).",
        anchor="fusion-kld_fo_median",
    )
    for c in cfgs:
        median.rows.append(
            _config_cells(configurations, c)
            + [_row_cell(src, c, m, "kld_fo_median") for m in methods]
        )
    tables.append(median)

    # every row's intervals
    ci_keys = (
        (HEADLINE, "KLD(b)"),
        ("kld_fo_mean", "KLD(a)"),
        ("dice_occ", "Dice occ"),
        ("dice_free", "Dice free"),
        ("u_mean", "mean u"),
        ("u_auroc", "AUROC(u)"),
    )
    cis = Table(
        "Fusion: estimates with 95 % intervals per configuration and method (test split)",
        ["config", "method", *[x for _, name in ci_keys for x in (name, "95 % CI")]],
        note="Dice pooled over pairs; AUROC(u): u as a detector of wrongly classified label-known "
        "cells. " + CI_NOTE,
        anchor="fusion-ci",
    )
    for c in cfgs:
        for m in methods:
            if not _has(src, c, m):
                continue
            row = [Cell(c), Cell(FUSION_METHOD_LABELS.get(m, m))]
            for k, _ in ci_keys:
                row += [
                    src.cell(FUSION_FILE, fusion_key(c, m, k)),
                    _ci_cell(src, fusion_key(c, m, k)),
                ]
            cis.rows.append(row)
    if cis.rows and any(
        isinstance(src.get(FUSION_FILE, fusion_key(c, m, f"{HEADLINE}_ci")), dict)
        for c in cfgs
        for m in methods
    ):
        tables.append(cis)

    # paired differences against naive and registered
    diffs = Table(
        "Fusion: paired differences (method − baseline) on the same test pairs",
        [
            "config",
            "method",
            "baseline",
            "Δ KLD(b)",
            "95 % CI",
            "KLD(b)",
            "Δ KLD(a)",
            "95 % CI",
            "Δ Dice occ",
            "95 % CI",
            "Dice occ",
        ],
        note="Negative Δ KLD / positive Δ Dice favour the method. 'lower' / 'higher' only when the "
        "interval excludes 0, else 'no difference shown'. " + CI_NOTE,
        anchor="fusion-diff",
    )
    for c in cfgs:
        for m in methods:
            for b in (NAIVE, REG):
                base = f"diff.{c}.{m}.vs_{b}"
                if not isinstance(src.get(FUSION_FILE, base), dict):
                    continue
                row = [Cell(c), Cell(FUSION_METHOD_LABELS.get(m, m)), Cell(b)]
                for k in (HEADLINE, "kld_fo_mean", "dice_occ"):
                    dk = f"{base}.{k}"
                    row += [src.cell(FUSION_FILE, f"{dk}.estimate"), _ci_cell(src, dk)]
                    if k != "kld_fo_mean":
                        row.append(_verdict_cell(src, c, m, b, k))
                diffs.rows.append(row)
    if diffs.rows:
        tables.append(diffs)

    scores = Table(
        "Fusion: precision / recall / Dice per class (test split, pooled over cells; higher is better)",
        [
            "config",
            "method",
            "precision occ",
            "recall occ",
            "Dice occ",
            "Dice occ 95 % CI",
            "precision free",
            "recall free",
            "Dice free",
            "Dice free 95 % CI",
        ],
        note=(
            "A cell is predicted occupied where p_O > 0.5 and free where p_O < 0.5 (docs/design.md; the paper's "
            "sentence swaps the words); only label-known cells count. The paper shows these as Figs. 6 and 7 "
            "without printed values. " + CI_NOTE
        ),
        anchor="fusion-scores",
    )
    for c in cfgs:
        for m in methods:
            if not _has(src, c, m):
                continue
            row = [Cell(c), Cell(FUSION_METHOD_LABELS.get(m, m))]
            for cls in ("occ", "free"):
                row += [
                    src.cell(FUSION_FILE, fusion_key(c, m, f"{k}_{cls}"))
                    for k in ("precision", "recall", "dice")
                ]
                row.append(_ci_cell(src, fusion_key(c, m, f"dice_{cls}")))
            scores.rows.append(row)
    tables.append(scores)

    tables.extend(registration_tables(src, configurations, cfgs))
    targets = target_table(src)
    if targets is not None:
        tables.append(targets)
    ablation = loss_ablation_table(src, cfgs)
    if ablation is not None:
        tables.append(ablation)
    one = per_config_table(src, configurations, cfgs)
    if one is not None:
        tables.append(one)

    cross = lookup(src.metrics.get(FUSION_FILE), "cross")
    if isinstance(cross, dict) and cross:
        nets = sorted(cross)
        tcfgs = sorted({tc for n in nets if isinstance(cross[n], dict) for tc in cross[n]})
        t = Table(
            "Fusion: cross table, KLD(b) mean of the per-configuration networks (the ablation) "
            "trained on one configuration (rows) tested on another (columns)",
            ["network trained on", *[f"test {tc}" for tc in tcfgs]],
            anchor="fusion-cross",
            note="Own configuration: all test pairs; others: a subset "
            "(evaluation.fusion.cross_max_pairs). The one network (row dnn of the KLD table) is "
            "evaluated at every configuration on all pairs.",
        )
        for n in nets:
            t.rows.append(
                [Cell(n)] + [src.cell(FUSION_FILE, f"cross.{n}.{tc}.{HEADLINE}") for tc in tcfgs]
            )
        tables.append(t)
    return tables


def registration_tables(
    src: page.Sources, configurations: Mapping[str, tuple[float, float]], cfgs: Sequence[str]
) -> list[Table]:
    """The registration error table (every row that estimates a pose, per configuration) and the
    success rate per bin of the drawn translation and yaw error."""
    rows = [
        m
        for m in POSE_ROWS
        if any(
            isinstance(src.get(FUSION_FILE, fusion_key(c, m, "success_rate")), (int, float))
            for c in cfgs
        )
    ]
    if not rows:
        return []
    cols = (
        ("success_rate", "success"),
        ("fallback_rate", "fallback"),
        ("residual_trans_m_median", "median Δt [m]"),
        ("residual_trans_m_p90", "p90 Δt [m]"),
        ("residual_rot_deg_median", "median Δψ [deg]"),
        ("residual_rot_deg_p90", "p90 Δψ [deg]"),
    )
    t = Table(
        "Registration: pose error of every method that estimates a pose (test split, same pairs)",
        [
            "config",
            "r [m]",
            "α [deg]",
            "method",
            "success",
            "95 % CI",
            *[name for k, name in cols[1:]],
            "Δ success vs registered",
            "95 % CI",
        ],
        note="Error of the pose used (the estimate, or the noisy pose where the estimate was rejected: "
        "'fallback', counted in the success rate like any other pose) against the simulator's true "
        "relative pose; success = translation error < evaluation.fusion.success_trans_m (0.5 m) and yaw "
        "error < success_rot_deg (1°). Wall time per pair: reports/timings/evaluate_fusion.json "
        "(this run) and benchmarks/registration.py. Δ: paired over the same pairs. " + CI_NOTE,
        anchor="fusion-registration",
        headline=True,
    )
    for c in cfgs:
        for m in rows:
            if not isinstance(src.get(FUSION_FILE, fusion_key(c, m, "success_rate")), (int, float)):
                continue
            row = _config_cells(configurations, c) + [Cell(FUSION_METHOD_LABELS.get(m, m))]
            row += [
                _row_cell(src, c, m, "success_rate"),
                _ci_cell(src, fusion_key(c, m, "success_rate")),
            ]
            row += [_row_cell(src, c, m, k) for k, _ in cols[1:]]
            dk = _diff_key(c, m, REG, "success_rate")
            if isinstance(src.get(FUSION_FILE, dk), dict):
                row += [src.cell(FUSION_FILE, f"{dk}.estimate"), _ci_cell(src, dk)]
            else:
                row += [Cell(NA), Cell(NA)]
            t.rows.append(row)
    out = [t]
    for axis, what in (("translation", "translation"), ("rotation", "yaw")):
        bins = lookup(src.metrics.get(FUSION_FILE), f"bins.{axis}")
        if not isinstance(bins, dict):
            continue
        labels: list[str] = []
        for m in rows:
            for lab in bins.get(m, {}) if isinstance(bins.get(m), dict) else {}:
                if lab not in labels:
                    labels.append(lab)
        if not labels:
            continue
        b = Table(
            f"Registration: success rate per bin of the drawn {what} error (all configurations pooled)",
            ["method", *[f"{lab} (n)" for lab in labels]],
            note=f"Bins of the drawn pose noise's {what} (evaluation.fusion.trans_bins_m / rot_bins_deg), "
            "as in the pose-error bins of the fusion metrics; n = pairs in the bin.",
            anchor=f"fusion-registration-{axis}-bins",
        )
        for m in rows:
            cells = [Cell(FUSION_METHOD_LABELS.get(m, m))]
            for lab in labels:
                key = f"bins.{axis}.{m}.{lab}"
                sr = src.get(FUSION_FILE, f"{key}.success_rate")
                if isinstance(sr, (int, float)):
                    n = src.get(FUSION_FILE, f"{key}.n")
                    count = int(n) if isinstance(n, (int, float)) else "?"
                    cells.append(
                        Cell(
                            f"{fmt_value(sr, 'g4')} ({count})",
                            value=[sr, n],
                            derived=f"metrics/{FUSION_FILE}#{key}.success_rate (n: .n)",
                        )
                    )
                else:
                    cells.append(Cell(NA))
            b.rows.append(cells)
        out.append(b)
    return out


def target_table(src: page.Sources) -> Table | None:
    """The issue's targets (``targets`` of fusion.json): figure, interval, threshold, status per
    configuration (None without a ``targets`` block)."""
    targets = lookup(src.metrics.get(FUSION_FILE), "targets")
    if not isinstance(targets, dict) or not targets:
        return None
    t = Table(
        "Fusion: targets (test split)",
        [
            "target",
            "config",
            "value",
            "95 % CI",
            "needs",
            "threshold",
            "status",
            "CI beyond threshold",
        ],
        note="Status from the point estimate against the threshold ('not evaluated' where the row or "
        "configuration was not evaluated — never a pass); 'CI beyond threshold': the whole interval "
        "lies on the side of the verdict. hybrid_vs_registered needs the KLD(b) difference's interval "
        "below 0 and the Dice occ difference's not wholly below 0. '(ablation <name>)': a target this "
        "run does not evaluate, from that ablation experiment's own evaluation "
        "(reports/ablations/<name>.json).",
        anchor="fusion-targets",
    )
    ablations = [f for f in sorted(src.metrics) if f.startswith("ablations/")]
    for name, spec in targets.items():
        per = spec.get("per_config", {}) if isinstance(spec, dict) else {}
        for c, e in per.items():
            file, key = FUSION_FILE, f"targets.{name}.per_config.{c}"
            status = str(e.get("status", NA))
            if e.get("value") is None:
                # a target this run cannot evaluate (e.g. one_vs_per_config needs the per-config
                # networks): the ablation experiment's verdict, where one was collected
                for f in ablations:
                    found = src.get(f, f"fusion.{key}")
                    if isinstance(found, dict) and found.get("value") is not None:
                        file, key, e = f, f"fusion.{key}", found
                        status = f"{e.get('status', NA)} (ablation {src.get(f, 'name', f)})"
                        break
            value = (
                src.cell(file, f"{key}.value")
                if e.get("value") is not None
                else Cell(NA, title=e.get("why", "not evaluated"))
            )
            beyond = e.get("ci_beyond_threshold")
            t.rows.append(
                [
                    Cell(name, title=str(spec.get("description", ""))),
                    Cell(c),
                    value,
                    _ci_cell(src, key, file),
                    Cell(str(spec.get("op", ""))),
                    src.cell(FUSION_FILE, f"targets.{name}.threshold"),
                    Cell(status),
                    Cell("" if beyond is None else ("yes" if beyond else "no")),
                ]
            )
    return t


def loss_ablation_table(src: page.Sources, cfgs: Sequence[str]) -> Table | None:
    """The network rows ``dnn`` and ``dnn[<loss>]`` side by side at the configurations where a loss
    variant exists (None when there is none)."""
    variants = [v for v in _network_rows(src, cfgs) if not v.startswith(PER_CONFIG_ROW)]
    at = [c for c in cfgs if any(_has(src, c, v) for v in variants)]
    if not at:
        return None
    keys = (
        (HEADLINE, "KLD(b)"),
        ("kld_fo_mean", "KLD(a)"),
        ("dice_occ", "Dice occ"),
        ("dice_free", "Dice free"),
        ("u_mean", "mean u"),
    )
    t = Table(
        "Fusion: loss ablation, the network trained with each loss (test split)",
        [
            "config",
            "network",
            *[x for _, name in keys for x in (name, "95 % CI")],
            "label mean u",
            "AUROC(u)",
            "95 % CI",
        ],
        note="dnn = the default loss (fusion_model.loss.name); dnn[<loss>] = the fusion_variants "
        "networks trained with another loss on the same data. " + CI_NOTE,
        anchor="fusion-loss-ablation",
    )
    for c in at:
        for m in [NET, *variants]:
            if not _has(src, c, m):
                continue
            row = [Cell(c), Cell(m)]
            for k, _ in keys:
                row += [
                    src.cell(FUSION_FILE, fusion_key(c, m, k)),
                    _ci_cell(src, fusion_key(c, m, k)),
                ]
            row.append(src.cell(FUSION_FILE, f"label.{c}.u_mean"))
            row += [
                src.cell(FUSION_FILE, fusion_key(c, m, "u_auroc")),
                _ci_cell(src, fusion_key(c, m, "u_auroc")),
            ]
            t.rows.append(row)
    return t


def _per_config_source(src: page.Sources, cfgs: Sequence[str]) -> tuple[str, str] | None:
    """``(metrics file, key prefix)`` holding the per-configuration networks' rows: this run's
    fusion.json, else an ablation experiment's results (``reports/ablations/<name>.json``, blocks
    under ``fusion.``); None when neither has them."""
    candidates = [(FUSION_FILE, "")] + [
        (f, "fusion.") for f in sorted(src.metrics) if f.startswith("ablations/")
    ]
    for f, prefix in candidates:
        if any(isinstance(src.get(f, f"{prefix}test.{c}.{PER_CONFIG_ROW}"), dict) for c in cfgs):
            return f, prefix
    return None


def per_config_table(
    src: page.Sources, configurations: Mapping[str, tuple[float, float]], cfgs: Sequence[str]
) -> Table | None:
    """The one network against the per-configuration networks (the ablation's ``dnn[per-config]``
    rows): KLD(b) of both and their paired difference per configuration, from this run or from
    the ablation experiment's collected results (None without them)."""
    found = _per_config_source(src, cfgs)
    if found is None:
        return None
    f, prefix = found
    origin = (
        "this run"
        if f == FUSION_FILE
        else f"the ablation experiment {src.get(f, 'experiment', '?')} "
        f"(commit {str(src.get(f, 'commit', '?'))[:8]}, `{f}`; its own evaluation of both networks)"
    )
    t = Table(
        "Fusion: the one network against a network per configuration (test split, same pairs)",
        [
            "config",
            "r [m]",
            "α [deg]",
            "KLD(b) one network",
            "95 % CI",
            "KLD(b) own network",
            "95 % CI",
            "Δ one − own",
            "95 % CI",
        ],
        note="dnn[per-config] = a network trained on that configuration's noise only (the paper's "
        "setting; `make ablations`, the per_config ablation); the one network "
        "is trained on the mixed noise of every configuration. Δ: paired over the same pairs; "
        f"target one_vs_per_config: the interval's upper end <= +0.005. Numbers from {origin}. "
        + CI_NOTE,
        anchor="fusion-one-vs-per-config",
    )

    def ci(key: str) -> Cell:
        b = src.get(f, key)
        if not isinstance(b, dict) or not isinstance(b.get("lo"), (int, float)):
            return Cell(NA)
        return Cell(f"[{fmt_value(b['lo'], 'g4')}, {fmt_value(b['hi'], 'g4')}]")

    for c in cfgs:
        if not isinstance(src.get(f, f"{prefix}test.{c}.{PER_CONFIG_ROW}"), dict):
            continue
        row = _config_cells(configurations, c)
        for m in (NET, PER_CONFIG_ROW):
            k = f"{prefix}{fusion_key(c, m, HEADLINE)}"
            row += [src.cell(f, k), ci(f"{k}_ci")]
        dk = f"{prefix}{_diff_key(c, NET, PER_CONFIG_ROW, HEADLINE)}"
        if isinstance(src.get(f, dk), dict):
            row += [src.cell(f, f"{dk}.estimate"), ci(dk)]
        else:
            row += [Cell(NA), Cell(NA)]
        t.rows.append(row)
    return t


def _captioned(figures: list[page.Figure]) -> list[page.Figure]:
    """Learning-curve figures of stage train_fusion (``train_fusion_<name>.png``) get a caption."""
    out = []
    for f in figures:
        m = LEARNING_CURVE.fullmatch(f.path.rsplit("/", 1)[-1].rsplit(".", 1)[0])
        if m and m.group(1) == "fusion":
            f = replace(
                f,
                caption=f"Learning curves of fusion network {m.group(2)} (training / validation "
                f"loss and validation KLD(b) per epoch) — `{f.path}`",
            )
        elif m:
            f = replace(
                f,
                caption="Learning curves of the learned registration (one model for every pose-noise "
                "level; validation success rate, mean pose errors, training / validation loss per "
                f"epoch) — `{f.path}`",
            )
        out.append(f)
    return out


def training_stops(src: page.Sources) -> list[str]:
    """Where each training of this run stopped and why (its metrics file: ``epochs``,
    ``max_epochs``, ``best_epoch``, ``stopped_early``): one sentence per model. The files'
    ``best_epoch`` is 0-based (Lightning's epoch); the sentences count from 1, like the training
    logs ("best epoch k of n": the k-th of the n epochs run; :class:`traffictwin.trainer.History`)."""
    out = []
    for f in sorted(src.metrics):
        m = re.fullmatch(TRAINING_FILES, f) or re.fullmatch(REGISTRATION_FILES, f)
        data = src.metrics[f] if m else None
        if not isinstance(data, dict) or not isinstance(data.get("epochs"), int):
            continue
        n, cap, best = data["epochs"], data.get("max_epochs"), data.get("best_epoch")
        what = (
            "the learned registration"
            if f.startswith("train_registration")
            else f"fusion network `{m.group(1)}`"
        )
        if data.get("stopped_early"):
            why = f"early stopping ended it after {n} of at most {cap} epochs (its validation metric had stopped improving)"
        elif cap is not None:
            why = f"it ran all {n} of its {cap} epochs (not converged by the early-stopping rule)"
        else:
            why = f"it ran {n} epochs"
        tail = ""
        if isinstance(best, int) and best >= 0:
            tail = f"; best epoch {best + 1} of {n}" + (
                " (in the last 20 % of the epochs run)" if best + 1 > 0.8 * n else ""
            )
        out.append(f"Training of {what}: {why}{tail} (`metrics/{f}`).")
    return out


def section(
    src: page.Sources,
    figures: list[page.Figure],
    configurations: Mapping[str, tuple[float, float]],
) -> page.Section:
    """The fusion results section: the KLD / score / cross tables, the training table, this run's
    findings, the paper's qualitative claims and ``figures``. ``configurations``:
    ``{name: (r m, alpha deg)}`` of this run (empty: the paper's A-D)."""
    sec = page.Section(TITLE)
    sec.paragraphs.append(
        f"Reference: {P.FUSION_CITATION}. Baseline: the second map transformed by the noisy "
        "relative pose, then Dempster's rule (the paper's 'naive fusion')."
    )
    if src.has(FUSION_FILE):
        sec.tables.extend(fusion_tables(src, configurations))
    else:
        sec.paragraphs.append(
            f"`reports/metrics/{FUSION_FILE}` is missing: the fusion evaluation has not run."
        )
    training = files_table(
        src,
        TRAINING_FILES,
        "Fusion: training of the one network and the variants (validation split of their own "
        "training noise; `_naive` = the naive fusion on the same pairs; `stopped_early`: early "
        "stopping ended the run before `max_epochs`, i.e. val KLD(b) had plateaued)",
        "fusion-training",
    )
    if training:
        sec.tables.append(training)
    reg_training = files_table(
        src,
        REGISTRATION_FILES,
        "Learned registration: training of the one model (validation split of the mixed noise; "
        "success = error < 0.5 m and < 1°, before the fallback check; `stopped_early`: early "
        "stopping ended the run, i.e. val/loss had plateaued)",
        "registration-training",
    )
    if reg_training:
        sec.tables.append(reg_training)
    sec.paragraphs.extend(training_stops(src))
    sec.bullet_groups.append(findings_group(src, FUSION_FILE, fusion_findings))
    sec.bullet_groups.append(
        (
            "What the paper reports (qualitatively; it prints no numbers)",
            [f"{c.text} ({c.source})" for c in P.FUSION_CLAIMS.values()],
        )
    )
    sec.figures = _captioned(figures)
    return sec


def headlines(
    metrics: Mapping[str, Any], configurations: Mapping[str, tuple[float, float]]
) -> list[Headline]:
    """Per configuration: the one network (``dnn``) on the configuration's test pairs, KL(label‖pred)
    over ``(m_F, m_O, u)`` (nats per cell, the headline) and occupied-cell Dice, with their
    scenario-bootstrap intervals (keys ``<cfg>.kld``, ``<cfg>.dice``: occupied cells)."""
    out: list[Headline] = []
    for c, (r, a) in configurations.items():
        row = lookup(metrics.get(FUSION_FILE), f"test.{c}.dnn")
        if not isinstance(row, Mapping):
            continue
        where = f"configuration {c} (r = {r:g} m, α = {a:g}°), test pairs"
        out += headline(
            f"{c}.kld",
            "KL(label ‖ network) over (m_F, m_O, u), nats per cell",
            where,
            row.get(f"{HEADLINE}"),
            row.get(f"{HEADLINE}_ci"),
        )
        out += headline(
            f"{c}.dice",
            "Dice of occupied cells, network",
            where,
            row.get("dice_occ"),
            row.get("dice_occ_ci"),
            "pct",
        )
    return out


def provider(configurations: Mapping[str, tuple[float, float]]) -> page.SectionProvider:
    """The fusion section's provider for the report; ``configurations`` as in :func:`section`."""
    return page.SectionProvider(
        name="fusion",
        headlines=partial(headlines, configurations=dict(configurations)),
        section=partial(section, configurations=dict(configurations)),
        figures=FIGURES,
        figure_pattern=FIGURE_PATTERN,
        data_files=DATA_FILES,
        shown_files=f"(?:{TRAINING_FILES})|(?:{REGISTRATION_FILES})",
        replaces=REPLACES,
    )


def zoomed_limits(
    values: np.ndarray, pad: float = 0.15, min_span: float = 0.01, top: float = 1.0
) -> tuple[float, float]:
    """y limits around the finite ``values``: their range widened by ``pad`` of itself on each
    side (at least ``min_span`` in all), never above ``top``; (0, top) without a finite value."""
    v = np.asarray(values, np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return 0.0, top
    lo, hi = float(v.min()), float(v.max())
    margin = max((hi - lo) * pad, (min_span - (hi - lo)) / 2, 0.0)
    upper = min(hi + margin, top)
    return min(lo - margin, upper - min_span), upper


def score_figure(
    scores: pd.DataFrame, configurations: Mapping[str, tuple[float, float]], cls: str
) -> Any:
    """Precision / recall / Dice of ``cls`` cells (``occupied`` / ``free``) per configuration, one
    line per method (colours and markers of :data:`traffictwin.fusion.figures.METHOD_STYLE`), each
    panel's y axis zoomed to its data (:func:`zoomed_limits`); x: the configurations with their
    pose noise r (m) and α (deg). ``scores``: the long table of
    :func:`traffictwin.report.plot_data.fusion_scores_long`. Returns the matplotlib figure."""
    from traffictwin.fusion.figures import CONFIG_AXIS, CONFIG_NOTE, _plt, _style, config_label

    plt = _plt()
    d = scores[scores["class"] == cls]
    cfgs = [c for c in configurations if c in set(d["config"])]
    x = {c: i for i, c in enumerate(cfgs)}
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.9))
    methods = sorted(set(d["method"]), key=lambda m: (m not in ("dnn", "naive"), m))
    for ax, metric in zip(axes, SCORE_METRICS):
        dm = d[(d["metric"] == metric) & d["config"].isin(cfgs)]
        for meth in methods:
            dd = dm[dm["method"] == meth]
            if dd.empty:
                continue
            st = _style(meth)
            ls = "-" if meth in ("dnn", "naive") else "--"
            ax.plot(
                dd["config"].map(x),
                dd["value"],
                ls,
                marker=st["marker"],
                color=st["color"],
                label=st["label"],
                gid=meth,
            )
        ax.set_ylim(*zoomed_limits(dm["value"].to_numpy()))
        ax.set_xticks(range(len(cfgs)))
        ax.set_xticklabels([config_label(c, configurations) for c in cfgs])
        ax.set_xlabel(CONFIG_AXIS, fontsize=9)
        ax.set_ylabel(f"{metric} ({cls} cells)")
        ax.grid(alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    for ax in axes[1:]:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            if lab not in labels:
                handles.append(h)
                labels.append(lab)
    fig.legend(handles, labels, fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 0.95))
    fig.suptitle(
        f"Classification of {cls} cells vs pose-noise configuration (test split)\n{CONFIG_NOTE}",
        fontsize=11,
    )
    fig.tight_layout()
    return fig


def draw_score_figures(
    wide_csv: Path, out_dir: Path, configurations: Mapping[str, tuple[float, float]]
) -> list[Path]:
    """The report stage's score figures: ``<out_dir>/fusion_scores_<occupied|free>_zoomed.png``
    from evaluate_fusion's wide table ``wide_csv`` (``reports/plots/fusion_scores.csv``); none
    when the table is absent (a partial pipeline)."""
    from traffictwin.io.atomic import save_figure
    from traffictwin.report.plot_data import fusion_scores_long

    if not Path(wide_csv).is_file():
        return []
    scores = fusion_scores_long(pd.read_csv(wide_csv))
    out = []
    for cls in ("occupied", "free"):
        fig = score_figure(scores, configurations, cls)
        out.append(save_figure(fig, Path(out_dir) / f"fusion_scores_{cls}_zoomed.png"))
    return out
