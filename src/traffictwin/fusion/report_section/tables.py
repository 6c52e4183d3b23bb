"""The fusion section's tables, each number once: KLD(b) per configuration and method (the
headline), every row's estimates and the paired differences with their intervals, the
registration's pose error, and the one network against the per-configuration networks.

Every table is a list of column specs ``(header, key)`` built by :func:`spec_table`: ``key`` a
path in ``fusion.json`` (``test.<cfg>.<row>.<metric>``, ``diff.<cfg>.<row>.vs_<base>.<metric>``)
with ``{c}`` the configuration, ``{m}`` the row, ``{b}`` the baseline and ``{p}`` the prefix of an
ablation's file; :func:`cell` reads it. A row not evaluated at a configuration is ``n/a``. Its
other numbers: the report's appendix.
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
CI = "95 % CI"
CI_NOTE = (
    "Brackets: 95 % cluster-bootstrap interval (scenario = pair_id // 1000 resampled; "
    "evaluation.fusion_ci)."
)
Configurations = Mapping[str, tuple[float, float]]  # {name: (r m, alpha deg)}
T, D = "{p}test.{c}.{m}.", "{p}diff.{c}.{m}.vs_{b}."  # a row's estimates, its paired differences


def with_ci(header: str, key: str) -> list[tuple[str, str]]:
    """The column specs of ``key`` and of its interval."""
    return [(header, key), (CI, f"{key}_ci")]


ESTIMATE_COLUMNS = [
    ("KLD(b) 95 % CI", f"{T}{HEADLINE}_ci"),
    *with_ci("KLD(a)", f"{T}kld_fo_mean"),
    *with_ci("Dice occ", f"{T}dice_occ"),
    *with_ci("Dice free", f"{T}dice_free"),
    *with_ci("mean u", f"{T}u_mean"),
]
DIFF_COLUMNS = [
    *with_ci("Δ KLD(b)", f"{D}{HEADLINE}"),
    ("KLD(b) verdict", f"{D}{HEADLINE}_verdict"),
    *with_ci("Δ KLD(a)", f"{D}kld_fo_mean"),
    *with_ci("Δ Dice occ", f"{D}dice_occ"),
    ("Dice occ verdict", f"{D}dice_occ_verdict"),
]
POSE_COLUMNS = [
    *with_ci("success", f"{T}success_rate"),
    ("fallback", f"{T}fallback_rate"),
    ("median Δt [m]", f"{T}residual_trans_m_median"),
    ("p90 Δt [m]", f"{T}residual_trans_m_p90"),
    ("median Δψ [deg]", f"{T}residual_rot_deg_median"),
    ("p90 Δψ [deg]", f"{T}residual_rot_deg_p90"),
    *with_ci("Δ success vs registered", f"{D.replace('{b}', REG)}success_rate"),
]
PER_CONFIG_COLUMNS = [
    *with_ci("one network", f"{T}{HEADLINE}"),
    *with_ci("own network", f"{{p}}test.{{c}}.{{b}}.{HEADLINE}"),
    *with_ci("Δ one − own", f"{D}{HEADLINE}"),
]


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
    found = {m for c in cfgs if isinstance(d := src.get(FUSION_FILE, f"test.{c}"), dict) for m in d}
    order = list(FUSION_METHOD_LABELS)
    return sorted(found, key=lambda m: (order.index(m) if m in order else len(order), m))


def cell(src: page.Sources, key: str, file: str = FUSION_FILE) -> Cell:
    """The cell of ``key`` in ``file``: the number at ``key`` (a paired difference's
    ``estimate``), its interval where ``key`` ends in ``_ci``, the interval rule's verdict
    (:func:`~traffictwin.fusion.findings.verdict`) where it ends in ``_verdict``; ``n/a`` where
    the row or difference it belongs to was not evaluated."""
    path = key.removesuffix("_ci").removesuffix("_verdict")
    row = path.rsplit(".", 1)[0]
    if not isinstance(src.get(file, row), dict):
        return Cell(NA, title=f"not evaluated: {row}")
    value = src.get(file, path)
    if key.endswith("_verdict"):
        d = value if isinstance(value, dict) else None
        return Cell(verdict(d), title="claimed only when the paired 95 % interval excludes 0")
    if key.endswith("_ci"):
        return interval_cell(src, file, path, BOOTSTRAP)
    return src.cell(file, f"{path}.estimate" if isinstance(value, dict) else path)


def spec_table(
    src: page.Sources,
    rows: Sequence[tuple[Sequence[Cell], Mapping[str, str]]],
    columns: Sequence[tuple[str, str]],
    lead: Sequence[str] = ("config", "method"),
    file: str = FUSION_FILE,
    **table: Any,
) -> Table:
    """One table row per ``(labels, names)`` of ``rows``: its label cells (headers ``lead``),
    then per column spec ``(header, key)`` the :func:`cell` of ``key`` filled with ``names``
    (``c``, ``m``, ``b``, ``p``; empty where not given); ``table``: :class:`Table`'s other fields."""
    t = Table(columns=[*lead, *(h for h, _ in columns)], **table)
    for labels, names in rows:
        fill = {"c": "", "m": "", "b": "", "p": "", **names}
        t.rows.append([*labels, *(cell(src, k.format(**fill), file) for _, k in columns)])
    return t


