"""The interval rule, in one place: where a 95 % interval lies against a reference.

A difference is a finding only when its interval excludes zero; a number is compared with a
reference value (a paper's printed number) or with another interval the same way. The fusion
findings (:func:`traffictwin.fusion.findings.verdict`), the report's claim verdicts
(:mod:`traffictwin.report.claims`) and the fusion page's tables all place intervals with
:func:`interval_side`. :func:`traffictwin.stats.excludes_zero` asks the same question of an
:class:`~traffictwin.stats.Interval`.
"""

from __future__ import annotations

import math
from numbers import Real
from typing import Any

__all__ = ["HIGHER", "LOWER", "NO_DIFFERENCE", "NO_INTERVAL", "SIDES", "finite", "interval_side"]

LOWER, HIGHER, NO_DIFFERENCE, NO_INTERVAL = "lower", "higher", "no difference shown", "n/a"
#: every value :func:`interval_side` returns
SIDES = (LOWER, HIGHER, NO_DIFFERENCE, NO_INTERVAL)


def finite(v: Any) -> float | None:
    """``v`` as a float when it is a finite real number (not a bool), else None."""
    if isinstance(v, bool) or not isinstance(v, Real):
        return None
    x = float(v)
    return x if math.isfinite(x) else None


def interval_side(lo: Any, hi: Any, ref_lo: Any = 0.0, ref_hi: Any = None) -> str:
    """Where the interval ``[lo, hi]`` lies against the reference ``[ref_lo, ref_hi]`` (a point
    when ``ref_hi`` is None: zero for a difference, a paper's value): ``"lower"`` when entirely
    below it, ``"higher"`` when entirely above, ``"no difference shown"`` when they overlap
    (touching counts as overlapping), ``"n/a"`` when a bound is missing or not finite."""
    lo, hi = finite(lo), finite(hi)
    bottom = finite(ref_lo)
    top = bottom if ref_hi is None else finite(ref_hi)
    if lo is None or hi is None or bottom is None or top is None:
        return NO_INTERVAL
    if hi < bottom:
        return LOWER
    if lo > top:
        return HIGHER
    return NO_DIFFERENCE
