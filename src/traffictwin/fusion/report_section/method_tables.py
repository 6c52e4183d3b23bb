"""The fusion section's tables of every method per configuration: KLD(b) (headline), the KLD(a)
median, every row's intervals, paired differences against naive and registered,
precision / recall / Dice and the cross table; :func:`fusion_tables` adds the registration,
target and ablation tables (:mod:`.pose_tables`, :mod:`.ablation_tables`)."""

from __future__ import annotations

from collections.abc import Sequence

from traffictwin.fusion.findings import verdict
from traffictwin.fusion.report_section.ablation_tables import (
    loss_ablation_table,
    per_config_table,
)
from traffictwin.fusion.report_section.cells import (
    AUROC_COLUMNS,
    AUROC_NOTE,
    CI_NOTE,
    FUSION_FILE,
    HEADLINE,
    NAIVE,
    NET,
    REG,
    Configurations,
    auroc_cells,
    ci_cell,
    config_cells,
    diff_key,
    estimate_ci_cells,
    fusion_configs,
    fusion_key,
    fusion_methods,
    has_row,
    label,
    row_cell,
    value_ci_cells,
    verdict_cell,
)
from traffictwin.fusion.report_section.pose_tables import registration_tables
from traffictwin.report import model as page
from traffictwin.report.model import NA, Cell, Table, lookup

# every row's intervals: (metric key, column name)
CI_COLUMNS = (
    (HEADLINE, "KLD(b)"),
    ("kld_fo_mean", "KLD(a)"),
    ("dice_occ", "Dice occ"),
    ("dice_free", "Dice free"),
    ("u_mean", "mean u"),
)
DIFF_COLUMNS = [
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
]
SCORE_COLUMNS = [
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
]


def _network_vs_naive(src: page.Sources, c: str, metric: str) -> list[Cell]:
    """Network − naive of ``metric`` at ``c``: estimate, interval, verdict (n/a without it)."""
    dk = diff_key(c, NET, NAIVE, metric)
    if not isinstance(src.get(FUSION_FILE, dk), dict):
        return [Cell(NA), Cell(NA), Cell(NA)]
    v = verdict(src.get(FUSION_FILE, dk))
    return [
        *estimate_ci_cells(src, dk),
        Cell(
            {"lower": "network lower", "higher": "naive lower"}.get(v, v),
            title="claimed only when the paired 95 % interval excludes 0",
        ),
    ]


def _kld_table(
    src: page.Sources, configurations: Configurations, cfgs: Sequence[str], methods: Sequence[str]
) -> Table:
    """The headline table: config, r, α, each method's KLD(b) mean, the network − naive difference
    with its interval and verdict (KLD(a): the estimates and paired-difference tables)."""
    cols = ["config", "r [m]", "α [deg]", *[label(m) for m in methods]]
    cols += ["network − naive", "95 % CI", "network vs naive (ours)"]
    t = Table(
        "Fusion: KLD(b) mean per pose-noise configuration and method (test split; lower is better)",
        cols,
        note="KLD(b): KL(label‖pred) over the full mass vector (m_F, m_O, u), clipped to [1e-7, 1], "
        "averaged over cells, then over test pairs — a divergence of distributions (≥ 0). "
        "network − naive: paired over the same pairs; 'no difference shown' when its interval "
        "contains 0. " + CI_NOTE,
        anchor="fusion-kld",
        headline=True,
    )
    for c in cfgs:
        row = config_cells(configurations, c)
        row += [row_cell(src, c, m, HEADLINE) for m in methods]
        t.rows.append(row + _network_vs_naive(src, c, HEADLINE))
    return t


def _median_table(
    src: page.Sources, configurations: Configurations, cfgs: Sequence[str], methods: Sequence[str]
) -> Table:
    median = Table(
        "Fusion: KLD(a) median per configuration and method (test split)",
        ["config", "r [m]", "α [deg]", *[label(m) for m in methods]],
        note="Median over test pairs (the line in the paper's Fig. 5 boxes).",
        anchor="fusion-kld_fo_median",
    )
    for c in cfgs:
        median.rows.append(
            config_cells(configurations, c)
            + [row_cell(src, c, m, "kld_fo_median") for m in methods]
        )
    return median