def _has(src: page.Sources, key: str) -> bool:
    """fusion.json has a row or a number (not null) at ``key``."""
    v = src.get(FUSION_FILE, key)
    return isinstance(v, dict) or json_number(v) is not None


def _geometry(c: str, configurations: Configurations) -> list[Cell]:
    """r [m] and α [deg] of configuration ``c``: this run's, else the paper's."""
    ours = c in configurations
    base = f"params#configurations.{c}" if ours else f"paper:FUSION_CONFIGURATIONS.{c}"
    values = (configurations if ours else P.FUSION_CONFIGURATIONS).get(c, (float("nan"),) * 2)
    return [
        Cell(fmt_value(v, "g4"), src=f"{base}.{k}", value=v, fmt="g4")
        for k, v in zip(("r", "alpha"), values)
    ]


def per_config_table(src: page.Sources, cfgs: Sequence[str]) -> Table | None:
    """The one network against the per-configuration networks (``dnn[per-config]``): KLD(b) of
    both and their paired difference, from this run's fusion.json or else an ablation
    experiment's results (``ablations/<name>.json``, blocks under ``fusion.``); None without them."""
    candidates = [(FUSION_FILE, "")] + [
        (f, "fusion.") for f in sorted(src.metrics) if f.startswith("ablations/")
    ]
    found = [
        (f, p, [c for c in cfgs if isinstance(src.get(f, f"{p}test.{c}.{PER_CONFIG_ROW}"), dict)])
        for f, p in candidates
    ]
    f, p, have = next((x for x in found if x[2]), (None, "", []))
    if f is None:
        return None
    origin = (
        "this run"
        if f == FUSION_FILE
        else f"`reports/{src.paths.get(f, f)}` (the ablation's own evaluation of both networks; its experiment and commit: the appendix)"
    )
    names = {"m": NET, "b": PER_CONFIG_ROW, "p": p}
    return spec_table(
        src,
        [([Cell(c)], {"c": c, **names}) for c in have],
        PER_CONFIG_COLUMNS,
        ("config",),
        f,
        title="Fusion: KLD(b) of the one network against a network per configuration (test split, same pairs)",
        note="dnn[per-config] = a network trained on that configuration's noise only (the paper's "
        "setting; `make ablations`, the per_config ablation); the one network is trained on the "
        "mixed noise of every configuration. Δ: paired over the same pairs; its target "
        f"one_vs_per_config: the acceptance table at the end of the index. Numbers from {origin}. "
        + CI_NOTE,
        anchor="fusion-one-vs-per-config",
    )


def fusion_tables(src: page.Sources, configurations: Configurations) -> list[Table]:
    """KLD(b) per configuration and method (the headline), every row's estimates with their
    intervals, the paired differences against naive and registered (naive − registered only
    without registered − naive), the registration's pose error and the one network against the
    per-configuration networks (the targets: the index's acceptance table)."""
    cfgs = fusion_configs(src, configurations)
    methods = fusion_methods(src, cfgs)
    rows = [(c, m) for c in cfgs for m in methods if _has(src, f"test.{c}.{m}")]
    pose = [(c, m) for c, m in rows if m in POSE_ROWS and _has(src, f"test.{c}.{m}.success_rate")]
    diffs = [
        (c, m, b)
        for c, m in rows
        for b in (NAIVE, REG)
        if isinstance(src.get(FUSION_FILE, f"diff.{c}.{m}.vs_{b}"), dict)
        and not ((m, b) == (NAIVE, REG) and _has(src, f"diff.{c}.{REG}.vs_{NAIVE}"))
    ]
    tables = [
        spec_table(
            src,
            [([Cell(c), *_geometry(c, configurations)], {"c": c}) for c in cfgs],
            [(label(m), f"test.{{c}}.{m}.{HEADLINE}") for m in methods],
            ("config", "r [m]", "α [deg]"),
            title="Fusion: KLD(b) mean per pose-noise configuration and method (test split; lower is better)",
            note="KLD(b): KL(label‖pred) over the full mass vector (m_F, m_O, u), clipped to [1e-7, 1], "
            "averaged over cells, then over test pairs — a divergence of distributions (≥ 0). Its "
            "intervals: the estimates table; network − naive: the paired differences.",
            anchor="fusion-kld",
            headline=True,
        ),
        spec_table(
            src,
            [([Cell(c), Cell(label(m))], {"c": c, "m": m}) for c, m in rows],
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
        spec_table(
            src,
            [([Cell(c), Cell(label(m)), Cell(b)], {"c": c, "m": m, "b": b}) for c, m, b in diffs],
            DIFF_COLUMNS,
            ("config", "method", "baseline"),
            title="Fusion: paired differences (method − baseline) on the same test pairs",
            note="Negative Δ KLD / positive Δ Dice favour the method. 'lower' / 'higher' only "
            "when the interval excludes 0, else 'no difference shown'. naive − registered is "
            "registered − naive with the signs turned: one row. " + CI_NOTE,
            anchor="fusion-diff",
        ),
        spec_table(
            src,
            [([Cell(c), Cell(label(m))], {"c": c, "m": m}) for c, m in pose],
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
