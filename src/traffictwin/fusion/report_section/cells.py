"""The fusion section's shared vocabulary: where its numbers are (``fusion.json`` keys), the rows'
labels, and the cells every table is built of (a number, its 95 % interval, a paired verdict)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from traffictwin import paper_numbers as P
from traffictwin.fusion.findings import verdict
from traffictwin.report import model as page
from traffictwin.report.model import NA, Cell, fmt_value, interval_cell, lookup

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
POSE_ROWS = (
    "registered",
    "learned",
    "learned-refined",
)  # rows with their own pose estimate (the hybrids reuse them)
NET, NAIVE, REG = "dnn", "naive", "registered"
HEADLINE = "kld_fou_mean"
CI_NOTE = (
    "Brackets: 95 % cluster-bootstrap interval (scenario = pair_id // 1000 resampled; "
    "evaluation.fusion_ci)."
)
Configurations = Mapping[str, tuple[float, float]]  # {name: (r m, alpha deg)}


def fusion_key(cfg: str, method: str, metric: str) -> str:
    """Key of ``metric`` for configuration ``cfg`` and ``method`` in fusion.json."""
    return f"test.{cfg}.{method}.{metric}"


def diff_key(c: str, row: str, base: str, metric: str) -> str:
    """Key of the paired difference ``row − base`` of ``metric`` at configuration ``c``."""
    return f"diff.{c}.{row}.vs_{base}.{metric}"


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
        d = lookup(src.metrics.get(FUSION_FILE), f"test.{c}")
        if isinstance(d, dict):
            found += [m for m in d if m not in found]
    order = list(FUSION_METHOD_LABELS)
    return sorted(found, key=lambda m: (order.index(m) if m in order else len(order), m))


def network_rows(src: page.Sources, cfgs: Sequence[str], prefix: str = "dnn[") -> list[str]:
    return [m for m in fusion_methods(src, cfgs) if m.startswith(prefix)]


def config_cells(configurations: Configurations, c: str) -> list[Cell]:
    """Configuration, r [m], α [deg] (this run's, else the paper's)."""
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


def ci_cell(src: page.Sources, key: str, file: str = FUSION_FILE) -> Cell:
    """``[lo, hi]`` of ``<key>_ci`` (or of ``key`` itself when it holds ``lo``/``hi``) in metrics
    file ``file``: the cluster-bootstrap interval cell (:func:`~traffictwin.report.model.interval_cell`)."""
    return interval_cell(src, file, key, "cluster-bootstrap")


def value_ci_cells(src: page.Sources, key: str) -> list[Cell]:
    """The number at fusion.json ``key`` and its interval ``<key>_ci``."""
    return [src.cell(FUSION_FILE, key), ci_cell(src, key)]


TOO_FEW_WRONG = "too few wrong cells"
AUROC_COLUMNS = ("AUROC(u)", "95 % CI", "wrong / right cells")
AUROC_NOTE = (
    "AUROC(u): u as a detector of wrongly classified label-known cells, with the wrong and right "
    "cells behind it; 'too few wrong cells' where fewer than evaluation.fusion.auroc_min_wrong "
    "wrong cells, or wrong cells in fewer than auroc_min_pairs pairs, stand behind it (an AUROC "
    "of a handful of cells says nothing about u). "
)


def auroc_cells(src: page.Sources, c: str, m: str) -> list[Cell]:
    """Row ``m``'s AUROC(u) at ``c``: value, interval and the cells behind it
    (:data:`AUROC_COLUMNS`); "too few wrong cells" instead of a number where fusion.json withholds it."""
    base = fusion_key(c, m, "u_auroc")
    wrong = src.get(FUSION_FILE, f"{base}_n_wrong")
    right = src.get(FUSION_FILE, f"{base}_n_right")
    pairs = src.get(FUSION_FILE, f"{base}_pairs_wrong")
    if isinstance(wrong, (int, float)) and isinstance(right, (int, float)):
        where = f" in {int(pairs)} pairs" if isinstance(pairs, (int, float)) else ""
        counts = (
            Cell(  # composite text: no single source value (fusion.json <base>_n_wrong/_n_right)
                f"{int(wrong):,}{where} / {int(right):,}",
                title=f"wrong cells (pairs with any) / right cells, label-known cells only "
                f"(fusion.json {base}_n_wrong, _n_right, _pairs_wrong)",
            )
        )
    else:
        counts = Cell(NA, title="fusion.json has no cell counts (an older run)")
    if src.get(FUSION_FILE, f"{base}_enough") is False:
        return [
            Cell(TOO_FEW_WRONG, title="AUROC(u) withheld: too few wrong cells behind it"),
            Cell(NA),
            counts,
        ]
    return [*value_ci_cells(src, base), counts]


def estimate_ci_cells(src: page.Sources, dk: str) -> list[Cell]:
    """A paired difference at fusion.json ``dk``: its estimate and interval."""
    return [src.cell(FUSION_FILE, f"{dk}.estimate"), ci_cell(src, dk)]


def has_row(src: page.Sources, c: str, m: str) -> bool:
    """Row ``m`` was evaluated at configuration ``c``."""
    return isinstance(src.get(FUSION_FILE, f"test.{c}.{m}"), dict)


def row_cell(src: page.Sources, c: str, m: str, metric: str) -> Cell:
    """``test.<c>.<m>.<metric>``; a row not evaluated at ``c`` (a variant elsewhere) is n/a, not missing."""
    if not has_row(src, c, m):
        return Cell(NA, title=f"{m} not evaluated at configuration {c}")
    return src.cell(FUSION_FILE, fusion_key(c, m, metric))


def verdict_cell(src: page.Sources, c: str, row: str, base: str, metric: str) -> Cell:
    """ "lower" / "higher" / "no difference shown" of the paired difference ``row − base``."""
    d = src.get(FUSION_FILE, diff_key(c, row, base, metric))
    v = verdict(d if isinstance(d, dict) else None)
    return Cell(v, title="claimed only when the paired 95 % interval excludes 0")
