"""Markdown findings of the fusion evaluation, computed from the numbers in ``fusion.json``.

Nothing is hand-typed: every statement is read from the metrics dict written by stage
``evaluate_fusion`` (layout in :mod:`traffictwin.fusion.evaluation`: ``test.<cfg>.<row>.<metric>``
with its ``<metric>_ci``, ``diff.<cfg>.<row>.vs_<base>.<metric>``, ``label.<cfg>``).

The headline metric is KLD(b) ``kld_fou_mean`` (KL over the full mass vector). A difference
between two methods is *claimed* only when its paired 95 % cluster-bootstrap interval excludes
zero; otherwise the text says "no difference shown". Estimates are quoted with their intervals.

This module computes what the findings say (:class:`FusionFindings`: formatted numbers with
their intervals, verdicts, lists of configurations); the sentences are in the template
``templates/findings.md.j2`` next to it. Configuration A against naive, the learned
registration, the other network rows, the cross table and the targets are not restated here: the
report's verdict, registration, estimate, paired-difference, cross and acceptance tables show them.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

from traffictwin.interval_rule import NO_INTERVAL, SIDES, interval_side
from traffictwin.report.prose import render_prose

__all__ = ["FusionFindings", "fusion_findings", "fusion_findings_record", "verdict"]

HEADLINE = "kld_fou_mean"
NET, NAIVE, REG, EGO = "dnn", "naive", "registered", "ego"
TEMPLATES = Path(__file__).parent / "templates"
VERDICTS = SIDES

#: configurations grouped by the verdict of a paired difference (keys: :data:`VERDICTS`)
Groups = dict[str, list[str]]


def _num(v: Any) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return float("nan")


def _fmt(v: float, digits: int = 3) -> str:
    return "n/a" if not math.isfinite(v) else f"{v:.{digits}f}"


def _get(metrics: Mapping[str, Any], cfg: str, row: str, key: str) -> float:
    return _num(metrics.get("test", {}).get(cfg, {}).get(row, {}).get(key))


def _with_ci(metrics: Mapping[str, Any], cfg: str, row: str, key: str, digits: int = 3) -> str:
    """``estimate [lo, hi]`` of ``test.<cfg>.<row>.<key>`` (just the estimate without an interval)."""
    v = _get(metrics, cfg, row, key)
    ci = metrics.get("test", {}).get(cfg, {}).get(row, {}).get(f"{key}_ci") or {}
    lo, hi = _num(ci.get("lo")), _num(ci.get("hi"))
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return _fmt(v, digits)
    return f"{_fmt(v, digits)} [{_fmt(lo, digits)}, {_fmt(hi, digits)}]"


def _diff(
    metrics: Mapping[str, Any], cfg: str, row: str, base: str, key: str
) -> Mapping[str, Any] | None:
    d = metrics.get("diff", {}).get(cfg, {}).get(row, {}).get(f"vs_{base}", {}).get(key)
    return d if isinstance(d, Mapping) else None


def verdict(d: Mapping[str, Any] | None) -> str:
    """``"lower"`` / ``"higher"`` when the paired interval of ``row − base`` excludes 0,
    ``"no difference shown"`` when it does not, ``"n/a"`` when there is none (the interval rule:
    :func:`traffictwin.interval_rule.interval_side`)."""
    return NO_INTERVAL if d is None else interval_side(d.get("lo"), d.get("hi"))


def _diff_text(d: Mapping[str, Any] | None, digits: int = 3) -> str:
    if d is None:
        return "n/a"
    return (
        f"{_fmt(_num(d.get('estimate')), digits)} [{_fmt(_num(d.get('lo')), digits)}, "
        f"{_fmt(_num(d.get('hi')), digits)}]"
    )


def _claims(
    metrics: Mapping[str, Any], cfgs: Sequence[str], row: str, base: str, key: str
) -> Groups:
    """Configurations grouped by the verdict of ``row − base`` on ``key``."""
    out: Groups = {v: [] for v in VERDICTS}
    for c in cfgs:
        out[verdict(_diff(metrics, c, row, base, key))].append(c)
    return out


class Registered(NamedTuple):
    """The classical registration at one configuration."""

    config: str
    kld: str
    vs_naive: str  #: verdict of registered − naive KLD(b)
    net_vs_registered: str  #: verdict of network − registered KLD(b)
    success_pct: str
    residual_m: str  #: median residual translation
    noisy_m: str  #: median translation error of the noisy pose


@dataclass(frozen=True)
class NoisyFindings:
    """Network vs naive from the first noisy configuration on."""

    configs: list[str]
    kld: Groups  #: verdicts of network − naive on KLD(b)
    dice: Groups  #: ... on occupied Dice
    diffs: list[tuple[str, str]]  #: (config, network − naive KLD(b) with interval)
    narrower: int  #: configurations where the network's KLD(b) IQR is narrower than naive's


@dataclass(frozen=True)
class FusionFindings:
    """Everything the fusion findings state, computed from ``fusion.json``; lists hold one
    tuple per configuration (or row), numbers are formatted with their intervals."""

    configs: list[str]
    level: str = ""  #: bootstrap level in percent
    cluster: Any = None
    n_boot: Any = None
    noisy: NoisyFindings | None = None
    kld_a: Groups = field(default_factory=dict)
    kld_a_net: list[tuple[str, str]] = field(default_factory=list)
    negative: list[str] = field(default_factory=list)  #: configs with a negative KLD(a)
    registered: list[Registered] = field(default_factory=list)
    u_auroc: list[tuple[str, str]] = field(default_factory=list)  #: (cfg, "AUROC [CI] (counts)")
    u_too_few: list[tuple[str, str]] = field(default_factory=list)  #: (cfg, counts): withheld
    u_above: list[str] = field(default_factory=list)  #: configs whose AUROC interval is above 0.5
    u_mean: list[tuple[str, str, str]] | None = None  #: (cfg, network, label); None: no label


def _iqr(m: Mapping[str, Any], c: str, row: str) -> float:
    return _get(m, c, row, "kld_fou_q75") - _get(m, c, row, "kld_fou_q25")


def _noisy(m: Mapping[str, Any], noisy: list[str]) -> NoisyFindings | None:
    if not noisy:
        return None
    return NoisyFindings(
        configs=noisy,
        kld=_claims(m, noisy, NET, NAIVE, HEADLINE),
        dice=_claims(m, noisy, NET, NAIVE, "dice_occ"),
        diffs=[(c, _diff_text(_diff(m, c, NET, NAIVE, HEADLINE))) for c in noisy],
        narrower=sum(_iqr(m, c, NET) < _iqr(m, c, NAIVE) for c in noisy),
    )


def _registered(m: Mapping[str, Any], c: str) -> Registered:
    return Registered(
        c,
        _with_ci(m, c, REG, HEADLINE),
        verdict(_diff(m, c, REG, NAIVE, HEADLINE)),
        verdict(_diff(m, c, NET, REG, HEADLINE)),
        _fmt(100 * _get(m, c, REG, "success_rate"), 0),
        _fmt(_get(m, c, REG, "residual_trans_m_median"), 2),
        _fmt(_get(m, c, REG, "noisy_trans_m_median"), 2),
    )


def auroc_counts_text(row: Mapping[str, Any]) -> str:
    """The cells behind a row's AUROC(u): ``"12,345 wrong cells in 150 pairs, 1,234,567 right"``
    (`` in N pairs`` where the pairs are counted); empty where fusion.json has no counts."""
    wrong, right = row.get("u_auroc_n_wrong"), row.get("u_auroc_n_right")
    if wrong is None or right is None:
        return ""
    pairs = row.get("u_auroc_pairs_wrong")
    where = f" in {int(pairs)} pairs" if pairs is not None else ""
    return f"{int(wrong):,} wrong cells{where}, {int(right):,} right"


def auroc_withheld(row: Mapping[str, Any]) -> bool:
    """Whether fusion.json withholds a row's AUROC(u) for too few wrong cells."""
    return row.get("u_auroc_enough") is False


