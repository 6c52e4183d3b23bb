"""Markdown findings of the fusion evaluation, computed from the numbers in ``fusion.json``
(written by stage ``evaluate_fusion``, layout in :mod:`traffictwin.fusion.evaluation`:
``test.<cfg>.<row>.<metric>`` with its ``<metric>_ci``, ``diff.<cfg>.<row>.vs_<base>.<metric>``,
``label.<cfg>``); the sentences are in the template ``templates/findings.md.j2``.

The headline metric is KLD(b) ``kld_fou_mean`` (KL over the full mass vector). A difference
between two methods is *claimed* only when its paired 95 % cluster-bootstrap interval excludes
zero; otherwise the text says "no difference shown". What the report's verdict, estimate,
paired-difference, registration and acceptance tables show is not restated here.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
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


def verdict(d: Mapping[str, Any] | None) -> str:
    """``"lower"`` / ``"higher"`` when the paired interval of ``row − base`` excludes 0,
    ``"no difference shown"`` when it does not, ``"n/a"`` when there is none (the interval rule:
    :func:`traffictwin.interval_rule.interval_side`)."""
    return NO_INTERVAL if d is None else interval_side(d.get("lo"), d.get("hi"))


def fusion_findings(metrics: Mapping[str, Any]) -> str:
    """Markdown findings from the ``fusion.json`` dict (see the module docstring), read by the
    template through the accessors below (config, row[, baseline], metric)."""

    def row(c: str, r: str) -> Mapping[str, Any]:
        return metrics.get("test", {}).get(c, {}).get(r, {})

    def get(c: str, r: str, key: str) -> float:
        return _num(row(c, r).get(key))

    def ci(c: str, r: str, key: str) -> str:
        """``estimate [lo, hi]`` (just the estimate without an interval)."""
        lo, hi = (_num((row(c, r).get(f"{key}_ci") or {}).get(b)) for b in ("lo", "hi"))
        est = _fmt(get(c, r, key))
        return f"{est} [{_fmt(lo)}, {_fmt(hi)}]" if math.isfinite(lo + hi) else est

    def paired(c: str, r: str, base: str, key: str) -> Mapping[str, Any] | None:
        d = metrics.get("diff", {}).get(c, {}).get(r, {}).get(f"vs_{base}", {}).get(key)
        return d if isinstance(d, Mapping) else None

    def diff(c: str, r: str, base: str, key: str) -> str:
        """``estimate [lo, hi]`` of the paired difference ``r − base``."""
        if (d := paired(c, r, base, key)) is None:
            return "n/a"
        return f"{_fmt(d.get('estimate'))} [{_fmt(d.get('lo'))}, {_fmt(d.get('hi'))}]"

    def groups(cfgs: list[str], r: str, base: str, key: str) -> dict[str, list[str]]:
        """Configurations grouped by the verdict of ``r − base`` (keys: ``SIDES``)."""
        out: dict[str, list[str]] = {v: [] for v in SIDES}
        for c in cfgs:
            out[verdict(paired(c, r, base, key))].append(c)
        return out

    def counts(c: str, r: str) -> str:
        """The cells behind a row's AUROC(u): ``"12,345 wrong cells in 150 pairs, 1,234,567
        right"`` (`` in N pairs`` where counted); empty where fusion.json has no counts."""
        wrong, right, pairs = (
            row(c, r).get(f"u_auroc_{k}") for k in ("n_wrong", "n_right", "pairs_wrong")
        )
        if wrong is None or right is None:
            return ""
        where = f" in {int(pairs)} pairs" if pairs is not None else ""
        return f"{int(wrong):,} wrong cells{where}, {int(right):,} right"

    def iqr(c: str, r: str) -> float:
        return get(c, r, "kld_fou_q75") - get(c, r, "kld_fou_q25")

    configs = sorted(metrics.get("test", {}))
    finite = [c for c in configs if math.isfinite(get(c, "dnn", "u_auroc"))]
    sel = {  # the configurations each bullet names
        "narrower": sum(iqr(c, "dnn") < iqr(c, "naive") for c in configs[1:]),
        "negative": [c for c in configs if get(c, "dnn", "kld_fo_mean") < 0],
        "finite": finite,  # with an AUROC(u); "above": its interval above 0.5
        "above": [
            c for c in finite if _num((row(c, "dnn").get("u_auroc_ci") or {}).get("lo")) > 0.5
        ],
        "few": [c for c in configs if row(c, "dnn").get("u_auroc_enough") is False],
    }
    boot = metrics.get("bootstrap", {})
    level = _fmt(100 * _num(boot.get("level", 0.95)), 0)
    context = dict(configs=configs, sel=sel, boot=boot, level=level, label=metrics.get("label", {}))
    accessors = dict(fmt=_fmt, ci=ci, diff=diff, groups=groups, counts=counts)
    return render_prose(TEMPLATES, "findings.md.j2", **context, **accessors)
