"""The fusion part of the report (van Kempen et al.): what the results section says, which
metrics and figures it shows, and the paper's claims beside them.

Reads ``fusion.json`` (stage evaluate_fusion; layout in :mod:`traffictwin.fusion.evaluation`):
``test.<cfg>.<row>.<metric>`` with its 95 % interval ``<metric>_ci``, rows in
:data:`FUSION_METHOD_LABELS` plus the ``fusion_variants`` network rows (``dnn[<loss>]``, …);
``diff.<cfg>.<row>.vs_<base>.<metric>`` (paired differences); ``label.<cfg>.u_mean``;
``cross.dnn-<net>.<cfg>.<metric>`` (its ``targets``: the index's acceptance table,
:mod:`traffictwin.report.acceptance`). Also ``train_fusion_<name>.json`` (stage
train_fusion) and ``fusion_data.json`` (stage generate_fusion), and the learning-curve figures
``figures/train_fusion_<name>.png`` that train_fusion writes (captioned here). Entry point:
:func:`provider`. Tables: :mod:`.method_tables` (every method), :mod:`.pose_tables`
(registration), :mod:`.ablation_tables` (ablations), :mod:`.seed_tables` (the seed
replicates, ``ablations/fusion_seeds.json``), built of the cells of :mod:`.cells`;
the report stage's zoomed score figures: :mod:`.score_figures`.

The headline is KLD(b) ``kld_fou_mean`` (KL over the full mass vector); KLD(a) ``kld_fo_mean``
is kept as a table "for comparison with the paper". An interval cell is *derived* (its
``derived`` names the ``_ci`` key it was read from); a "lower" / "higher" verdict is shown only
when the paired interval of the difference excludes 0.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import replace
from functools import partial
from typing import Any

from traffictwin import paper_numbers as P
from traffictwin.fusion.findings import fusion_findings
from traffictwin.fusion.report_section.cells import FUSION_FILE, FUSION_METHOD_LABELS, HEADLINE
from traffictwin.fusion.report_section.claims import fusion_claims
from traffictwin.fusion.report_section.method_tables import fusion_tables
from traffictwin.fusion.report_section.score_figures import draw_score_figures
from traffictwin.fusion.report_section.seed_tables import (
    seed_findings,
    seed_row_table,
    single_seed_note,
)
from traffictwin.report import model as page
from traffictwin.report.acceptance import POINTER as ACCEPTANCE_POINTER
from traffictwin.report.model import lookup
from traffictwin.report.summary import Baseline, Headline, headline, strongest
from traffictwin.report.tables import files_table, findings_group

__all__ = [
    "FIGURES",
    "TITLE",
    "draw_score_figures",
    "fusion_claims",
    "fusion_tables",
    "headlines",
    "provider",
    "section",
]

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
FIGURE_PATTERN = r"fusion|prealign|pose|ogm|registration"
DATA_FILES = (page.DataFile("fusion_data.json", "Fusion data (reports/metrics/fusion_data.json)"),)
REGISTRATION_FILES = r"train_(registration)\.json"  # the one learned registration
LEARNING_CURVE = re.compile(
    r"train_(fusion|registration)_?(\w*)"
)  # figures/train_fusion_<name>.png (train_fusion and its variants), train_registration.png


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
        sec.paragraphs.append(ACCEPTANCE_POINTER)
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
    note = single_seed_note(src)
    if note:
        sec.paragraphs.append(note)
    else:
        sec.bullet_groups.append(
            (
                "Seed replicates: the findings with training seeds in their intervals",
                seed_findings(src),
            )
        )
        seeds_table = seed_row_table(src)
        if seeds_table:
            sec.tables.append(seeds_table)
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
            baseline=_baseline(metrics, c, HEADLINE, higher_better=False),
        )
        out += headline(
            f"{c}.dice",
            "Dice of occupied cells, network",
            where,
            row.get("dice_occ"),
            row.get("dice_occ_ci"),
            "pct",
            baseline=_baseline(metrics, c, "dice_occ", higher_better=True),
        )
    return out


# the fusion rules without a network or a learned registration: the baselines of the headline
BASELINE_ROWS = ("naive", "naive-yager", "naive-cautious", "registered", "ego")


def _baseline(
    metrics: Mapping[str, Any], c: str, key: str, *, higher_better: bool
) -> Baseline | None:
    """The best of :data:`BASELINE_ROWS` on ``key`` at configuration ``c`` (test pairs)."""
    rows = {
        FUSION_METHOD_LABELS.get(r, r): lookup(metrics.get(FUSION_FILE), f"test.{c}.{r}")
        for r in BASELINE_ROWS
    }
    return strongest(
        {
            label: (row.get(key), row.get(f"{key}_ci"), f"metrics/{FUSION_FILE}#test.{c}.{r}.{key}")
            for (label, row), r in zip(rows.items(), BASELINE_ROWS)
            if isinstance(row, Mapping)
        },
        higher_better=higher_better,
    )


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
        shown_files=f"(?:{TRAINING_FILES})|(?:{REGISTRATION_FILES})",
        replaces=REPLACES,
    )
