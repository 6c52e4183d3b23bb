"""Markdown findings of the fusion evaluation, computed from the numbers in ``fusion.json``.

Nothing is hand-typed: every statement is read from the metrics dict written by stage
``evaluate_fusion`` (layout in :mod:`traffictwin.fusion.evaluation`: ``test.<cfg>.<row>.<metric>``
with its ``<metric>_ci``, ``diff.<cfg>.<row>.vs_<base>.<metric>``, ``label.<cfg>``, ``targets``).

The headline metric is KLD(b) ``kld_fou_mean`` (KL over the full mass vector). A difference
between two methods is *claimed* only when its paired 95 % cluster-bootstrap interval excludes
zero; otherwise the text says "no difference shown". Estimates are quoted with their intervals.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

__all__ = ["fusion_findings", "verdict"]

HEADLINE = "kld_fou_mean"
NET, NAIVE, REG, EGO = "dnn", "naive", "registered", "ego"


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
    ``"no difference shown"`` when it does not, ``"n/a"`` when there is none."""
    if d is None:
        return "n/a"
    lo, hi = _num(d.get("lo")), _num(d.get("hi"))
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return "n/a"
    if hi < 0:
        return "lower"
    if lo > 0:
        return "higher"
    return "no difference shown"


def _diff_text(d: Mapping[str, Any] | None, digits: int = 3) -> str:
    if d is None:
        return "n/a"
    return (
        f"{_fmt(_num(d.get('estimate')), digits)} [{_fmt(_num(d.get('lo')), digits)}, "
        f"{_fmt(_num(d.get('hi')), digits)}]"
    )


def _claims(
    metrics: Mapping[str, Any], cfgs: Sequence[str], row: str, base: str, key: str
) -> dict[str, list[str]]:
    """Configurations grouped by the verdict of ``row − base`` on ``key``."""
    out: dict[str, list[str]] = {"lower": [], "higher": [], "no difference shown": [], "n/a": []}
    for c in cfgs:
        out[verdict(_diff(metrics, c, row, base, key))].append(c)
    return out


def _claim_sentence(groups: Mapping[str, list[str]], low: str, high: str) -> str:
    parts = []
    if groups["lower"]:
        parts.append(f"{low} at {', '.join(groups['lower'])}")
    if groups["higher"]:
        parts.append(f"{high} at {', '.join(groups['higher'])}")
    if groups["no difference shown"]:
        parts.append(f"no difference shown at {', '.join(groups['no difference shown'])}")
    if groups["n/a"]:
        parts.append(f"no interval at {', '.join(groups['n/a'])}")
    return "; ".join(parts) or "nothing evaluated"


