"""The fusion part of the report (van Kempen et al.): what the results section says, which
metrics and figures it shows, and the paper's claims beside them.

Reads ``fusion.json`` (stage evaluate_fusion): ``metrics["test"][cfg][method][metric]``, methods
in :data:`FUSION_METHOD_LABELS`; ``metrics["cross"][network cfg][test cfg][metric]`` for networks
evaluated on other configurations; ``train_fusion_<cfg>.json`` (stage train_fusion) and
``fusion_data.json`` (stage generate_fusion). Entry point: :func:`provider`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from functools import partial

from traffictwin.fusion.findings import fusion_findings
from traffictwin.report import model as page
from traffictwin.report import paper_numbers as P
from traffictwin.report.model import NA, Cell, Table, fmt_value, lookup
from traffictwin.report.tables import files_table, findings_group

FUSION_FILE = "fusion.json"
TRAINING_FILES = r"train_fusion_(\w+)\.json"  # one per configuration, shown side by side
TITLE = "Paper 1 — cooperative evidential occupancy-grid fusion"

# The figures the fusion stages write: file stem -> caption, in the order the section shows them.
FIGURES: dict[str, str] = {
    "fusion_data_samples": "Input maps and label of sample pairs from our simulator (cf. the paper's Fig. 2)",
    "fusion_qualitative": "Label, naive fusion and network per configuration (mirrors the paper's Fig. 4)",
    "fusion_kld_boxplot": "KLD distribution over the test set per configuration and method (mirrors Fig. 5)",
    "fusion_scores_occupied": "Precision / recall / Dice of occupied cells per configuration (mirrors Fig. 6)",
    "fusion_scores_free": "Precision / recall / Dice of free cells per configuration (mirrors Fig. 7)",
}
FIGURE_PATTERN = r"fusion|prealign|pose|ogm"
DATA_FILES = (page.DataFile("fusion_data.json", "Fusion data (reports/metrics/fusion_data.json)"),)

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


def fusion_tables(
    src: page.Sources, configurations: Mapping[str, tuple[float, float]]
) -> list[Table]:
    """KLD per configuration and method (+ our ranking vs the paper's Fig. 5), P/R/Dice, cross table."""
    cfgs = _fusion_configs(src, configurations)
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
            headline=head,
        )
        for c in cfgs:
            cells = [src.cell(FUSION_FILE, fusion_key(c, m, metric)) for m in methods]
            row = _config_cells(configurations, c) + cells
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
        "Fusion: training per configuration (validation split; "
        "`_naive` = the naive fusion on the same pairs)",
        "fusion-training",
    )
    if training:
        sec.tables.append(training)
    sec.bullet_groups.append(findings_group(src, FUSION_FILE, fusion_findings))
    sec.bullet_groups.append(
        (
            "What the paper reports (qualitatively; it prints no numbers)",
            [f"{c.text} ({c.source})" for c in P.FUSION_CLAIMS.values()],
        )
    )
    sec.figures = figures
    return sec


def provider(configurations: Mapping[str, tuple[float, float]]) -> page.SectionProvider:
    """The fusion section's provider for the report; ``configurations`` as in :func:`section`."""
    return page.SectionProvider(
        section=partial(section, configurations=dict(configurations)),
        figures=FIGURES,
        figure_pattern=FIGURE_PATTERN,
        data_files=DATA_FILES,
        shown_files=TRAINING_FILES,
    )
