"""Does this run reproduce the papers? One verdict per claim of a paper, computed from this run's
numbers and their 95 % intervals, never typed in.

The rule is the report's interval rule: a difference is a finding only when its 95 % interval
excludes zero. A claim is checked on one or more intervals (e.g. network − naive KLD at B, C and
D), each placed against a reference (zero for a difference; the paper's printed value for a
number the paper reports) with :func:`interval_side`; :func:`claim_verdict` turns the sides into

- ``reproduced``: every interval lies on the side the paper claims (for a paper's number: our
  interval reaches the paper's value or lies beyond it on the better side);
- ``not reproduced``: some interval does not (it lies on the other side, or -- for a claimed
  difference -- it contains zero: this run shows no difference);
- ``not comparable``: a number or its interval is missing (the claim has no interval in this
  run's metrics, or the stage did not run).

Each problem's :class:`~traffictwin.report.model.SectionProvider` lists its claims
(``claims``: metrics files -> :class:`ClaimCheck` list); this module knows none of them.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

__all__ = [
    "NOT_COMPARABLE",
    "NOT_REPRODUCED",
    "REPRODUCED",
    "ClaimCheck",
    "claim_verdict",
    "fmt_interval",
    "interval_side",
    "pct",
]

REPRODUCED, NOT_REPRODUCED, NOT_COMPARABLE = "reproduced", "not reproduced", "not comparable"
LOWER, HIGHER, NO_DIFFERENCE, NO_INTERVAL = "lower", "higher", "no difference shown", "n/a"


@dataclass(frozen=True)
class ClaimCheck:
    """One claim of a paper against this run: the paper (short name), the claim's text and where
    the paper makes it (section / figure), what this run measured (numbers with their 95 %
    intervals, as text) and the verdict computed from them (:func:`claim_verdict`)."""

    paper: str
    claim: str
    where: str
    measured: str
    verdict: str


def _finite(v: Any) -> float | None:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    return float(v) if math.isfinite(float(v)) else None


def interval_side(lo: Any, hi: Any, ref_lo: float = 0.0, ref_hi: float | None = None) -> str:
    """Where the interval ``[lo, hi]`` lies against the reference ``[ref_lo, ref_hi]`` (a point
    when ``ref_hi`` is None: zero for a difference, a paper's value): ``"lower"`` when entirely
    below it, ``"higher"`` when entirely above, ``"no difference shown"`` when they overlap,
    ``"n/a"`` when a bound is missing or not finite."""
    lo, hi = _finite(lo), _finite(hi)
    top = ref_lo if ref_hi is None else ref_hi
    if lo is None or hi is None or _finite(ref_lo) is None or _finite(top) is None:
        return NO_INTERVAL
    if hi < ref_lo:
        return LOWER
    if lo > top:
        return HIGHER
    return NO_DIFFERENCE


def claim_verdict(sides: Sequence[str], expected: str, *, value: bool = False) -> str:
    """The verdict of a claim from the :func:`interval_side` of each of its intervals.

    ``expected``: ``"lower"`` or ``"higher"``, the side the paper claims. ``value``: the
    reference is a number the paper reports (not a difference of zero), so an interval that
    contains it reproduces it too. No sides, or a side ``"n/a"``: ``not comparable``."""
    if expected not in (LOWER, HIGHER):
        raise ValueError(f"claim_verdict: expected must be 'lower' or 'higher', got {expected!r}")
    if not sides or NO_INTERVAL in sides:
        return NOT_COMPARABLE
    agree = {expected, NO_DIFFERENCE} if value else {expected}
    return REPRODUCED if all(s in agree for s in sides) else NOT_REPRODUCED


def pct(x: float) -> str:
    """A fraction as percent with 2 decimals, the report's ``pct`` format (``0.7287`` -> ``72.87 %``)."""
    return f"{100.0 * x:.2f} %"


def fmt_interval(
    estimate: Any, lo: Any, hi: Any, fmt: str | Callable[[float], str] = "{:+.3g}"
) -> str:
    """``estimate [lo, hi]`` formatted with ``fmt`` (a format string or a function of the number;
    ``n/a`` for a missing number; the estimate alone without an interval)."""

    def f(v: Any) -> str:
        x = _finite(v)
        if x is None:
            return "n/a"
        return fmt(x) if callable(fmt) else fmt.format(x)

    if _finite(lo) is None or _finite(hi) is None:
        return f(estimate)
    return f"{f(estimate)} [{f(lo)}, {f(hi)}]"
