"""The values the risk findings quote, read from ``reports/metrics/risk.json``.

Numbers formatted with their 95 % intervals (``value [lo, hi]``; "n/a" where missing), the
verdict of a paired difference (:func:`beats`: a claim only when its interval excludes zero,
:func:`traffictwin.stats.excludes_zero`), one comparison as a :class:`Claim`, and
:class:`FindingsRun`, what every findings group (:mod:`traffictwin.risk.findings_data`) reads.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, NamedTuple

from traffictwin.nested import lookup
from traffictwin.risk.evaluation import LOWER_IS_BETTER, PAPER, SEED_MEAN
from traffictwin.stats import Interval, excludes_zero


def as_float(x: Any) -> float | None:
    """``x`` as a float when it is a number (not a bool), else None."""
    return float(x) if isinstance(x, (int, float)) and not isinstance(x, bool) else None


def percent(x: Any) -> str:
    """A share in [0, 1] as ``"12.34 %"``; "n/a" unless ``x`` is a number."""
    v = as_float(x)
    return "n/a" if v is None else f"{100 * v:.2f} %"


def formatted(x: Any, fmt: str = ".4f") -> str:
    """``x`` in format ``fmt``; "n/a" unless it is a number."""
    v = as_float(x)
    return "n/a" if v is None else format(v, fmt)


def with_ci(d: Any, key: str, fmt: str = ".3f", pct: bool = False) -> str:
    """``value [lo, hi]`` of ``d``'s dotted ``key`` and ``key + "_ci"`` (just the value without
    interval; "n/a" without a value)."""
    v = as_float(lookup(d, key))
    ci = lookup(d, f"{key}_ci") or {}
    lo, hi = as_float(ci.get("lo")), as_float(ci.get("hi"))
    show = (lambda x: percent(x)) if pct else (lambda x: formatted(x, fmt))
    if v is None:
        return "n/a"
    if lo is None or hi is None:
        return show(v)
    return f"{show(v)} [{show(lo)}, {show(hi)}]"


def interval_of(d: Any) -> Interval | None:
    """The :class:`~traffictwin.stats.Interval` of ``{estimate, lo, hi}``; None if incomplete or NaN."""
    if not isinstance(d, Mapping):
        return None
    e, lo, hi = as_float(d.get("estimate")), as_float(d.get("lo")), as_float(d.get("hi"))
    if e is None or lo is None or hi is None or math.isnan(lo) or math.isnan(hi):
        return None
    return Interval(e, lo, hi)


def _signed(x: float) -> str:
    return f"{x:+.3f}".replace("-", "−")


def diff_text(iv: Interval | None) -> str | None:
    """A paired difference as ``"+0.050 [+0.020, +0.080]"`` (minus signs as −); None without one."""
    return None if iv is None else f"{_signed(iv.estimate)} [{_signed(iv.lo)}, {_signed(iv.hi)}]"


def beats(diff: Mapping[str, Any] | None, metric: str) -> bool | None:
    """True / False when the paired interval of dotted ``metric`` (``at_1.5s.roc_auc``,
    ``test/mse``) says a is better / worse than b,
    None when it does not exclude zero (or there is none)."""
    iv = interval_of(lookup(diff, metric))
    if iv is None or not excludes_zero(iv):
        return None
    return (iv.estimate < 0) == (metric.rsplit(".", 1)[-1] in LOWER_IS_BETTER)


class Claim(NamedTuple):
    """The paired difference ``a − b`` of one metric (template macro ``claim``)."""

    a: str
    b: str
    name: str  #: the metric's name
    diff: str | None  #: estimate [lo, hi]; None: no interval
    better: bool | None  #: a better / worse than b; None: the interval does not exclude zero


def claim_record(diff: Mapping[str, Any] | None, metric: str, name: str, a: str, b: str) -> Claim:
    """:class:`Claim` for the paired difference ``a − b`` of dotted ``metric``
    (``at_1.5s.roc_auc`` or ``test/mse``)."""
    return Claim(a, b, name, diff_text(interval_of(lookup(diff, metric))), beats(diff, metric))


@dataclass(frozen=True)
class FindingsRun:
    """What every part of the findings reads: the metrics, the threshold, the headline."""

    metrics: Mapping[str, Any]
    t: float  #: the THW threshold the findings quote (s)
    models: Mapping[str, Any]
    base: Mapping[str, Any]
    diffs: Mapping[str, Any]
    groups: Mapping[str, Any]
    main: str  #: the headline variant
    main_key: str  #: its predictor (the seed mean where there is one)
    collapsed: frozenset[str]

    @property
    def at(self) -> str:
        return f"at_{self.t:g}s"

    @property
    def head(self) -> Any:
        """The headline's seed group (or None)."""
        return self.groups.get(self.main) if self.main_key.endswith(SEED_MEAN) else None


def findings_run(metrics: Mapping[str, Any]) -> FindingsRun | None:
    """The :class:`FindingsRun` of a ``risk.json`` dict; None when no risk network was evaluated."""
    models: Mapping[str, Any] = metrics.get("models", {})
    main = metrics.get("main_variant") or next(iter(models), None)
    if main is None or main not in models:
        return None
    return FindingsRun(
        metrics=metrics,
        t=(metrics.get("thresholds_s") or [PAPER["threshold_s"]])[0],
        models=models,
        base=metrics.get("baselines", {}),
        diffs=metrics.get("differences", {}) or {},
        groups=metrics.get("groups", {}) or {},
        main=main,
        main_key=metrics.get("main_predictor") or main,
        collapsed=frozenset(v for v, e in models.items() if e.get("collapsed")),
    )
