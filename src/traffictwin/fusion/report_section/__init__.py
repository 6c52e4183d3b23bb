"""The fusion part of the report (van Kempen et al.), entry point :func:`provider`: the section
(tables of ``fusion.json``: :mod:`.tables`; seed replicates: :mod:`.seed_tables`), the headline
numbers and the paper's claims (:mod:`.claims`). The targets: the index's acceptance table; every other number: the
appendix. The headline is KLD(b) ``kld_fou_mean`` (KL over the full mass vector, nats per cell).
"""

from __future__ import annotations

from collections.abc import Mapping
from functools import partial
from typing import Any

from traffictwin import paper_numbers as P
from traffictwin.fusion.findings import fusion_findings
from traffictwin.fusion.report_section.claims import fusion_claims
from traffictwin.fusion.report_section.seed_tables import (
    seed_diff_table,
    seed_row_table,
    single_seed_note,
)
from traffictwin.fusion.report_section.tables import FUSION_FILE, HEADLINE, fusion_tables, label
from traffictwin.report import model as page
from traffictwin.report.acceptance import POINTER as ACCEPTANCE_POINTER
from traffictwin.report.model import lookup
from traffictwin.report.summary import Baseline, Headline, headline, strongest
from traffictwin.report.tables import findings_group

TITLE = "Paper 1 — cooperative evidential occupancy-grid fusion"

# The figures the fusion stages write: file stem -> caption, in the order the section shows them.
FIGURES: dict[str, str] = {
    "fusion_data_samples": "Input maps and label of sample pairs from our simulator (cf. the paper's Fig. 2)",
    "fusion_qualitative": "Label, naive fusion and network per configuration (mirrors the paper's Fig. 4)",
    "fusion_kld_boxplot": "KLD(b) distribution over the test set per configuration and method (cf. Fig. 5, which shows KLD(a))",
    "fusion_scores_occupied": "Precision / recall / Dice of occupied cells per configuration, each "
    "panel's score axis zoomed to its data (mirrors Fig. 6)",
    "fusion_scores_free": "Precision / recall / Dice of free cells per configuration, each panel's "
    "score axis zoomed to its data (mirrors Fig. 7)",
    "train_fusion_network": "Learning curves of the fusion network (training / validation loss and "
    "validation KLD(b) per epoch)",
    "train_registration": "Learning curves of the learned registration (one model for every "
    "pose-noise level; validation success rate, mean pose errors, training / validation loss per "
    "epoch)",
}
# the other images of the fusion stages (a loss variant's learning curves train_fusion_<name>)
FIGURE_PATTERN = r"fusion|prealign|pose|ogm|registration"
DATA_FILES = (page.DataFile("fusion_data.json", "Fusion data (reports/metrics/fusion_data.json)"),)


def section(
    src: page.Sources,
    figures: list[page.Figure],
    configurations: Mapping[str, tuple[float, float]],
) -> page.Section:
    """The fusion results section: the tables of :func:`fusion_tables`, this run's findings, the
    seed replicates and ``figures``. ``configurations``: ``{name: (r m, alpha deg)}`` of this run
    (empty: the paper's A-D). The paper's claims: the index's verdict table."""
    sec = page.Section(TITLE, figures=figures)
    sec.paragraphs.append(
        f"Reference: {P.FUSION_CITATION}. Baseline: the second map transformed by the noisy "
        "relative pose, then Dempster's rule (the paper's 'naive fusion')."
    )
    if src.has(FUSION_FILE):
        sec.paragraphs.append(ACCEPTANCE_POINTER)
        sec.tables.extend(fusion_tables(src, configurations))
    else:
        sec.paragraphs.append(
            f"`reports/metrics/{FUSION_FILE}` is missing: the fusion evaluation has not run."
        )
    sec.bullet_groups.append(findings_group(src, FUSION_FILE, fusion_findings))
    if note := single_seed_note(src):
        sec.paragraphs.append(note)
    sec.tables += [t for t in (seed_diff_table(src), seed_row_table(src)) if t]
    return sec


def headlines(
    metrics: Mapping[str, Any], configurations: Mapping[str, tuple[float, float]]
) -> list[Headline]:
    """Per configuration: the one network's KLD(b) and occupied Dice on its test pairs with their
    intervals (keys ``<cfg>.kld``, ``<cfg>.dice``) beside the strongest baseline's."""
    out: list[Headline] = []
    for c, (r, a) in configurations.items():
        row = lookup(metrics.get(FUSION_FILE), f"test.{c}.dnn")
        if not isinstance(row, Mapping):
            continue
        where = f"configuration {c} (r = {r:g} m, α = {a:g}°), test pairs"
        for key, name, what, fmt, higher in (
            (HEADLINE, "kld", "KL(label ‖ network) over (m_F, m_O, u), nats per cell", "g4", False),
            ("dice_occ", "dice", "Dice of occupied cells, network", "pct", True),
        ):
            base = _baseline(metrics, c, key, higher_better=higher)
            out += headline(
                f"{c}.{name}", what, where, row.get(key), row.get(f"{key}_ci"), fmt, baseline=base
            )
    return out


# the fusion rules without a network or a learned registration: the baselines of the headline
BASELINE_ROWS = ("naive", "naive-yager", "naive-cautious", "registered", "ego")


def _baseline(
    metrics: Mapping[str, Any], c: str, key: str, *, higher_better: bool
) -> Baseline | None:
    """The best of :data:`BASELINE_ROWS` on ``key`` at configuration ``c`` (test pairs)."""
    found = {}
    for r in BASELINE_ROWS:
        row = lookup(metrics.get(FUSION_FILE), f"test.{c}.{r}")
        if isinstance(row, Mapping):
            source = f"metrics/{FUSION_FILE}#test.{c}.{r}.{key}"
            found[label(r)] = (row.get(key), row.get(f"{key}_ci"), source)
    return strongest(found, higher_better=higher_better)


def provider(configurations: Mapping[str, tuple[float, float]]) -> page.SectionProvider:
    """The fusion section's provider for the report; ``configurations`` as in :func:`section`."""
    return page.SectionProvider(
        name="fusion",
        headlines=partial(headlines, configurations=dict(configurations)),
        claims=fusion_claims,
        section=partial(section, configurations=dict(configurations)),
        figures=FIGURES,
        figure_pattern=FIGURE_PATTERN,
        data_files=DATA_FILES,
    )
