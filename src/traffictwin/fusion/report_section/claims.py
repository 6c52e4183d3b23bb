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


def fusion_claims(metrics: Mapping[str, Any]) -> list[ClaimCheck]:
    """Every claim of :data:`~traffictwin.paper_numbers.FUSION_CLAIMS` with this run's
    numbers (paired 95 % cluster-bootstrap intervals of network − naive from ``fusion.json``)
    and its verdict; empty when ``fusion.json`` has no test configuration."""
    m = metrics.get(FUSION_FILE)
    configs = sorted(lookup(m, "test") or {}) if isinstance(m, Mapping) else []
    if not configs:
        return []
    a, noisy, last = configs[0], configs[1:], configs[-1]

    def diff(c: str, key: str) -> tuple[Any, Any, Any]:
        """``(estimate, lo, hi)`` of network − naive on ``key`` at ``c``."""
        d = lookup(m, f"diff.{c}.{NET}.vs_{NAIVE}.{key}")
        return tuple((d if isinstance(d, Mapping) else {}).get(k) for k in ("estimate", "lo", "hi"))

    def at(cfgs: Sequence[str], key: str) -> tuple[list[str], str]:
        """Sides (against zero) of network − naive at ``cfgs``, and ``B −0.131 [−0.153, …]; C …``."""
        sides = [interval_side(*diff(c, key)[1:]) for c in cfgs]
        return sides, "; ".join(f"{c} {fmt_interval(*diff(c, key))}" for c in cfgs)

    def growth(key: str) -> tuple[list[str], str]:
        """Side of network − naive's interval at the last configuration against the first one's
        (they must not overlap for the gap to have changed), and ``A … → D …``."""
        (e0, lo0, hi0), (e1, lo1, hi1) = diff(a, key), diff(last, key)
        side = NO_INTERVAL if None in (lo0, hi0) else interval_side(lo1, hi1, lo0, hi0)
        return [side], f"{a} {fmt_interval(e0, lo0, hi0)} → {last} {fmt_interval(e1, lo1, hi1)}"

    def iqr(c: str, row: str) -> str:
        """KLD(b) interquartile range of ``row`` at ``c`` (no interval in fusion.json)."""
        q25, q75 = (lookup(m, f"test.{c}.{row}.kld_fou_{q}") for q in ("q25", "q75"))
        ok = all(isinstance(q, (int, float)) for q in (q25, q75))
        return f"{float(q75) - float(q25):.3g}" if ok else "n/a"

    kld, dice = "network − naive KLD(b), nats/cell", "network − naive occupied Dice"
    gap = f", the gap at {last} against {a} (intervals must not overlap)"
    spread = "; ".join(f"{c} {iqr(c, NET)} vs {iqr(c, NAIVE)}" for c in noisy)
    iqr_text = "KLD(b) interquartile range, network vs naive (point estimates, no interval)"
    checks = {  # claim: ((sides, numbers), the side that confirms it, what the numbers are)
        "kld_A_baseline_better": (at([a], HEADLINE), HIGHER, kld),
        "kld_BCD_net_better": (at(noisy, HEADLINE), LOWER, kld),
        "kld_baseline_degrades_faster": (growth(HEADLINE), LOWER, kld + gap),
        "kld_net_less_spread": (([NO_INTERVAL], spread), LOWER, iqr_text),
        "scores_A_baseline_better": (
            at([a], DICE),
            LOWER,
            f"{dice} (the only score with a paired interval)",
        ),
        "scores_flatter_net": (growth(DICE), HIGHER, dice + gap),
        "scores_net_dominant_except": (
            at(noisy, DICE),
            HIGHER,
            f"{dice} (precision / recall have no interval)",
        ),
    }
    out = []
    for name, ((sides, text), expected, what) in checks.items():
        c = P.FUSION_CLAIMS[name]
        out.append(
            ClaimCheck(PAPER, c.text, c.source, f"{what}: {text}", claim_verdict(sides, expected))
        )
    return out
