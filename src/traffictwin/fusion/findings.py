"""Markdown findings of the fusion evaluation, computed from the numbers in ``fusion.json``.

Nothing is hand-typed: every statement is read from the metrics dict written by stage
``evaluate_fusion`` (layout in :mod:`traffictwin.fusion.evaluation`: ``test.<cfg>.<row>.<metric>``
with its ``<metric>_ci``, ``diff.<cfg>.<row>.vs_<base>.<metric>``, ``label.<cfg>``).

The headline metric is KLD(b) ``kld_fou_mean`` (KL over the full mass vector). A difference
between two methods is *claimed* only when its paired 95 % cluster-bootstrap interval excludes
zero; otherwise the text says "no difference shown". The sentences are in the template
``templates/findings.md.j2``, which reads the numbers through the accessors of
:func:`fusion_findings` (formatted with their intervals). Configuration A against naive, the
classical and the learned registration, the other network rows, the cross table and the targets
are not restated here: the report's verdict, estimate, paired-difference, registration and
acceptance tables show them.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from functools import partial
from pathlib import Path
from typing import Any

from traffictwin.interval_rule import NO_INTERVAL, SIDES, interval_side
from traffictwin.report.prose import render_prose

__all__ = ["fusion_findings", "verdict"]

TEMPLATES = Path(__file__).parent / "templates"


def _num(v: Any) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return float("nan")


def _fmt(v: Any, digits: int = 3) -> str:
    return "n/a" if not math.isfinite(v := _num(v)) else f"{v:.{digits}f}"


def _row(m: Mapping[str, Any], cfg: str, row: str) -> Mapping[str, Any]:
    return m.get("test", {}).get(cfg, {}).get(row, {})


def _get(m: Mapping[str, Any], cfg: str, row: str, key: str) -> float:
    return _num(_row(m, cfg, row).get(key))


def _with_ci(m: Mapping[str, Any], cfg: str, row: str, key: str) -> str:
    """``estimate [lo, hi]`` of ``test.<cfg>.<row>.<key>`` (just the estimate without an interval)."""
    ci = _row(m, cfg, row).get(f"{key}_ci") or {}
    lo, hi = _num(ci.get("lo")), _num(ci.get("hi"))
    est = _fmt(_get(m, cfg, row, key))
    return (
        est if not (math.isfinite(lo) and math.isfinite(hi)) else f"{est} [{_fmt(lo)}, {_fmt(hi)}]"
    )


def _diff(m: Mapping[str, Any], cfg: str, row: str, base: str, key: str) -> Mapping | None:
    d = m.get("diff", {}).get(cfg, {}).get(row, {}).get(f"vs_{base}", {}).get(key)
    return d if isinstance(d, Mapping) else None


def verdict(d: Mapping[str, Any] | None) -> str:
    """``"lower"`` / ``"higher"`` when the paired interval of ``row − base`` excludes 0,
    ``"no difference shown"`` when it does not, ``"n/a"`` when there is none (the interval rule:
    :func:`traffictwin.interval_rule.interval_side`)."""
    return NO_INTERVAL if d is None else interval_side(d.get("lo"), d.get("hi"))


def _diff_text(m: Mapping[str, Any], cfg: str, row: str, base: str, key: str) -> str:
    """``estimate [lo, hi]`` of the paired difference ``row − base`` on ``key`` at ``cfg``."""
    if (d := _diff(m, cfg, row, base, key)) is None:
        return "n/a"
    return f"{_fmt(d.get('estimate'))} [{_fmt(d.get('lo'))}, {_fmt(d.get('hi'))}]"


def _groups(
    m: Mapping[str, Any], cfgs: Sequence[str], row: str, base: str, key: str
) -> dict[str, list[str]]:
    """Configurations grouped by the verdict of ``row − base`` on ``key`` (keys: ``SIDES``)."""
    out: dict[str, list[str]] = {v: [] for v in SIDES}
    for c in cfgs:
        out[verdict(_diff(m, c, row, base, key))].append(c)
    return out


def _iqr(m: Mapping[str, Any], cfg: str, row: str) -> float:
    return _get(m, cfg, row, "kld_fou_q75") - _get(m, cfg, row, "kld_fou_q25")


def _counts(m: Mapping[str, Any], cfg: str, row: str) -> str:
    """The cells behind a row's AUROC(u): ``"12,345 wrong cells in 150 pairs, 1,234,567 right"``
    (`` in N pairs`` where the pairs are counted); empty where fusion.json has no counts."""
    r = _row(m, cfg, row)
    wrong, right, pairs = (r.get(f"u_auroc_{k}") for k in ("n_wrong", "n_right", "pairs_wrong"))
    if wrong is None or right is None:
        return ""
    where = f" in {int(pairs)} pairs" if pairs is not None else ""
    return f"{int(wrong):,} wrong cells{where}, {int(right):,} right"


def _selections(m: Mapping[str, Any], configs: Sequence[str]) -> dict[str, Any]:
    """The configurations each bullet names: ``narrower`` (how many noisy ones have a narrower
    network KLD(b) IQR than naive), ``negative`` (negative network KLD(a)), ``finite`` (an AUROC(u)),
    ``above`` (its interval above 0.5), ``few`` (AUROC withheld: too few wrong cells)."""
    finite = [c for c in configs if math.isfinite(_get(m, c, "dnn", "u_auroc"))]
    return {
        "narrower": sum(_iqr(m, c, "dnn") < _iqr(m, c, "naive") for c in configs[1:]),
        "negative": [c for c in configs if _get(m, c, "dnn", "kld_fo_mean") < 0],
        "finite": finite,
        "above": [
            c for c in finite if _num((_row(m, c, "dnn").get("u_auroc_ci") or {}).get("lo")) > 0.5
        ],
        "few": [c for c in configs if _row(m, c, "dnn").get("u_auroc_enough") is False],
    }


def fusion_findings(metrics: Mapping[str, Any]) -> str:
    """Markdown findings from the ``fusion.json`` dict (see module docstring)."""
    accessors = {
        "get": _get,
        "ci": _with_ci,
        "diff": _diff_text,
        "groups": _groups,
        "row": _row,
        "counts": _counts,
    }
    return render_prose(
        TEMPLATES,
        "findings.md.j2",
        configs=(configs := sorted(metrics.get("test", {}))),
        sel=_selections(metrics, configs),
        boot=(boot := metrics.get("bootstrap", {})),
        level=_fmt(100 * _num(boot.get("level", 0.95)), 0),
        label=metrics.get("label", {}),
        fmt=_fmt,
        **{k: partial(f, metrics) for k, f in accessors.items()},
    )
