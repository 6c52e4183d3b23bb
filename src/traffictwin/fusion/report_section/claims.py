"""The fusion paper's claims (:data:`traffictwin.paper_numbers.FUSION_CLAIMS`) against this
run's ``fusion.json``, one :class:`~traffictwin.report.claims.ClaimCheck` each (the verdict table
on the report's first screen). Configurations: the test ones in order, the first noise-free. The
paper's Fig. 5 shows KLD(a); the run checks KLD(b) (the full mass vector), which has paired
intervals of network − naive; of the scores only occupied Dice has them, and the text says so.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from traffictwin import paper_numbers as P
from traffictwin.fusion.report_section.tables import FUSION_FILE, HEADLINE, NAIVE, NET
from traffictwin.interval_rule import HIGHER, LOWER, NO_INTERVAL, interval_side
from traffictwin.report.claims import ClaimCheck, claim_verdict, fmt_interval
from traffictwin.report.model import lookup

__all__ = ["PAPER", "fusion_claims"]

PAPER = "Paper 1 — fusion"
DICE = "dice_occ"


def _diff(m: Any, c: str, key: str) -> tuple[Any, Any, Any]:
    """``(estimate, lo, hi)`` of the paired difference network − naive on ``key`` at ``c``."""
    d = lookup(m, f"diff.{c}.{NET}.vs_{NAIVE}.{key}")
    d = d if isinstance(d, Mapping) else {}
    return d.get("estimate"), d.get("lo"), d.get("hi")


def _at(m: Any, configs: Sequence[str], key: str) -> tuple[list[str], str]:
    """Sides (against zero) of network − naive on ``key`` at ``configs``, and the text
    ``B −0.131 [−0.153, −0.111]; C …``."""
    diffs = [(c, _diff(m, c, key)) for c in configs]
    sides = [interval_side(lo, hi) for _, (_, lo, hi) in diffs]
    text = "; ".join(f"{c} {fmt_interval(*d)}" for c, d in diffs)
    return sides, text


def _growth(m: Any, first: str, last: str, key: str) -> tuple[list[str], str]:
    """Side of the interval of network − naive on ``key`` at ``last`` against the one at ``first``
    (they must not overlap for the gap to have changed), and the text ``A … → D …``."""
    e0, lo0, hi0 = _diff(m, first, key)
    e1, lo1, hi1 = _diff(m, last, key)
    side = NO_INTERVAL if None in (lo0, hi0) else interval_side(lo1, hi1, lo0, hi0)
    return [side], f"{first} {fmt_interval(e0, lo0, hi0)} → {last} {fmt_interval(e1, lo1, hi1)}"


def _spread(m: Any, configs: Sequence[str]) -> tuple[list[str], str]:
    """No side (the interquartile range has no interval in fusion.json) and the text of the
    network's against naive's KLD(b) interquartile range at ``configs``."""

    def iqr(c: str, row: str) -> str:
        q25, q75 = (lookup(m, f"test.{c}.{row}.kld_fou_{q}") for q in ("q25", "q75"))
        ok = all(isinstance(q, (int, float)) for q in (q25, q75))
        return f"{float(q75) - float(q25):.3g}" if ok else "n/a"

    return [NO_INTERVAL], "; ".join(f"{c} {iqr(c, NET)} vs {iqr(c, NAIVE)}" for c in configs)


def fusion_claims(metrics: Mapping[str, Any]) -> list[ClaimCheck]:
    """Every claim of :data:`~traffictwin.paper_numbers.FUSION_CLAIMS` with this run's
    numbers (paired 95 % cluster-bootstrap intervals of network − naive from ``fusion.json``)
    and its verdict; empty when ``fusion.json`` has no test configuration."""
    m = metrics.get(FUSION_FILE)
    configs = sorted(lookup(m, "test") or {}) if isinstance(m, Mapping) else []
    if not configs:
        return []
    a, noisy, last = configs[0], configs[1:], configs[-1]
    kld, dice = "network − naive KLD(b), nats/cell", "network − naive occupied Dice"
    gap = f", the gap at {last} against {a} (intervals must not overlap)"
    checks = (  # (claim, (sides, numbers), the side that confirms it, what the numbers are)
        ("kld_A_baseline_better", _at(m, [a], HEADLINE), HIGHER, kld),
        ("kld_BCD_net_better", _at(m, noisy, HEADLINE), LOWER, kld),
        ("kld_baseline_degrades_faster", _growth(m, a, last, HEADLINE), LOWER, kld + gap),
        (
            "kld_net_less_spread",
            _spread(m, noisy),
            LOWER,
            "KLD(b) interquartile range, network vs naive (point estimates, no interval)",
        ),
        (
            "scores_A_baseline_better",
            _at(m, [a], DICE),
            LOWER,
            f"{dice} (the only score with a paired interval)",
        ),
        ("scores_flatter_net", _growth(m, a, last, DICE), HIGHER, dice + gap),
        (
            "scores_net_dominant_except",
            _at(m, noisy, DICE),
            HIGHER,
            f"{dice} (precision / recall have no interval)",
        ),
    )
    out = []
    for name, (sides, text), expected, what in checks:
        c = P.FUSION_CLAIMS[name]
        out.append(
            ClaimCheck(PAPER, c.text, c.source, f"{what}: {text}", claim_verdict(sides, expected))
        )
    return out
