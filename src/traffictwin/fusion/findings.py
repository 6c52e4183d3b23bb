"""Markdown findings of the fusion evaluation, computed from the numbers in ``fusion.json``.

Nothing is hand-typed: every statement is a comparison of values in the metrics dict written by
stage ``evaluate_fusion`` (layout: ``metrics["test"][cfg][method][metric]`` with methods
``ego``, ``naive``, ``naive-yager``, ``naive-cautious``, ``registered``, ``dnn``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

__all__ = ["fusion_findings"]


def _num(v: Any) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return float("nan")
    return f


def _fmt(v: float, digits: int = 3) -> str:
    return "n/a" if not math.isfinite(v) else f"{v:.{digits}f}"


def _get(metrics: Mapping[str, Any], cfg: str, method: str, key: str) -> float:
    return _num(metrics.get("test", {}).get(cfg, {}).get(method, {}).get(key))


def fusion_findings(metrics: Mapping[str, Any], kld_key: str = "kld_fo_mean") -> str:
    """Markdown findings from the ``fusion.json`` dict (see module docstring)."""
    test = metrics.get("test", {})
    configs: Sequence[str] = sorted(test)
    if not configs:
        return "## Fusion findings\n\nNo configuration was evaluated.\n"
    lines = [
        "## Fusion findings",
        "",
        f"KLD = mean over test pairs of `{kld_key.removesuffix('_mean')}`; Dice over label-known cells.",
        "",
    ]

    # table
    lines += [
        "| config | naive KLD | network KLD | registered KLD | naive Dice occ | network Dice occ | registered Dice occ |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for c in configs:
        lines.append(
            f"| {c} | {_fmt(_get(metrics, c, 'naive', kld_key))} | {_fmt(_get(metrics, c, 'dnn', kld_key))} | "
            f"{_fmt(_get(metrics, c, 'registered', kld_key))} | {_fmt(_get(metrics, c, 'naive', 'dice_occ'))} | "
            f"{_fmt(_get(metrics, c, 'dnn', 'dice_occ'))} | {_fmt(_get(metrics, c, 'registered', 'dice_occ'))} |"
        )
    lines.append("")

    # 1. network vs naive from the first noisy configuration on
    noisy = configs[1:]
    wins = [
        c for c in noisy if _get(metrics, c, "dnn", kld_key) < _get(metrics, c, "naive", kld_key)
    ]
    dice_wins = [
        c
        for c in noisy
        if _get(metrics, c, "dnn", "dice_occ") > _get(metrics, c, "naive", "dice_occ")
    ]
    if noisy:
        verdict = (
            "reproduces"
            if len(wins) == len(noisy)
            else ("partly reproduces" if wins else "does not reproduce")
        )
        lines.append(
            f"- **Network vs naive with pose noise ({', '.join(noisy)}):** the network has the lower mean KLD in "
            f"{len(wins)}/{len(noisy)} configurations ({', '.join(wins) or 'none'}) and the higher occupied Dice in "
            f"{len(dice_wins)}/{len(noisy)} ({', '.join(dice_wins) or 'none'}); this {verdict} the paper's finding that the "
            f"network beats the naive fusion from configuration B on."
        )
        spread = [
            c
            for c in noisy
            if (_get(metrics, c, "dnn", "kld_fo_q75") - _get(metrics, c, "dnn", "kld_fo_q25"))
            < (_get(metrics, c, "naive", "kld_fo_q75") - _get(metrics, c, "naive", "kld_fo_q25"))
        ]
        lines.append(
            f"- **Spread:** the network's KLD interquartile range is narrower than naive's in {len(spread)}/{len(noisy)} "
            f'noisy configurations (the paper: the network "varies much less").'
        )
        prec = [
            c
            for c in noisy
            if _get(metrics, c, "dnn", "precision_occ") < _get(metrics, c, "naive", "precision_occ")
        ]
        rec = [
            c
            for c in noisy
            if _get(metrics, c, "dnn", "recall_free") < _get(metrics, c, "naive", "recall_free")
        ]
        lines.append(
            f"- **Over-estimated occupancy:** occupied precision of the network is below naive's in {len(prec)}/{len(noisy)} "
            f"and free recall in {len(rec)}/{len(noisy)} noisy configurations (the paper reports both lower, from o_w = 3)."
        )

    # 1b. the second KLD definition, and what a negative KLD(a) means
    kb = "kld_fou_mean"
    b_known = [
        c
        for c in configs
        if math.isfinite(_get(metrics, c, "dnn", kb))
        and math.isfinite(_get(metrics, c, "naive", kb))
    ]
    if b_known:
        b_wins = [c for c in b_known if _get(metrics, c, "dnn", kb) < _get(metrics, c, "naive", kb)]
        lines.append(
            f"- **KLD (b), over the full (m_F, m_O, u):** the network has the lower mean in {len(b_wins)}/{len(b_known)} "
            f"configurations ({', '.join(b_wins) or 'none'}): "
            + ", ".join(
                f"{c} {_fmt(_get(metrics, c, 'dnn', kb))} vs naive {_fmt(_get(metrics, c, 'naive', kb))}"
                for c in b_known
            )
            + ". Mean u of the network vs naive: "
            + ", ".join(
                f"{c} {_fmt(_get(metrics, c, 'dnn', 'u_mean'))} vs {_fmt(_get(metrics, c, 'naive', 'u_mean'))}"
                for c in b_known
            )
            + "."
        )
    negative = [c for c in configs if _get(metrics, c, "dnn", kld_key) < 0]
    if negative:
        lines.append(
            f"- **Negative KLD (a) ({', '.join(negative)}):** KLD (a) compares the two masses (m_F, m_O) only, which do not "
            "sum to 1, so it is not a divergence of distributions: it goes below 0 when the prediction puts more mass on "
            "free/occupied than the label, i.e. it rewards over-confidence. A negative value is not a fusion better than "
            "the exact one; read it together with KLD (b)."
        )

    # 2. configuration A
    a = configs[0]
    ka, kn = _get(metrics, a, "dnn", kld_key), _get(metrics, a, "naive", kld_key)
    if math.isfinite(ka) and math.isfinite(kn):
        rel = "worse than" if ka > kn else "at least as good as"
        lines.append(
            f"- **Configuration {a} (no noise):** the network's mean KLD is {_fmt(ka)} vs naive {_fmt(kn)}: the network is "
            f"{rel} the naive fusion, which at zero noise equals the label construction"
            f"{' (as in the paper)' if ka > kn else ' (the paper found the network worse here)'}; occupied Dice "
            f"{_fmt(_get(metrics, a, 'dnn', 'dice_occ'))} vs {_fmt(_get(metrics, a, 'naive', 'dice_occ'))}."
        )

    # 3. registration
    reg_lines = []
    for c in configs:
        kr = _get(metrics, c, "registered", kld_key)
        if not math.isfinite(kr):
            continue
        kn, kd = _get(metrics, c, "naive", kld_key), _get(metrics, c, "dnn", kld_key)
        pos = (
            "between naive and the network"
            if min(kn, kd) <= kr <= max(kn, kd)
            else ("better than both" if kr < min(kn, kd) else "worse than both")
        )
        reg_lines.append(
            f"{c}: KLD {_fmt(kr)} ({pos}), success {_fmt(100 * _get(metrics, c, 'registered', 'success_rate'), 0)} %, "
            f"residual translation median {_fmt(_get(metrics, c, 'registered', 'residual_trans_m_median'), 2)} m "
            f"(noisy pose {_fmt(_get(metrics, c, 'registered', 'noisy_trans_m_median'), 2)} m)"
        )
    if reg_lines:
        lines.append(
            "- **Classical registration (Fourier–Mellin + ECC, then Dempster):** "
            + "; ".join(reg_lines)
            + "."
        )

    # 4. uncertainty
    au = {c: _get(metrics, c, "dnn", "u_auroc") for c in configs}
    finite = {c: v for c, v in au.items() if math.isfinite(v)}
    if finite:
        good = [c for c, v in finite.items() if v > 0.5]
        lines.append(
            "- **Does u flag errors?** AUROC of the network's u for wrongly classified cells: "
            + ", ".join(f"{c} {_fmt(v)}" for c, v in finite.items())
            + f" — {'above' if len(good) == len(finite) else 'not always above'} chance (0.5)"
            + (
                f" in {len(good)}/{len(finite)} configurations."
                if len(good) != len(finite)
                else "."
            )
        )

    # 5. cross table
    cross = metrics.get("cross", {})
    if cross:
        own_best = []
        for c in configs:
            col = {n: _num(cross.get(n, {}).get(c, {}).get(kld_key)) for n in cross}
            col = {n: v for n, v in col.items() if math.isfinite(v)}
            if col:
                best = min(col, key=col.get)
                own_best.append(f"{c}: {best}")
        if own_best:
            lines.append(
                "- **Cross table (lowest KLD network per test set):** " + ", ".join(own_best) + "."
            )
    return "\n".join(lines) + "\n"