def _uncertainty(m: Mapping[str, Any], configs: list[str]) -> dict[str, Any]:
    test, label = m.get("test", {}), m.get("label", {})
    finite = [c for c in configs if math.isfinite(_get(m, c, NET, "u_auroc"))]

    def counts(c: str) -> str:
        text = auroc_counts_text(test[c][NET])
        return f" ({text})" if text else ""

    return {
        "u_auroc": [(c, _with_ci(m, c, NET, "u_auroc") + counts(c)) for c in finite],
        "u_too_few": [
            (c, auroc_counts_text(test[c][NET]))
            for c in configs
            if NET in test.get(c, {}) and auroc_withheld(test[c][NET])
        ],
        "u_above": [
            c for c in finite if _num((test[c][NET].get("u_auroc_ci") or {}).get("lo")) > 0.5
        ],
        "u_mean": [
            (c, _with_ci(m, c, NET, "u_mean"), _fmt(_num(label.get(c, {}).get("u_mean"))))
            for c in configs
        ]
        if label
        else None,
    }


def fusion_findings_record(metrics: Mapping[str, Any]) -> FusionFindings:
    """What the findings of the ``fusion.json`` dict state (see module docstring)."""
    configs: list[str] = sorted(metrics.get("test", {}))
    if not configs:
        return FusionFindings(configs=[])
    boot = metrics.get("bootstrap", {})
    return FusionFindings(
        configs=configs,
        level=_fmt(100 * _num(boot.get("level", 0.95)), 0),
        cluster=boot.get("cluster", "scenario"),
        n_boot=boot.get("n_boot", "?"),
        noisy=_noisy(metrics, configs[1:]),
        kld_a=_claims(metrics, configs, NET, NAIVE, "kld_fo_mean"),
        kld_a_net=[(c, _with_ci(metrics, c, NET, "kld_fo_mean")) for c in configs],
        negative=[c for c in configs if _get(metrics, c, NET, "kld_fo_mean") < 0],
        registered=[
            _registered(metrics, c)
            for c in configs
            if math.isfinite(_get(metrics, c, REG, HEADLINE))
        ],
        **_uncertainty(metrics, configs),
    )


def fusion_findings(metrics: Mapping[str, Any]) -> str:
    """Markdown findings from the ``fusion.json`` dict (see module docstring)."""
    return render_prose(TEMPLATES, "findings.md.j2", f=fusion_findings_record(metrics))
