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
    for cfg, per_row in rows.items():
        for row, per_metric in per_row.items():
            for metric, entry in per_metric.items():
                label, fmt = METRICS.get(metric, (metric, "g4"))
                key = f"rows.{cfg}.{row}.{metric}"
                t.rows.append(
                    [
                        Cell(cfg),
                        Cell(row),
                        Cell(label),
                        src.cell(SEEDS_FILE, f"{key}.estimate", fmt),
                        interval_cell(src, SEEDS_FILE, key, BOOTSTRAP, fmt),
                        Cell(", ".join(fmt_value(v, fmt) for v in entry.get("per_seed", []))),
                        src.cell(SEEDS_FILE, f"{key}.seed_sd", fmt),
                    ]
                )
    return t


def seed_findings(src: page.Sources) -> list[str]:
    """One bullet per compared claim: the single-seed and the seeds × scenarios difference, each
    with its verdict, and whether the claim holds with seeds in its interval."""
    found = src.get(SEEDS_FILE, "findings")
    if not isinstance(found, dict):
        return []
    n = len(src.get(SEEDS_FILE, "seeds", []))
    out = []
    for pair, per_metric in found.items():
        a, _, b = pair.partition("_vs_")
        for metric, per_cfg in per_metric.items():
            label, fmt = METRICS.get(metric, (metric, "g4"))
            if fmt == "pct":
                fmt = "f3"  # a difference of rates: as a fraction, signed
            parts, changed = [], []
            for cfg, e in per_cfg.items():
                one, many = e["single_seed"], e["seeds"]
                parts.append(
                    f"{cfg} {_signed(many['estimate'], fmt)} [{_signed(many['lo'], fmt)}, "
                    f"{_signed(many['hi'], fmt)}] ({many['verdict']}; one seed: {one['verdict']})"
                )
                if not e["holds"]:
                    changed.append(cfg)
            held = (
                "every verdict holds with seeds"
                if not changed
                else f"the verdict changes with seeds at {', '.join(changed)}"
            )
            out.append(f"**{a} − {b}, {label} ({n} seeds):** {'; '.join(parts)} — {held}.")
    return out


def _signed(v: float, fmt: str) -> str:
    s = fmt_value(v, fmt)
    return s if s.startswith("-") or s == "n/a" else f"+{s}"
