"""The fusion section's tables, each number once: KLD(b) per configuration and method (the
headline), every row's estimates and the paired differences with their intervals, the
registration's pose error, and the one network against the per-configuration networks. Cells
(:func:`cell`) read ``fusion.json``: ``test.<cfg>.<row>.<metric>`` with its 95 % interval
``<metric>_ci``, and ``diff.<cfg>.<row>.vs_<base>.<metric>`` (``estimate``, ``lo``, ``hi``); a row
not evaluated at a configuration is ``n/a``. Its other numbers: the report's appendix.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from traffictwin import paper_numbers as P
from traffictwin.fusion.findings import verdict
from traffictwin.report import model as page
from traffictwin.report.model import NA, Cell, Table, fmt_value, interval_cell, json_number, lookup

FUSION_FILE = "fusion.json"
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
    "learned-refined": "learned registration + ECC + Dempster",
    "learned-refined+network": "learned registration + ECC + network",
}
PER_CONFIG_ROW = "dnn[per-config]"  # the ablation's networks trained on one configuration each
POSE_ROWS = ("registered", "learned", "learned-refined")  # rows with their own pose estimate
NET, NAIVE, REG = "dnn", "naive", "registered"
HEADLINE = "kld_fou_mean"
BOOTSTRAP = "cluster-bootstrap"
CI_NOTE = (
    "Brackets: 95 % cluster-bootstrap interval (scenario = pair_id // 1000 resampled; "
    "evaluation.fusion_ci)."
)
Configurations = Mapping[str, tuple[float, float]]  # {name: (r m, alpha deg)}

#: the tables' columns, (key, header) with the keys of :func:`cell` (``{base}``: the baseline of a
#: paired difference)
ESTIMATE_COLUMNS = (
    ("kld_fou_mean_ci", "KLD(b) 95 % CI"),
    ("kld_fo_mean", "KLD(a)"),
    ("kld_fo_mean_ci", "95 % CI"),
    ("dice_occ", "Dice occ"),
    ("dice_occ_ci", "95 % CI"),
    ("dice_free", "Dice free"),
    ("dice_free_ci", "95 % CI"),
    ("u_mean", "mean u"),
    ("u_mean_ci", "95 % CI"),
)
DIFF_COLUMNS = (
    (f"vs_{{base}}.{HEADLINE}", "Δ KLD(b)"),
    (f"vs_{{base}}.{HEADLINE}_ci", "95 % CI"),
    (f"vs_{{base}}.{HEADLINE}_verdict", "KLD(b) verdict"),
    ("vs_{base}.kld_fo_mean", "Δ KLD(a)"),
    ("vs_{base}.kld_fo_mean_ci", "95 % CI"),
    ("vs_{base}.dice_occ", "Δ Dice occ"),
    ("vs_{base}.dice_occ_ci", "95 % CI"),
    ("vs_{base}.dice_occ_verdict", "Dice occ verdict"),
)
POSE_COLUMNS = (
    ("success_rate", "success"),
    ("success_rate_ci", "95 % CI"),
    ("fallback_rate", "fallback"),
    ("residual_trans_m_median", "median Δt [m]"),
    ("residual_trans_m_p90", "p90 Δt [m]"),
    ("residual_rot_deg_median", "median Δψ [deg]"),
    ("residual_rot_deg_p90", "p90 Δψ [deg]"),
    (f"vs_{REG}.success_rate", "Δ success vs registered"),
    (f"vs_{REG}.success_rate_ci", "95 % CI"),
)


def label(m: str) -> str:
    """The table label of an evaluation row (the row itself where it has none)."""
    return FUSION_METHOD_LABELS.get(m, m)


def fusion_configs(src: page.Sources, configurations: Configurations) -> list[str]:
    """The evaluated configurations: this run's (or the paper's) order, then any others."""
    test = lookup(src.metrics.get(FUSION_FILE), "test")
    present = sorted(test) if isinstance(test, dict) else []
    wanted = list(configurations) or list(P.FUSION_CONFIGURATIONS)
    return [c for c in wanted if c in present] + [c for c in present if c not in wanted]


def fusion_methods(src: page.Sources, cfgs: Sequence[str]) -> list[str]:
    """Every evaluated row, in the order of :data:`FUSION_METHOD_LABELS`, then by name."""
    found: list[str] = []
    for c in cfgs:
        d = src.get(FUSION_FILE, f"test.{c}")
        found += [m for m in d if m not in found] if isinstance(d, dict) else []
    order = list(FUSION_METHOD_LABELS)
    return sorted(found, key=lambda m: (order.index(m) if m in order else len(order), m))


def cell(src: page.Sources, c: str, m: str, key: str) -> Cell:
    """Row ``m`` at configuration ``c``: ``<metric>`` (``test.<c>.<m>.<metric>``), ``<metric>_ci``
    (its interval), ``vs_<base>.<metric>`` / ``vs_<base>.<metric>_ci`` /
    ``vs_<base>.<metric>_verdict`` (the paired difference ``m − base``: estimate / interval /
    :func:`~traffictwin.fusion.findings.verdict`). ``n/a`` for a row or difference not evaluated
    at ``c``."""
    metric = key.removesuffix("_ci").removesuffix("_verdict")
    if key.startswith("vs_"):
        base = f"diff.{c}.{m}.{metric}"
        if not isinstance(d := src.get(FUSION_FILE, base), dict):
            return Cell(NA, title=f"no paired difference {m} {metric} at configuration {c}")
        if key.endswith("_verdict"):
            return Cell(verdict(d), title="claimed only when the paired 95 % interval excludes 0")
        if key.endswith("_ci"):
            return interval_cell(src, FUSION_FILE, base, BOOTSTRAP)
        return src.cell(FUSION_FILE, f"{base}.estimate")
    if not isinstance(src.get(FUSION_FILE, f"test.{c}.{m}"), dict):
        return Cell(NA, title=f"{m} not evaluated at configuration {c}")
    if key.endswith("_ci"):
        return interval_cell(src, FUSION_FILE, f"test.{c}.{m}.{metric}", BOOTSTRAP)
    return src.cell(FUSION_FILE, f"test.{c}.{m}.{key}")


def _has(src: page.Sources, key: str) -> bool:
    """fusion.json has a row or a number (not null) at ``key``."""
    v = src.get(FUSION_FILE, key)
    return isinstance(v, dict) or json_number(v) is not None


def row_table(
    src: page.Sources,
    rows: Sequence[tuple[str, ...]],
    columns: Sequence[tuple[str, str]],
    lead: Sequence[str] = ("config", "method"),
    **table: Any,
) -> Table:
    """One table row per ``(config, row)`` or ``(config, row, baseline)`` of ``rows``: their
    labels (headers ``lead``), then ``columns`` (``(key, header)``, cells of :func:`cell`, with
    ``{base}`` in a key the row's baseline); ``table``: :class:`Table`'s other fields."""
    t = Table(columns=[*lead, *(h for _, h in columns)], **table)
    for c, m, *base in rows:
        keys = [k.format(base=base[0] if base else "") for k, _ in columns]
        labels = [Cell(c), Cell(label(m)), *map(Cell, base)]
        t.rows.append(labels + [cell(src, c, m, k) for k in keys])
    return t


def _kld_table(
    src: page.Sources, configurations: Configurations, cfgs: Sequence[str], methods: Sequence[str]
) -> Table:
    """The headline: config, r [m], α [deg] (this run's, else the paper's), each method's KLD(b)."""
    t = Table(
        "Fusion: KLD(b) mean per pose-noise configuration and method (test split; lower is better)",
        ["config", "r [m]", "α [deg]", *[label(m) for m in methods]],
        note="KLD(b): KL(label‖pred) over the full mass vector (m_F, m_O, u), clipped to [1e-7, 1], "
        "averaged over cells, then over test pairs — a divergence of distributions (≥ 0). Its "
        "intervals: the estimates table; network − naive: the paired differences.",
        anchor="fusion-kld",
        headline=True,
    )
    conf = configurations or P.FUSION_CONFIGURATIONS
    for c in cfgs:
        base = (
            f"params#configurations.{c}"
            if c in configurations
            else f"paper:FUSION_CONFIGURATIONS.{c}"
        )
        geometry = [
            Cell(fmt_value(v, "g4"), src=f"{base}.{k}", value=v, fmt="g4")
            for k, v in zip(("r", "alpha"), conf.get(c, (float("nan"), float("nan"))))
        ]
        t.rows.append([Cell(c), *geometry, *[cell(src, c, m, HEADLINE) for m in methods]])
    return t


def _diff_rows(src: page.Sources, cfgs: Sequence[str], methods: Sequence[str]) -> list[tuple]:
    """``(config, row, baseline)`` of every paired difference against naive and registered;
    naive − registered (registered − naive with the signs turned) only without the latter."""
    return [
        (c, m, b)
        for c in cfgs
        for m in methods
        for b in (NAIVE, REG)
        if isinstance(src.get(FUSION_FILE, f"diff.{c}.{m}.vs_{b}"), dict)
        and not ((m, b) == (NAIVE, REG) and _has(src, f"diff.{c}.{REG}.vs_{NAIVE}"))
    ]


def per_config_table(src: page.Sources, cfgs: Sequence[str]) -> Table | None:
    """The one network against the per-configuration networks (``dnn[per-config]``): KLD(b) of
    both and their paired difference, from this run's fusion.json or else an ablation
    experiment's results (``ablations/<name>.json``, blocks under ``fusion.``); None without them."""
    candidates = [(FUSION_FILE, "")] + [
        (f, "fusion.") for f in sorted(src.metrics) if f.startswith("ablations/")
    ]
    has = (
        (f, pre)
        for f, pre in candidates
        if any(isinstance(src.get(f, f"{pre}test.{c}.{PER_CONFIG_ROW}"), dict) for c in cfgs)
    )
    if (found := next(has, None)) is None:
        return None
    f, pre = found
    origin = (
        "this run"
        if f == FUSION_FILE
        else f"`reports/{src.paths.get(f, f)}` (the ablation's own evaluation of both networks; its experiment and commit: the appendix)"
    )
    t = Table(
        "Fusion: KLD(b) of the one network against a network per configuration (test split, same pairs)",
        ["config"]
        + [h for n in ("one network", "own network", "Δ one − own") for h in (n, "95 % CI")],
        note="dnn[per-config] = a network trained on that configuration's noise only (the paper's "
        "setting; `make ablations`, the per_config ablation); the one network is trained on the "
        "mixed noise of every configuration. Δ: paired over the same pairs; its target "
        f"one_vs_per_config: the acceptance table at the end of the index. Numbers from {origin}. "
        + CI_NOTE,
        anchor="fusion-one-vs-per-config",
    )
    for c in cfgs:
        if isinstance(src.get(f, f"{pre}test.{c}.{PER_CONFIG_ROW}"), dict):
            keys = [f"{pre}test.{c}.{m}.{HEADLINE}" for m in (NET, PER_CONFIG_ROW)]
            dk = f"{pre}diff.{c}.{NET}.vs_{PER_CONFIG_ROW}.{HEADLINE}"
            cells = [x for k in keys for x in (src.cell(f, k), interval_cell(src, f, k, BOOTSTRAP))]
            cells += [src.cell(f, f"{dk}.estimate"), interval_cell(src, f, dk, BOOTSTRAP)]
            t.rows.append([Cell(c), *cells])
    return t


def fusion_tables(src: page.Sources, configurations: Configurations) -> list[Table]:
    """KLD(b) per configuration and method (the headline), every row's estimates with their
    intervals, the paired differences, the registration's pose error and the one network against
    the per-configuration networks (the targets: the index's acceptance table)."""
    cfgs = fusion_configs(src, configurations)
    methods = fusion_methods(src, cfgs)
    rows = [(c, m) for c in cfgs for m in methods if _has(src, f"test.{c}.{m}")]
    pose = [(c, m) for c, m in rows if m in POSE_ROWS and _has(src, f"test.{c}.{m}.success_rate")]
    tables = [
        _kld_table(src, configurations, cfgs, methods),
        row_table(
            src,
            rows,
            ESTIMATE_COLUMNS,
            title="Fusion: estimates with 95 % intervals per configuration and method (test split)",
            note="KLD(b) means: the KLD table; KLD(a) over (m_F, m_O) only, for comparison with "
            "the paper. Dice over label-known cells, pooled; a cell is predicted occupied where "
            "p_O > 0.5 and free where p_O < 0.5 (docs/design.md; the paper's sentence swaps the "
            "words). Precision and recall (the paper's Figs. 6 and 7): the score figures; they, "
            "AUROC(u) and the KLD(a) median of every row: the appendix (the network's AUROC(u): "
            "the findings). The dnn[<loss>] rows: the fusion_variants networks, trained with "
            "another loss on the same data. " + CI_NOTE,
            anchor="fusion-ci",
        ),
        row_table(
            src,
            _diff_rows(src, cfgs, methods),
            DIFF_COLUMNS,
            ("config", "method", "baseline"),
            title="Fusion: paired differences (method − baseline) on the same test pairs",
            note="Negative Δ KLD / positive Δ Dice favour the method. 'lower' / 'higher' only "
            "when the interval excludes 0, else 'no difference shown'. naive − registered is "
            "registered − naive with the signs turned: one row. " + CI_NOTE,
            anchor="fusion-diff",
        ),
        row_table(
            src,
            pose,
            POSE_COLUMNS,
            headline=True,
            title="Registration: pose error of every method that estimates a pose (test split, same pairs)",
            note="Error of the pose used (the estimate, or the noisy pose where the estimate was "
            "rejected: 'fallback', counted in the success rate like any other pose) against the "
            "simulator's true relative pose; success = translation error <= "
            "evaluation.fusion.success_trans_m (m) and yaw error <= "
            "evaluation.fusion.success_rot_deg (deg). Wall time per pair: "
            "reports/timings/evaluate_fusion.json (this run) and benchmarks/registration.py. Δ: "
            "paired over the same pairs. " + CI_NOTE,
            anchor="fusion-registration",
        ),
    ]
    optional = per_config_table(src, cfgs)
    return [t for t in tables + ([optional] if optional else []) if t.rows]
