"""The fusion section's seed replicates: the network and the learned registration trained with
several seeds (``reports/ablations/fusion_seeds.json``, written by ``python -m pipelines.ablations
collect seeds_1 seeds_2``; layout in :mod:`traffictwin.fusion.evaluation.seeds`), or the note that
the section's claims rest on one seed when they have not been collected."""

from __future__ import annotations

from traffictwin.report import model as page
from traffictwin.report.model import Cell, Table, fmt_value, interval_cell

SEEDS_FILE = "ablations/fusion_seeds.json"
SEEDS_COMMAND = "python -m pipelines.ablations run seeds_1 seeds_2 --until evaluate_fusion"
METRICS = {
    "kld_fou_mean": ("KLD(b)", "g4"),
    "dice_occ": ("Dice occ", "pct"),
    "success_rate": ("success", "pct"),
}
BOOTSTRAP = "seeds × scenarios bootstrap"


def single_seed_note(src: page.Sources) -> str | None:
    """The sentence that the fusion claims are single-seed, while no replicates are collected."""
    if src.has(SEEDS_FILE):
        return None
    return (
        "**One training seed:** every fusion and registration finding above rests on one training "
        "seed of the network and of the learned registration; the seed replicates "
        f"(`{SEEDS_COMMAND}`) have not been collected into `reports/{SEEDS_FILE}`."
    )


def _mean(src: page.Sources, key: str, fmt: str) -> list[Cell]:
    """The mean over seeds at ``key`` of the seeds file and its seeds × scenarios interval."""
    return [
        src.cell(SEEDS_FILE, f"{key}.estimate", fmt),
        interval_cell(src, SEEDS_FILE, key, BOOTSTRAP, fmt),
    ]


def _paths(nested: dict) -> list[tuple[str, str, str]]:
    """The ``(a, b, c)`` key paths of a dict of dicts of dicts, in its order."""
    return [(a, b, c) for a, x in nested.items() for b, y in x.items() for c in y]


def seed_row_table(src: page.Sources) -> Table | None:
    """Every seed-dependent row's KLD(b), occupied Dice and success per configuration: the mean
    over seeds with its seeds × scenarios interval, each seed's value and the seed SD."""
    rows = src.get(SEEDS_FILE, "rows")
    if not isinstance(rows, dict):
        return None
    seeds = src.get(SEEDS_FILE, "seeds", [])
    t = Table(
        f"Fusion: seed replicates ({len(seeds)} training seeds of the network and the learned "
        "registration, same data and test pairs)",
        ["config", "row", "metric", "mean over seeds", "95 % CI", "per seed", "seed SD"],
        note=f"Interval: {BOOTSTRAP} (seeds drawn with replacement, scenarios = pair_id // 1000); "
        f"seeds in order: {', '.join(map(str, seeds))}. Source: reports/{SEEDS_FILE}.",
        anchor="fusion-seeds",
    )
    for cfg, row, metric in _paths(rows):
        name, fmt = METRICS.get(metric, (metric, "g4"))
        key = f"rows.{cfg}.{row}.{metric}"
        per_seed = ", ".join(fmt_value(v, fmt) for v in src.get(SEEDS_FILE, f"{key}.per_seed", []))
        t.rows.append([Cell(cfg), Cell(row), Cell(name), *_mean(src, key, fmt), Cell(per_seed)])
        t.rows[-1].append(src.cell(SEEDS_FILE, f"{key}.seed_sd", fmt))
    return t


def seed_diff_table(src: page.Sources) -> Table | None:
    """Every compared claim's paired difference with seeds in its interval (mean over seeds,
    seeds × scenarios interval, verdict) beside this run's single-seed verdict."""
    found = src.get(SEEDS_FILE, "findings")
    if not isinstance(found, dict):
        return None
    t = Table(
        f"Fusion: the findings with {len(src.get(SEEDS_FILE, 'seeds', []))} training seeds in "
        "their intervals (paired differences on the same test pairs)",
        ["difference", "metric", "config", "mean over seeds", "95 % CI", "verdict"]
        + ["verdict with one seed"],
        note=f"Interval: {BOOTSTRAP}; 'lower' / 'higher' only when it excludes 0. One seed: this "
        "run's paired difference (its numbers: the paired-difference table). Rates as fractions. "
        f"Source: reports/{SEEDS_FILE}.",
        anchor="fusion-seed-findings",
    )
    for pair, metric, cfg in _paths(found):
        name, fmt = METRICS.get(metric, (metric, "g4"))
        fmt = "f3" if fmt == "pct" else fmt  # a difference of rates: as a fraction
        key = f"findings.{pair}.{metric}.{cfg}"
        verdicts = [src.get(SEEDS_FILE, f"{key}.{k}.verdict") for k in ("seeds", "single_seed")]
        t.rows.append([Cell(pair.replace("_vs_", " − ")), Cell(name), Cell(cfg)])
        t.rows[-1] += [*_mean(src, f"{key}.seeds", fmt), *(Cell(str(v)) for v in verdicts)]
    return t