def fusion_findings(metrics: Mapping[str, Any]) -> str:
    """Markdown findings from the ``fusion.json`` dict (see module docstring)."""
    test = metrics.get("test", {})
    configs: Sequence[str] = sorted(test)
    if not configs:
        return "## Fusion findings\n\nNo configuration was evaluated.\n"
    boot = metrics.get("bootstrap", {})
    level = _num(boot.get("level", 0.95))
    lines = [
        "## Fusion findings",
        "",
        "KLD(b) = mean over test pairs of KL(label ‖ prediction) over the full mass vector "
        "(m_F, m_O, u) — the headline; KLD(a) over (m_F, m_O) only is kept for comparison with the "
        f"paper. Dice over label-known cells, pooled. Brackets: {_fmt(100 * level, 0)} % cluster-"
        f"bootstrap intervals ({boot.get('cluster', 'scenario')}, {boot.get('n_boot', '?')} "
        "resamples); a difference is claimed only when its paired interval excludes 0, otherwise "
        '"no difference shown".',
        "",
        "| config | naive KLD(b) | network KLD(b) | registered KLD(b) | network − naive KLD(b) "
        "| naive Dice occ | network Dice occ | registered Dice occ |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for c in configs:
        lines.append(
            f"| {c} | {_with_ci(metrics, c, NAIVE, HEADLINE)} | {_with_ci(metrics, c, NET, HEADLINE)} | "
            f"{_with_ci(metrics, c, REG, HEADLINE)} | "
            f"{_diff_text(_diff(metrics, c, NET, NAIVE, HEADLINE))} | "
            f"{_with_ci(metrics, c, NAIVE, 'dice_occ')} | {_with_ci(metrics, c, NET, 'dice_occ')} | "
            f"{_with_ci(metrics, c, REG, 'dice_occ')} |"
        )
    lines.append("")

    # 1. network vs naive from the first noisy configuration on
    noisy = configs[1:]
    if noisy:
        k = _claims(metrics, noisy, NET, NAIVE, HEADLINE)
        dc = _claims(metrics, noisy, NET, NAIVE, "dice_occ")
        wins = k["lower"]
        verdict_text = (
            "reproduces"
            if len(wins) == len(noisy)
            else ("partly reproduces" if wins else "does not reproduce")
        )
        lines.append(
            f"- **Network vs naive with pose noise ({', '.join(noisy)}), KLD(b):** the network is "
            f"lower in {len(wins)}/{len(noisy)} configurations ({', '.join(wins) or 'none'}): "
            f"{_claim_sentence(k, 'network lower', 'network higher')}. Differences network − naive: "
            + ", ".join(f"{c} {_diff_text(_diff(metrics, c, NET, NAIVE, HEADLINE))}" for c in noisy)
            + f". This {verdict_text} the paper's finding that the network beats the naive fusion "
            "from configuration B on."
        )
        lines.append(
            f"- **Occupied Dice, network vs naive:** "
            f"{_claim_sentence(dc, 'network lower', 'network higher')}."
        )
        spread = [
            c
            for c in noisy
            if (_get(metrics, c, NET, "kld_fou_q75") - _get(metrics, c, NET, "kld_fou_q25"))
            < (_get(metrics, c, NAIVE, "kld_fou_q75") - _get(metrics, c, NAIVE, "kld_fou_q25"))
        ]
        lines.append(
            f"- **Spread (point estimates, no interval):** the network's KLD(b) interquartile range "
            f"is narrower than naive's in {len(spread)}/{len(noisy)} noisy configurations (the "
            'paper: the network "varies much less").'
        )

    # 2. KLD(a), for comparison with the paper
    ka = _claims(metrics, configs, NET, NAIVE, "kld_fo_mean")
    lines.append(
        "- **KLD(a) over (m_F, m_O), for comparison with the paper:** network vs naive: "
        f"{_claim_sentence(ka, 'network lower', 'network higher')}; network "
        + ", ".join(f"{c} {_with_ci(metrics, c, NET, 'kld_fo_mean')}" for c in configs)
        + "."
    )
    negative = [c for c in configs if _get(metrics, c, NET, "kld_fo_mean") < 0]
    if negative:
        lines.append(
            f"- **Negative KLD(a) ({', '.join(negative)}):** KLD(a) compares the two masses (m_F, m_O) "
            "only, which do not sum to 1, so it is not a divergence of distributions: it goes below 0 "
            "when the prediction puts more mass on free/occupied than the label, i.e. it rewards "
            "over-confidence. This is why KLD(b) is the headline."
        )

    # 3. configuration A (no noise)
    a = configs[0]
    if math.isfinite(_get(metrics, a, NET, HEADLINE)):
        v = verdict(_diff(metrics, a, NET, NAIVE, HEADLINE))
        word = {"higher": "worse than", "lower": "better than"}.get(v, "not shown different from")
        lines.append(
            f"- **Configuration {a} (no noise):** network KLD(b) {_with_ci(metrics, a, NET, HEADLINE)} "
            f"vs naive {_with_ci(metrics, a, NAIVE, HEADLINE)}: the network is {word} the naive "
            "fusion, which at zero noise equals the label construction; occupied Dice "
            f"{_with_ci(metrics, a, NET, 'dice_occ')} vs {_with_ci(metrics, a, NAIVE, 'dice_occ')}."
        )

    # 4. registration and the network against it
    reg_lines = []
    for c in configs:
        if not math.isfinite(_get(metrics, c, REG, HEADLINE)):
            continue
        vs_naive = verdict(_diff(metrics, c, REG, NAIVE, HEADLINE))
        net_vs_reg = verdict(_diff(metrics, c, NET, REG, HEADLINE))
        reg_lines.append(
            f"{c}: KLD(b) {_with_ci(metrics, c, REG, HEADLINE)} (vs naive: {vs_naive}; network vs "
            f"registered: {net_vs_reg}), success "
            f"{_fmt(100 * _get(metrics, c, REG, 'success_rate'), 0)} %, residual translation median "
            f"{_fmt(_get(metrics, c, REG, 'residual_trans_m_median'), 2)} m (noisy pose "
            f"{_fmt(_get(metrics, c, REG, 'noisy_trans_m_median'), 2)} m)"
        )
    if reg_lines:
        lines.append(
            "- **Classical registration (Fourier–Mellin + ECC, then Dempster):** "
            + "; ".join(reg_lines)
            + "."
        )

    # 4b. the learned registration against the classical one (same pairs, paired differences)
    learned_lines = []
    for c in configs:
        if not math.isfinite(_get(metrics, c, "learned", "success_rate")):
            continue
        d = _diff(metrics, c, "learned", REG, "success_rate")
        dt = _diff_text(d, 3) if d is not None else "n/a"
        learned_lines.append(
            f"{c}: success {_with_ci(metrics, c, 'learned', 'success_rate')} vs registered "
            f"{_fmt(_get(metrics, c, REG, 'success_rate'))} (difference {dt}: "
            f"{verdict(d)}), fallback {_fmt(100 * _get(metrics, c, 'learned', 'fallback_rate'), 0)} %, "
            f"p90 error {_fmt(_get(metrics, c, 'learned', 'residual_trans_m_p90'), 2)} m / "
            f"{_fmt(_get(metrics, c, 'learned', 'residual_rot_deg_p90'), 2)}° "
            f"(registered {_fmt(_get(metrics, c, REG, 'residual_trans_m_p90'), 2)} m / "
            f"{_fmt(_get(metrics, c, REG, 'residual_rot_deg_p90'), 2)}°)"
        )
    if learned_lines:
        lines.append(
            "- **Learned registration (cost volume over rotations × shifts, then Dempster) vs classical:** "
            + "; ".join(learned_lines)
            + "."
        )

    # 5. the other network rows (loss ablation, hybrids)
    rows = []
    for c in configs:
        rows += [
            r
            for r in test.get(c, {})
            if r != NET
            and r.split("[")[0] in (NET, "registered+network", "learned+network")
            and r not in rows
        ]
    for r in sorted(rows):
        at = [c for c in configs if r in test.get(c, {})]
        parts = []
        for c in at:
            parts.append(
                f"{c}: KLD(b) {_with_ci(metrics, c, r, HEADLINE)} (vs naive: "
                f"{verdict(_diff(metrics, c, r, NAIVE, HEADLINE))}, vs registered: "
                f"{verdict(_diff(metrics, c, r, REG, HEADLINE))}), Dice occ "
                f"{_with_ci(metrics, c, r, 'dice_occ')} (vs registered: "
                f"{verdict(_diff(metrics, c, r, REG, 'dice_occ'))}), mean u "
                f"{_with_ci(metrics, c, r, 'u_mean')}"
            )
        lines.append(f"- **Row `{r}`:** " + "; ".join(parts) + ".")

    # 6. uncertainty
    au = {c: _get(metrics, c, NET, "u_auroc") for c in configs}
    finite = [c for c, v in au.items() if math.isfinite(v)]
    if finite:
        above = [c for c in finite if _num((test[c][NET].get("u_auroc_ci") or {}).get("lo")) > 0.5]
        lines.append(
            "- **Does u flag errors?** AUROC of the network's u for wrongly classified cells: "
            + ", ".join(f"{c} {_with_ci(metrics, c, NET, 'u_auroc')}" for c in finite)
            + f"; above chance (interval above 0.5) in {len(above)}/{len(finite)} configurations"
            + (f" ({', '.join(above)})." if above else ".")
        )
    label = metrics.get("label", {})
    if label:
        lines.append(
            "- **Mean u, network vs label:** "
            + ", ".join(
                f"{c} {_with_ci(metrics, c, NET, 'u_mean')} vs "
                f"{_fmt(_num(label.get(c, {}).get('u_mean')))}"
                for c in configs
            )
            + "."
        )

    # 7. targets
    targets = metrics.get("targets", {})
    if targets:
        by = {
            s: [n for n, t in sorted(targets.items()) if t.get("status") == s]
            for s in ("pass", "fail", "not evaluated")
        }
        lines.append(
            f"- **Targets (issues 14 and 15):** {len(by['pass'])} pass, {len(by['fail'])} fail, "
            f"{len(by['not evaluated'])} not evaluated"
            + (f"; failing: {', '.join(by['fail'])}" if by["fail"] else "")
            + (f"; not evaluated: {', '.join(by['not evaluated'])}" if by["not evaluated"] else "")
            + "."
        )

    # 8. cross table
    cross = metrics.get("cross", {})
    if cross:
        own_best = []
        for c in configs:
            col = {n: _num(cross.get(n, {}).get(c, {}).get(HEADLINE)) for n in sorted(cross)}
            col = {n: v for n, v in col.items() if math.isfinite(v)}
            if col:
                own_best.append(f"{c}: {min(col, key=col.get)}")
        if own_best:
            lines.append(
                "- **Cross table (lowest KLD(b) network per test set; point estimates on a subset):** "
                + ", ".join(own_best)
                + "."
            )
    return "\n".join(lines) + "\n"
