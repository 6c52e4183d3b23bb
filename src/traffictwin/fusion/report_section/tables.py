"""The fusion section's tables, each number once: KLD(b) per configuration and method (the
headline), every row's other estimates, precision / recall / Dice, the paired differences, the
registration's pose error (per configuration and per bin of the drawn noise), the one network
against the per-configuration networks, and the cross table.

Cells read ``fusion.json`` (:func:`cell`): ``test.<cfg>.<row>.<metric>`` with the 95 %
cluster-bootstrap interval ``<metric>_ci``, and the paired differences
``diff.<cfg>.<row>.vs_<base>.<metric>`` (``estimate``, ``lo``, ``hi``). A row not evaluated at a
configuration is ``n/a``; a "lower" / "higher" verdict only where the paired interval excludes 0.
"""

from __future__ import annotations

import math
import re
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

#: the per-row tables' columns, (key, header) with the keys of :func:`cell`; ``u_auroc``: AUROC(u),
#: its interval and the cells behind it (:func:`auroc_cells`)
ESTIMATE_COLUMNS = (
    ("kld_fou_mean_ci", "KLD(b) 95 % CI"),
    ("kld_fo_mean", "KLD(a)"),
    ("kld_fo_mean_ci", "95 % CI"),
    ("kld_fo_median", "KLD(a) median"),
    ("u_mean", "mean u"),
    ("u_mean_ci", "95 % CI"),
    ("u_auroc", "AUROC(u)"),
)
SCORE_COLUMNS = tuple(
    col
    for c in ("occ", "free")
    for col in (
        (f"precision_{c}", f"precision {c}"),
        (f"recall_{c}", f"recall {c}"),
        (f"dice_{c}", f"Dice {c}"),
        (f"dice_{c}_ci", "95 % CI"),
    )
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
AUROC_COLUMNS = ("AUROC(u)", "95 % CI", "wrong / right cells")


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
    (its interval), ``vs_<base>.<metric>`` / ``vs_<base>.<metric>_ci`` (the paired difference
    ``m − base``: estimate / interval). ``n/a`` for a row or difference not evaluated at ``c``."""
    metric = key.removesuffix("_ci")
    if key.startswith("vs_"):
        base = f"diff.{c}.{m}.{metric}"
        if not isinstance(src.get(FUSION_FILE, base), dict):
            return Cell(NA, title=f"no paired difference {m} {metric} at configuration {c}")
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


def auroc_cells(src: page.Sources, c: str, m: str) -> list[Cell]:
    """Row ``m``'s AUROC(u) at ``c``: value, interval and the cells behind it
    (:data:`AUROC_COLUMNS`); "too few wrong cells" where fusion.json withholds the value."""
    base = f"test.{c}.{m}.u_auroc"
    wrong, right, pairs = (
        src.get(FUSION_FILE, f"{base}_{k}") for k in ("n_wrong", "n_right", "pairs_wrong")
    )
    if isinstance(wrong, (int, float)) and isinstance(right, (int, float)):
        where = f" in {int(pairs)} pairs" if isinstance(pairs, (int, float)) else ""
        counts = Cell(  # composite text: no single source value
            f"{int(wrong):,}{where} / {int(right):,}",
            title=f"wrong cells (pairs with any) / right cells, label-known cells only "
            f"(fusion.json {base}_n_wrong, _n_right, _pairs_wrong)",
        )
    else:
        counts = Cell(NA, title="fusion.json has no cell counts (an older run)")
    if src.get(FUSION_FILE, f"{base}_enough") is False:
        return [
            Cell("too few wrong cells", title="AUROC(u) withheld: too few wrong cells behind it"),
            Cell(NA),
            counts,
        ]
    return [cell(src, c, m, "u_auroc"), cell(src, c, m, "u_auroc_ci"), counts]


def row_table(
    src: page.Sources,
    cfgs: Sequence[str],
    rows: Sequence[str],
    columns: Sequence[tuple[str, str]],
    require: str = "",
    **table: Any,
) -> Table:
    """One row per configuration and evaluated row of ``rows`` (that has metric ``require``):
    config, method, then ``columns`` (``(key, header)``, cells of :func:`cell`); ``table``:
    :class:`Table`'s other fields."""
    heads = [h for k, name in columns for h in (AUROC_COLUMNS if k == "u_auroc" else [name])]
    t = Table(columns=["config", "method", *heads], **table)
    for c in cfgs:
        for m in rows:
            if _has(src, f"test.{c}.{m}" + (f".{require}" if require else "")):
                cells = [
                    x
                    for k, _ in columns
                    for x in (auroc_cells(src, c, m) if k == "u_auroc" else [cell(src, c, m, k)])
                ]
                t.rows.append([Cell(c), Cell(label(m)), *cells])
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


def _diff_table(src: page.Sources, cfgs: Sequence[str], methods: Sequence[str]) -> Table:
    """Paired differences of every row against naive and registered."""
    t = Table(
        "Fusion: paired differences (method − baseline) on the same test pairs",
        ["config", "method", "baseline", "Δ KLD(b)", "95 % CI", "KLD(b) verdict", "Δ KLD(a)"]
        + ["95 % CI", "Δ Dice occ", "95 % CI", "Dice occ verdict"],
        note="Negative Δ KLD / positive Δ Dice favour the method. 'lower' / 'higher' only when the "
        "interval excludes 0, else 'no difference shown'. naive − registered is registered − naive "
        "with the signs turned: one row. " + CI_NOTE,
        anchor="fusion-diff",
    )
    for c in cfgs:
        for m in methods:
            for b in (NAIVE, REG):
                if not isinstance(src.get(FUSION_FILE, f"diff.{c}.{m}.vs_{b}"), dict) or (
                    (m, b) == (NAIVE, REG)  # registered − naive negated: shown once
                    and isinstance(src.get(FUSION_FILE, f"diff.{c}.{REG}.vs_{NAIVE}"), dict)
                ):
                    continue
                row = [Cell(c), Cell(label(m)), Cell(b)]
                for k in (HEADLINE, "kld_fo_mean", "dice_occ"):
                    row += [cell(src, c, m, f"vs_{b}.{k}"), cell(src, c, m, f"vs_{b}.{k}_ci")]
                    if k != "kld_fo_mean":
                        d = src.get(FUSION_FILE, f"diff.{c}.{m}.vs_{b}.{k}")
                        v = verdict(d if isinstance(d, dict) else None)
                        row.append(
                            Cell(v, title="claimed only when the paired 95 % interval excludes 0")
                        )
                t.rows.append(row)
    return t


def _bin_start(label: str) -> float:
    """A bin label's lower edge, as :func:`traffictwin.fusion.metrics.pose_error_bins` writes them
    (``"2-5deg"`` -> 2, ``">=15deg"`` -> 15): bins in numeric order (metrics files keep their keys
    sorted as strings, where ``10-15deg`` comes before ``2-5deg``); another label sorts last."""
    m = re.match(r"(?:>=)?(\d+(?:\.\d+)?)", label)
    return float(m.group(1)) if m else math.inf


def _bin_tables(src: page.Sources, rows: Sequence[str]) -> list[Table]:
    """Success rate (pairs) per bin of the drawn translation and yaw error, configurations pooled."""
    out = []
    for axis, what in (("translation", "translation"), ("rotation", "yaw")):
        bins = src.get(FUSION_FILE, f"bins.{axis}")
        bins = {
            m: bins[m] for m in rows if isinstance(bins, dict) and isinstance(bins.get(m), dict)
        }
        labels = sorted(
            dict.fromkeys(lab for per_bin in bins.values() for lab in per_bin), key=_bin_start
        )
        if not labels:
            continue
        t = Table(
            f"Registration: success rate per bin of the drawn {what} error (all configurations pooled)",
            ["method", *[f"{lab} (n)" for lab in labels]],
            note="Bins of the drawn pose noise (evaluation.fusion.trans_bins_m / rot_bins_deg); "
            "n = pairs in the bin.",
            anchor=f"fusion-registration-{axis}-bins",
        )
        for m in rows:
            cells = []
            for lab in labels:
                key = f"bins.{axis}.{m}.{lab}"
                sr = src.get(FUSION_FILE, f"{key}.success_rate")
                n = src.get(FUSION_FILE, f"{key}.n")
                if not isinstance(sr, (int, float)):
                    cells.append(Cell(NA))
                    continue
                count = int(n) if isinstance(n, (int, float)) else "?"
                derived = f"metrics/{FUSION_FILE}#{key}.success_rate (n: .n)"
                cells.append(
                    Cell(f"{fmt_value(sr, 'g4')} ({count})", value=[sr, n], derived=derived)
                )
            t.rows.append([Cell(label(m)), *cells])
        out.append(t)
    return out


def registration_tables(src: page.Sources, cfgs: Sequence[str]) -> list[Table]:
    """The pose error of every row that estimates a pose, per configuration, and its success
    rate per bin of the drawn translation and yaw error (none without such a row)."""
    rows = [m for m in POSE_ROWS if any(_has(src, f"test.{c}.{m}.success_rate") for c in cfgs)]
    if not rows:
        return []
    table = row_table(
        src,
        cfgs,
        rows,
        POSE_COLUMNS,
        "success_rate",
        headline=True,
        title="Registration: pose error of every method that estimates a pose (test split, same pairs)",
        note="Error of the pose used (the estimate, or the noisy pose where the estimate was "
        "rejected: 'fallback', counted in the success rate like any other pose) against the "
        "simulator's true relative pose; success = translation error <= "
        "evaluation.fusion.success_trans_m (m) and yaw error <= evaluation.fusion.success_rot_deg "
        "(deg). Wall time per pair: reports/timings/evaluate_fusion.json (this run) and "
        "benchmarks/registration.py. Δ: paired over the same pairs. " + CI_NOTE,
        anchor="fusion-registration",
    )
    return [table, *_bin_tables(src, rows)]


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


def _cross_table(src: page.Sources) -> Table | None:
    """KLD(b) of each per-configuration network on the other configurations (None without any)."""
    cross = src.get(FUSION_FILE, "cross")
    if not isinstance(cross, dict) or not cross:
        return None
    tcfgs = sorted({tc for n in cross.values() if isinstance(n, dict) for tc in n})
    t = Table(
        "Fusion: cross table, KLD(b) mean of the per-configuration networks (the ablation) "
        "trained on one configuration (rows) tested on another (columns)",
        ["network trained on", *[f"test {tc}" for tc in tcfgs]],
        anchor="fusion-cross",
        note="Own configuration: all test pairs; others: a subset "
        "(evaluation.fusion.cross_max_pairs). The one network (row dnn of the KLD table) is "
        "evaluated at every configuration on all pairs.",
    )
    for n in sorted(cross):
        t.rows.append(
            [Cell(n)] + [src.cell(FUSION_FILE, f"cross.{n}.{tc}.{HEADLINE}") for tc in tcfgs]
        )
    return t


def fusion_tables(src: page.Sources, configurations: Configurations) -> list[Table]:
    """KLD(b) per configuration and method (the headline), every row's other estimates and its
    scores, the paired differences, the registration tables, the one network against the
    per-configuration networks and the cross table (the targets: the index's acceptance table)."""
    cfgs = fusion_configs(src, configurations)
    methods = fusion_methods(src, cfgs)
    estimates = row_table(
        src,
        cfgs,
        methods,
        ESTIMATE_COLUMNS,
        title="Fusion: estimates with 95 % intervals per configuration and method (test split)",
        note="KLD(b) means: the KLD table; KLD(a) over (m_F, m_O) only, for comparison with the "
        "paper (median over test pairs: the line in its Fig. 5 boxes). AUROC(u): u as a detector "
        "of wrongly classified label-known cells, with the wrong and right cells behind it; 'too "
        "few wrong cells' where fewer than evaluation.fusion.auroc_min_wrong wrong cells, or wrong "
        "cells in fewer than auroc_min_pairs pairs, stand behind it (an AUROC of a handful of "
        "cells says nothing about u). The dnn[<loss>] rows: the fusion_variants networks, trained "
        "with another loss on the same data. " + CI_NOTE,
        anchor="fusion-ci",
    )
    scores = row_table(
        src,
        cfgs,
        methods,
        SCORE_COLUMNS,
        title="Fusion: precision / recall / Dice per class (test split, pooled over cells; higher is better)",
        note="A cell is predicted occupied where p_O > 0.5 and free where p_O < 0.5 (docs/design.md; "
        "the paper's sentence swaps the words); only label-known cells count. The paper shows "
        "these as Figs. 6 and 7 without printed values. " + CI_NOTE,
        anchor="fusion-scores",
    )
    tables = [
        _kld_table(src, configurations, cfgs, methods),
        estimates,
        _diff_table(src, cfgs, methods),
        scores,
    ]
    tables += registration_tables(src, cfgs)
    optional = (per_config_table(src, cfgs), _cross_table(src))
    return [t for t in tables + [t for t in optional if t is not None] if t.rows]
