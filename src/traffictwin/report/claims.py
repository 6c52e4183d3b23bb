"""Does this run reproduce the papers? One verdict per claim of a paper, computed from this run's
numbers and their 95 % intervals, never typed in.

A claim is checked on one or more intervals (e.g. network − naive KLD at B, C and D), each placed
against a reference (zero for a difference, the paper's printed value for a number) by
:func:`~traffictwin.interval_rule.interval_side`, the report's one interval rule (a difference
is a finding only when its 95 % interval excludes zero); :func:`claim_verdict` turns the sides
into a verdict. Each problem's :class:`~traffictwin.report.model.SectionProvider` lists its
claims (``claims``: metrics files -> :class:`ClaimCheck` list); this module knows none of them.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from traffictwin.interval_rule import HIGHER, LOWER, NO_DIFFERENCE, NO_INTERVAL, finite

REPRODUCED, EXCEEDED = "reproduced", "exceeded"
NOT_REPRODUCED, NOT_COMPARABLE = "not reproduced", "not comparable"
#: every verdict, in the order the report counts them
VERDICTS = (REPRODUCED, EXCEEDED, NOT_REPRODUCED, NOT_COMPARABLE)


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


def claim_verdict(sides: Sequence[str], expected: str, *, value: bool = False) -> str:
    """The verdict of a claim from the :func:`~traffictwin.interval_rule.interval_side` of each of
    its intervals; ``expected``: ``"lower"`` or ``"higher"``, the side the paper claims (for a
    number the paper prints, ``value=True``: the better side).

    - ``reproduced``: every interval on the claimed side (a difference), or -- a printed number
      -- every interval reaching it or beyond it on the better side, at least one reaching it;
    - ``exceeded``: a printed number, every interval wholly beyond it on the better side (this
      run does better than the paper, which is no reproduction of its number);
    - ``not reproduced``: some interval on the other side, or -- a claimed difference --
      containing zero;
    - ``not comparable``: no sides, or a side ``"n/a"`` (a number or its interval missing).
    """
    if expected not in (LOWER, HIGHER):
        raise ValueError(f"claim_verdict: expected must be 'lower' or 'higher', got {expected!r}")
    if not sides or NO_INTERVAL in sides:
        return NOT_COMPARABLE
    if all(s == expected for s in sides):
        return EXCEEDED if value else REPRODUCED
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
        x = finite(v)
        if x is None:
            return "n/a"
        return fmt(x) if callable(fmt) else fmt.format(x)

    if finite(lo) is None or finite(hi) is None:
        return f(estimate)
    return f"{f(estimate)} [{f(lo)}, {f(hi)}]"