def _ci_table(src: page.Sources, cfgs: Sequence[str], methods: Sequence[str]) -> Table | None:
    """Every row's estimates with intervals (None when fusion.json has no interval)."""
    cis = Table(
        "Fusion: estimates with 95 % intervals per configuration and method (test split)",
        [
            "config",
            "method",
            *[x for _, name in CI_COLUMNS for x in (name, "95 % CI")],
            *AUROC_COLUMNS,
        ],
        note="Dice pooled over pairs. " + AUROC_NOTE + CI_NOTE,
        anchor="fusion-ci",
    )
    for c in cfgs:
        for m in methods:
            if has_row(src, c, m):
                row = [Cell(c), Cell(label(m))]
                for k, _ in CI_COLUMNS:
                    row += value_ci_cells(src, fusion_key(c, m, k))
                row += auroc_cells(src, c, m)
                cis.rows.append(row)
    has_ci = any(
        isinstance(src.get(FUSION_FILE, fusion_key(c, m, f"{HEADLINE}_ci")), dict)
        for c in cfgs
        for m in methods
    )
    return cis if cis.rows and has_ci else None


def _diff_row(src: page.Sources, c: str, m: str, b: str) -> list[Cell]:
    base = f"diff.{c}.{m}.vs_{b}"
    row = [Cell(c), Cell(label(m)), Cell(b)]
    for k in (HEADLINE, "kld_fo_mean", "dice_occ"):
        row += estimate_ci_cells(src, f"{base}.{k}")
        if k != "kld_fo_mean":
            row.append(verdict_cell(src, c, m, b, k))
    return row


def _diff_table(src: page.Sources, cfgs: Sequence[str], methods: Sequence[str]) -> Table | None:
    """Paired differences against naive and registered (None without any)."""
    diffs = Table(
        "Fusion: paired differences (method − baseline) on the same test pairs",
        DIFF_COLUMNS,
        note="Negative Δ KLD / positive Δ Dice favour the method. 'lower' / 'higher' only when the "
        "interval excludes 0, else 'no difference shown'. " + CI_NOTE,
        anchor="fusion-diff",
    )
    for c in cfgs:
        for m in methods:
            for b in (NAIVE, REG):
                if isinstance(src.get(FUSION_FILE, f"diff.{c}.{m}.vs_{b}"), dict):
                    diffs.rows.append(_diff_row(src, c, m, b))
    return diffs if diffs.rows else None


def _score_table(src: page.Sources, cfgs: Sequence[str], methods: Sequence[str]) -> Table:
    scores = Table(
        "Fusion: precision / recall / Dice per class (test split, pooled over cells; higher is better)",
        SCORE_COLUMNS,
        note=(
            "A cell is predicted occupied where p_O > 0.5 and free where p_O < 0.5 (docs/design.md; the paper's "
            "sentence swaps the words); only label-known cells count. The paper shows these as Figs. 6 and 7 "
            "without printed values. " + CI_NOTE
        ),
        anchor="fusion-scores",
    )
    for c in cfgs:
        for m in methods:
            if not has_row(src, c, m):
                continue
            row = [Cell(c), Cell(label(m))]
            for cls in ("occ", "free"):
                row += [
                    src.cell(FUSION_FILE, fusion_key(c, m, f"{k}_{cls}"))
                    for k in ("precision", "recall", "dice")
                ]
                row.append(ci_cell(src, fusion_key(c, m, f"dice_{cls}")))
            scores.rows.append(row)
    return scores


def _cross_table(src: page.Sources) -> Table | None:
    """KLD(b) of each per-configuration network on the other configurations (None without any)."""
    cross = lookup(src.metrics.get(FUSION_FILE), "cross")
    if not isinstance(cross, dict) or not cross:
        return None
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
    return t


def fusion_tables(src: page.Sources, configurations: Configurations) -> list[Table]:
    """KLD(b) (headline) per configuration and method with the network − naive difference, the
    KLD(a) median, intervals per row, paired differences, P/R/Dice, the loss ablation and the cross
    table (the targets: the index's acceptance table)."""
    cfgs = fusion_configs(src, configurations)
    methods = fusion_methods(src, cfgs)
    tables = [
        _kld_table(src, configurations, cfgs, methods),
        _median_table(src, configurations, cfgs, methods),
    ]
    optional = (_ci_table(src, cfgs, methods), _diff_table(src, cfgs, methods))
    tables += [t for t in optional if t is not None]
    tables.append(_score_table(src, cfgs, methods))
    tables.extend(registration_tables(src, configurations, cfgs))
    optional = (
        loss_ablation_table(src, cfgs),
        per_config_table(src, configurations, cfgs),
        _cross_table(src),
    )
    return tables + [t for t in optional if t is not None]
