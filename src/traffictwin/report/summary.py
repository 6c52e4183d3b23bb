"""The headline metrics file ``reports/summary.json``, the only file DVC declares as ``metrics``:
the few numbers a reader compares between experiments, each with its 95 % interval, from the
detailed metrics files (each problem's :class:`~traffictwin.report.model.SectionProvider` names
them: ``headlines``). One object per problem, every leaf a number; a dotted ``<key>`` nests::

    {"<problem>": {"<key>": value, "<key>_lo": lo, "<key>_hi": hi, ...}, ...}

A number that a partial pipeline did not produce is left out, never invented. The report's
headline table shows the strongest baseline beside each (:class:`Baseline`; not in the file).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from traffictwin.interval_rule import finite


@dataclass(frozen=True)
class Baseline:
    """The strongest baseline beside a headline number: its name, estimate and 95 % interval (None
    when it has none) on the same quantity and frames, and ``src``, the metrics file#key it was
    read from."""

    name: str
    value: float
    lo: float | None
    hi: float | None
    src: str


@dataclass(frozen=True)
class Headline:
    """One headline number: ``key`` (dotted, within its problem), what it is, where it was
    measured, the estimate, its 95 % interval, the number format and the strongest baseline."""

    key: str
    quantity: str
    where: str
    value: float
    lo: float
    hi: float
    fmt: str = "g4"
    baseline: Baseline | None = None


def interval(ci: Any) -> tuple[float, float] | None:
    """``(lo, hi)`` from ``{"lo", "hi"}`` or ``[lo, hi]``; None if absent or not numbers."""
    if isinstance(ci, Mapping):
        ci = (ci.get("lo"), ci.get("hi"))
    if not isinstance(ci, (list, tuple)) or len(ci) != 2:
        return None
    lo, hi = finite(ci[0]), finite(ci[1])
    return None if lo is None or hi is None else (lo, hi)


def headline(
    key: str,
    quantity: str,
    where: str,
    value: Any,
    ci: Any,
    fmt: str = "g4",
    baseline: Baseline | None = None,
) -> list[Headline]:
    """``[Headline]`` when ``value`` is a number and ``ci`` an interval, else ``[]``."""
    v, iv = finite(value), interval(ci)
    if v is None or iv is None:
        return []
    return [Headline(key, quantity, where, v, iv[0], iv[1], fmt, baseline)]


def strongest(
    candidates: Mapping[str, tuple[Any, Any, str]], *, higher_better: bool
) -> Baseline | None:
    """The best of ``candidates`` (``{name: (value, interval, src)}``, the interval as for
    :func:`interval`, ``src`` the metrics file#key of the value), as a :class:`Baseline`; None
    when no candidate has a number. Ties go to the first candidate."""
    best: Baseline | None = None
    for name, (value, ci, src) in candidates.items():
        v = finite(value)
        if v is None or (
            best is not None and not (v > best.value if higher_better else v < best.value)
        ):
            continue
        best = Baseline(name, v, *(interval(ci) or (None, None)), src)
    return best


def summary_json(
    headlines: Mapping[str, Sequence[Headline]], banner: str = ""
) -> dict[str, dict[str, Any]]:
    """``{problem: nested {key: value, key_lo: lo, key_hi: hi}}``; problems without numbers left
    out. A smoke profile's ``banner`` goes first as ``{"run": {"note": banner}}``, so
    ``dvc metrics show`` says the numbers are not results."""
    out: dict[str, dict[str, Any]] = {"run": {"note": banner.strip("() ")}} if banner else {}
    for problem, items in headlines.items():
        for h in items:
            *parents, leaf = h.key.split(".")
            node = out.setdefault(problem, {})
            for p in parents:
                node = node.setdefault(p, {})
            node[leaf], node[f"{leaf}_lo"], node[f"{leaf}_hi"] = h.value, h.lo, h.hi
    return out
