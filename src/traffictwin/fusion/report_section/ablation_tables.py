"""The fusion section's ablation tables: the loss ablation (``dnn`` beside ``dnn[<loss>]``) and
the one network against the per-configuration networks (this run's, or an ablation experiment's
collected results). The targets' verdicts are in the report index's acceptance table
(:mod:`traffictwin.report.acceptance`)."""

from __future__ import annotations

from collections.abc import Sequence

from traffictwin.fusion.report_section.cells import (
    AUROC_COLUMNS,
    AUROC_NOTE,
    CI_NOTE,
    FUSION_FILE,
    HEADLINE,
    NET,
    PER_CONFIG_ROW,
    Configurations,
    auroc_cells,
    config_cells,
    diff_key,
    fusion_key,
    has_row,
    network_rows,
    value_ci_cells,
)
from traffictwin.report import model as page
from traffictwin.report.model import NA, Cell, Table, fmt_value

# the loss ablation's columns with intervals: (metric key, column name)
ABLATION_COLUMNS = (
    (HEADLINE, "KLD(b)"),
    ("kld_fo_mean", "KLD(a)"),
    ("dice_occ", "Dice occ"),
    ("dice_free", "Dice free"),
    ("u_mean", "mean u"),
)


def loss_ablation_table(src: page.Sources, cfgs: Sequence[str]) -> Table | None:
    """The network rows ``dnn`` and ``dnn[<loss>]`` side by side at the configurations where a loss
    variant exists (None when there is none)."""
    variants = [v for v in network_rows(src, cfgs) if not v.startswith(PER_CONFIG_ROW)]
    at = [c for c in cfgs if any(has_row(src, c, v) for v in variants)]
    if not at:
        return None
    t = Table(
        "Fusion: loss ablation, the network trained with each loss (test split)",
        [
            "config",
            "network",
            *[x for _, name in ABLATION_COLUMNS for x in (name, "95 % CI")],
            "label mean u",
            *AUROC_COLUMNS,
        ],
        note="dnn = the default loss (fusion_model.loss.name); dnn[<loss>] = the fusion_variants "
        "networks trained with another loss on the same data. " + AUROC_NOTE + CI_NOTE,
        anchor="fusion-loss-ablation",
    )
    for c in at:
        for m in [NET, *variants]:
            if not has_row(src, c, m):
                continue
            row = [Cell(c), Cell(m)]
            for k, _ in ABLATION_COLUMNS:
                row += value_ci_cells(src, fusion_key(c, m, k))
            row.append(src.cell(FUSION_FILE, f"label.{c}.u_mean"))
            row += auroc_cells(src, c, m)
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


def _plain_ci(src: page.Sources, f: str, key: str) -> Cell:
    """``[lo, hi]`` of the interval at ``key`` of file ``f`` (n/a without one)."""
    b = src.get(f, key)
    if not isinstance(b, dict) or not isinstance(b.get("lo"), (int, float)):
        return Cell(NA)
    return Cell(f"[{fmt_value(b['lo'], 'g4')}, {fmt_value(b['hi'], 'g4')}]")


def _per_config_row(
    src: page.Sources, configurations: Configurations, f: str, prefix: str, c: str
) -> list[Cell]:
    """KLD(b) of the one and the own network at ``c`` and their paired difference."""
    row = config_cells(configurations, c)
    for m in (NET, PER_CONFIG_ROW):
        k = f"{prefix}{fusion_key(c, m, HEADLINE)}"
        row += [src.cell(f, k), _plain_ci(src, f, f"{k}_ci")]
    dk = f"{prefix}{diff_key(c, NET, PER_CONFIG_ROW, HEADLINE)}"
    if isinstance(src.get(f, dk), dict):
        row += [src.cell(f, f"{dk}.estimate"), _plain_ci(src, f, dk)]
    else:
        row += [Cell(NA), Cell(NA)]
    return row


def _upper_limit(src: page.Sources) -> str:
    """``<= <threshold>`` of target one_vs_per_config as fusion.json has it (n/a without)."""
    thr = src.get(FUSION_FILE, "targets.one_vs_per_config.threshold")
    op = src.get(FUSION_FILE, "targets.one_vs_per_config.op") or "<="
    return f"{op} {fmt_value(thr, 'g4')}" if isinstance(thr, (int, float)) else f"{op} {NA}"


def per_config_table(
    src: page.Sources, configurations: Configurations, cfgs: Sequence[str]
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
        f"target one_vs_per_config: the interval's upper end {_upper_limit(src)} (the acceptance "
        f"table at the end of the index). Numbers from {origin}. " + CI_NOTE,
        anchor="fusion-one-vs-per-config",
    )
    for c in cfgs:
        if isinstance(src.get(f, f"{prefix}test.{c}.{PER_CONFIG_ROW}"), dict):
            t.rows.append(_per_config_row(src, configurations, f, prefix, c))
    return t
