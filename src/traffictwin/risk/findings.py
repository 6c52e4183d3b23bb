"""Findings of the risk evaluation as markdown bullets, generated from ``reports/metrics/risk.json``.

:func:`findings` is called by the report stage (``traffictwin.report.render.findings``); every
number comes from the metrics dict (layout: :mod:`traffictwin.risk.evaluation`), nothing is typed
by hand. Missing entries (a variant or a baseline not evaluated, a metric undefined → ``None``)
are skipped, never invented.

Rules: a difference between two predictors is *claimed* ("X beats Y: +0.05 [0.02, 0.08]") only
when its paired sequence-bootstrap interval excludes zero (:func:`traffictwin.stats.excludes_zero`);
otherwise the text says "no significant difference" with the interval. A collapsed model (one
output for every frame) is listed as a failed run and never interpreted. The corridor rule on
ground-truth disparity sees perfect stereo but a straight corridor: a reference, not an oracle.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from traffictwin.risk.evaluation import GT_INPUT, LOWER_IS_BETTER, PAPER, SEED_MEAN
from traffictwin.stats import Interval, excludes_zero

#: how findings name the baselines
BASELINE_NAMES = {
    "train_mean": "training-mean predictor",
    "train_median": "majority class (training median)",
    "speed_only": "speed-only baseline (isotonic fit on the training split)",
    "geometric_sgm": "corridor rule (SGM disparity + speed, corridor chosen on validation)",
    "geometric_gt": "corridor rule on ground-truth disparity (perfect stereo, straight corridor)",
}
#: metrics the comparisons quote, with their names
COMPARED = (("roc_auc", "ROC-AUC"), ("balanced_accuracy", "balanced accuracy"))
REGIONS = {
    "risk_thw_corridor": "corridor",
    "risk_thw_paper": "paper",
    "risk_thw_fov": "camera_fov",
}


def _g(d: Any, path: str) -> Any:
    for k in path.split("|"):
        if not isinstance(d, Mapping) or k not in d:
            return None
        d = d[k]
    return d


def _f(x: Any) -> float | None:
    return float(x) if isinstance(x, (int, float)) and not isinstance(x, bool) else None


def _pct(x: float | None) -> str:
    return "n/a" if x is None else f"{100 * x:.2f} %"


def _num(x: float | None, fmt: str = ".4f") -> str:
    return "n/a" if x is None else format(x, fmt)


def _with_ci(d: Any, key: str, fmt: str = ".3f", pct: bool = False) -> str:
    """``value [lo, hi]`` of ``d[key]`` and ``d[key + "_ci"]`` (just the value without interval)."""
    v = _f(_g(d, key))
    ci = _g(d, f"{key}_ci") or {}
    lo, hi = _f(ci.get("lo")), _f(ci.get("hi"))
    show = (lambda x: _pct(x)) if pct else (lambda x: _num(x, fmt))
    if v is None:
        return "n/a"
    if lo is None or hi is None:
        return show(v)
    return f"{show(v)} [{show(lo)}, {show(hi)}]"


def _interval(d: Any) -> Interval | None:
    if not isinstance(d, Mapping):
        return None
    e, lo, hi = _f(d.get("estimate")), _f(d.get("lo")), _f(d.get("hi"))
    if e is None or lo is None or hi is None or math.isnan(lo) or math.isnan(hi):
        return None
    return Interval(e, lo, hi)


def _signed(x: float) -> str:
    return f"{x:+.3f}".replace("-", "−")


def claim(diff: Mapping[str, Any] | None, metric: str, name: str, a: str, b: str) -> str:
    """One comparison sentence for the paired difference ``a − b`` of ``metric`` (``at_…|roc_auc``
    or ``test/mse``): a claim when its interval excludes zero, else "no significant difference"."""
    iv = _interval(_g(diff, metric))
    if iv is None:
        return f"{a} vs {b} in {name}: no interval"
    text = f"{_signed(iv.estimate)} [{_signed(iv.lo)}, {_signed(iv.hi)}]"
    if not excludes_zero(iv):
        return f"{a} vs {b}: no significant difference in {name} ({a} − {b} = {text})"
    better = (iv.estimate < 0) == (metric.split("|")[-1] in LOWER_IS_BETTER)
    return f"{a} {'beats' if better else 'is worse than'} {b} in {name}: {text}"


def beats(diff: Mapping[str, Any] | None, metric: str) -> bool | None:
    """True / False when the paired interval of ``metric`` says a is better / worse than b,
    None when it does not exclude zero (or there is none)."""
    iv = _interval(_g(diff, metric))
    if iv is None or not excludes_zero(iv):
        return None
    return (iv.estimate < 0) == (metric.split("|")[-1] in LOWER_IS_BETTER)


def _describe(e: Mapping[str, Any]) -> str:
    inputs = "+".join(e.get("inputs") or []) or "?"
    parts = [inputs + (" + speed" if e.get("speed") else ", no speed")]
    if e.get("label"):
        parts.append(f"label {e['label']}")
    if e.get("objective") and e.get("objective") != "mse":
        parts.append(f"objective {e['objective']}")
    return ", ".join(parts)


def findings(metrics: Mapping[str, Any]) -> str:
    """Markdown bullet list: paper comparison, failed runs, seeds, baselines and paired
    comparisons (claims only where the CI excludes zero), critical shares, the region effect,
    situations, targets, data."""
    t = (metrics.get("thresholds_s") or [PAPER["threshold_s"]])[0]
    at = f"at_{t:g}s"
    models: Mapping[str, Any] = metrics.get("models", {})
    base: Mapping[str, Any] = metrics.get("baselines", {})
    diffs: Mapping[str, Any] = metrics.get("differences", {}) or {}
    groups: Mapping[str, Any] = metrics.get("groups", {}) or {}
    main = metrics.get("main_variant") or next(iter(models), None)
    if main is None or main not in models:
        return "- No risk network was evaluated."
    collapsed = {v for v, e in models.items() if e.get("collapsed")}
    main_key = metrics.get("main_predictor") or main
    m = models[main]
    head = groups.get(main) if main_key.endswith(SEED_MEAN) else None
    hm = head if isinstance(head, Mapping) else m  # the headline's figures (seed mean if any)
    out: list[str] = []

    # 1. the paper's numbers
    mse = _f(m.get("test/mse"))
    if mse is not None:
        rel = "below" if mse < PAPER["test/mse"] else "above"
        seeds = (
            f" (seed mean over {head.get('n_seeds')} seeds: MSE {_with_ci(hm, 'test/mse', '.5f')}, "
            f"accuracy {_with_ci(hm, f'{at}|accuracy', pct=True)})"
            if head
            else ""
        )
        out.append(
            f"**Paper comparison ({main}, {m.get('test/n')} test frames, label {m.get('label')}).** "
            f"Test MSE {_with_ci(m, 'test/mse', '.5f')} vs the paper's {PAPER['test/mse']:.5f} "
            f"({mse / PAPER['test/mse']:.2f}× — {rel}); accuracy at THW {t:g} s "
            f"{_with_ci(m, f'{at}|accuracy', pct=True)} vs the paper's {_pct(PAPER['accuracy'])} and "
            f"Wang & Kato's {_pct(PAPER['wang_kato_accuracy'])}; balanced accuracy "
            f"{_with_ci(m, f'{at}|balanced_accuracy', pct=True)}, F1 {_with_ci(m, f'{at}|f1')}, "
            f"ROC-AUC {_with_ci(m, f'{at}|roc_auc')}{seeds}. Critical share of the test frames "
            f"{_pct(_f(_g(m, f'{at}|critical_fraction_true')))} (the paper's data set: "
            f"{_pct(76789 / PAPER['n_frames'])}), so raw accuracies are only comparable with the "
            "majority baseline beside them."
            + (
                f" **{main} collapsed**: the numbers above are those of a constant output."
                if main in collapsed
                else ""
            )
        )

    # 1b. the shipped predictor (chosen on validation) and the learned model vs the corridor rule
    shipped, learned = metrics.get("shipped"), metrics.get("learned")
    sel = metrics.get("selection") or {}
    if shipped and isinstance(models.get(shipped), Mapping):
        sm = models[shipped]
        rules = sel.get("rules") or {}
        out.append(
            f"**Shipped predictor** (what `traffictwin risk` and the registered risk model serve): "
            f"{sel.get('shipped_from', shipped)} ({sel.get('shipped_kind', '?')}), chosen on the "
            f"validation split by ROC-AUC among the network runs, the hybrid runs and the corridor "
            f"rule (corridor half-widths chosen on validation: SGM {rules.get('geometric_sgm', 'n/a')} m, "
            f"GT {rules.get('geometric_gt', 'n/a')} m). On the test split: balanced accuracy "
            f"{_with_ci(sm, f'{at}|balanced_accuracy', pct=True)} at THW {t:g} s and "
            f"{_with_ci(sm, 'at_1s|balanced_accuracy', pct=True)} at 1 s, ROC-AUC "
            f"{_with_ci(sm, f'{at}|roc_auc')}, median |THW error| on critical frames "
            f"{_with_ci(sm, 'test/thw_median_error_critical_s', '.3f')} s."
        )
    if learned:
        d = diffs.get(f"{learned}|geometric_sgm")
        if d is not None:
            verdict = beats(d, f"{at}|roc_auc")
            plain = {
                True: "the learned model beats the corridor rule",
                False: "geometry wins: the corridor rule beats the learned model",
                None: "the learned model does not beat the corridor rule (no significant difference)",
            }[verdict]
            holm = ((metrics.get("comparisons") or {}).get("secondary_holm") or {}).get(
                "p_adjusted"
            ) or {}
            held = sum(1 for v in holm.values() if v < 0.05)
            out.append(
                f"**Learning vs geometry** (the primary comparison: {learned}, seeds and sequences "
                f"resampled, against the validation-tuned SGM corridor rule): {plain}; "
                + "; ".join(
                    claim(d, f"{at}|{k}", name, learned, "geometric_sgm") for k, name in COMPARED
                )
                + f". Every other paired difference is secondary: {held} of {len(holm)} keep "
                "p < 0.05 after Holm's correction (risk.json `comparisons`)."
            )

    # 2. failed runs
    if collapsed:
        out.append(
            "**Failed runs (collapsed: one output for every test frame, prediction std < "
            f"{_num(_f(metrics.get('collapse_std')), 'g')}):** "
            + ", ".join(
                f"{v} (std {_num(_f(models[v].get('pred_std')), '.2g')})" for v in sorted(collapsed)
            )
            + ". They are not interpreted and take no part in seed means."
        )

    # 3. seeds of the headline
    if head:
        sd = head.get("seed_sd") or {}
        per = ", ".join(
            f"{v} {_num(_f(_g(models.get(v), f'{at}|roc_auc')), '.3f')}"
            for v in head.get("members", [])
        )
        out.append(
            f"**Seeds ({main}):** ROC-AUC per run {per}; seed mean {_with_ci(head, f'{at}|roc_auc')} "
            f"(seed sd {_num(_f(sd.get(f'{at}.roc_auc')), '.3f')}); balanced accuracy seed mean "
            f"{_with_ci(head, f'{at}|balanced_accuracy', pct=True)} (seed sd "
            f"{_pct(_f(sd.get(f'{at}.balanced_accuracy')))}). Intervals resample the sequences once "
            "and draw the seeds with replacement inside each resample (seed variation is in the interval)."
        )

    # 4. baselines and the headline against them
    parts = []
    for b in ("speed_only", "geometric_sgm", "geometric_gt", "train_median"):
        e = base.get(b)
        if not isinstance(e, Mapping):
            continue
        parts.append(
            f"{BASELINE_NAMES[b]}: ROC-AUC {_with_ci(e, f'{at}|roc_auc')}, balanced accuracy "
            f"{_with_ci(e, f'{at}|balanced_accuracy', pct=True)}, MSE {_with_ci(e, 'test/mse', '.5f')}"
        )
    speed = base.get("speed_only") or {}
    vmin = _f(speed.get(f"critical_speed_at_{t:g}s"))
    if vmin is not None:
        parts.append(f"the speed-only baseline calls every frame above {vmin:.1f} m/s critical")
    if parts:
        claims = []
        if main_key not in collapsed:
            for b in ("speed_only", "geometric_sgm", "geometric_gt", "train_median"):
                d = diffs.get(f"{main_key}|{b}")
                if d is None:
                    continue
                nb = b + (" (GT disparity)" if b in GT_INPUT else "")
                claims += [claim(d, f"{at}|{k}", name, main_key, nb) for k, name in COMPARED[:1]]
                claims.append(claim(d, "test/mse", "MSE", main_key, nb))
        out.append(
            "**Baselines on the same frames (scored on the headline's label):** "
            + "; ".join(parts)
            + "."
            + (" " + "; ".join(claims) + "." if claims else "")
        )

    # 5. every variant vs the speed-only baseline on its own label
    rows = []
    for v in sorted(models):
        e = models[v]
        if v in collapsed:
            rows.append(f"{v}: failed run (collapsed), not compared")
            continue
        d = diffs.get(f"{v}|speed_only")
        if d is None:
            continue
        verdict = beats(d, f"{at}|roc_auc")
        word = {True: "beats it", False: "is worse", None: "no significant difference"}[verdict]
        iv = _interval(_g(d, f"{at}|roc_auc"))
        rows.append(
            f"{v} ({_describe(e)}): {word} (ΔROC-AUC "
            + (f"{_signed(iv.estimate)} [{_signed(iv.lo)}, {_signed(iv.hi)}]" if iv else "n/a")
            + ")"
        )
    for b in sorted(groups):
        d = diffs.get(f"{b}{SEED_MEAN}|speed_only")
        if d is not None:
            rows.append(claim(d, f"{at}|roc_auc", "ROC-AUC", f"{b} (seed mean)", "speed_only"))
    if rows:
        out.append(
            "**Does each variant beat the speed-only baseline?** (paired ROC-AUC difference, "
            "speed-only fitted on the variant's own label): " + "; ".join(rows) + "."
        )

    # 6. the headline vs the other variants (same label); threshold-aware objectives
    var_claims, obj_claims = [], []
    for _, d in sorted(diffs.items()):
        if d.get("a") != main_key or d.get("kind") not in ("variant", "objective"):
            continue
        b = str(d.get("b"))
        bv = b.removesuffix(SEED_MEAN)
        if bv in collapsed or main_key in collapsed:
            continue
        e = models.get(bv, {})
        sents = [claim(d, f"{at}|{mk}", name, main_key, b) for mk, name in COMPARED]
        sents.append(claim(d, "test/mse", "MSE", main_key, b))
        text = f"{b} ({_describe(e)}): " + "; ".join(sents)
        (obj_claims if d.get("kind") == "objective" else var_claims).append(text)
    if var_claims:
        out.append(
            f"**Headline vs the other variants on its label (paired, {main_key} − other):** "
            + " | ".join(var_claims)
            + "."
        )
    if obj_claims:
        out.append(
            f"**Training objectives (paired, {main_key} − the same net trained with another "
            "objective; the paper's is MSE on the normalised risk):** "
            + " | ".join(obj_claims)
            + "."
        )
    other = sorted(
        v
        for v, e in models.items()
        if e.get("label") != m.get("label") and v not in collapsed and e.get("group", v) == v
    )
    if other:
        out.append(
            "**Variants on another label** ("
            + ", ".join(f"{v}: {models[v].get('label')}" for v in other)
            + ") solve another task; they are compared only with the speed-only baseline of their "
            "own label (above), never with the headline directly."
        )

    # 7. critical shares of every region per split
    cs = metrics.get("critical_share") or {}
    splits = cs.get("splits") or {}
    if splits:
        labs = [lab for lab in REGIONS if any(lab in s for s in splits.values())]
        rows = [
            f"{REGIONS[lab]} "
            + " / ".join(_pct(_f((splits.get(s) or {}).get(lab))) for s in ("train", "val", "test"))
            for lab in labs
        ]
        if rows:
            out.append(
                f"**Critical share (THW < {_num(_f(cs.get('threshold_s')), 'g')} s) per region, "
                "train / val / test (all frames):** " + "; ".join(rows) + "."
            )

    # 8. the risk metric region (paper vs camera_fov), the paper's explanation of its errors
    reg = metrics.get("region")
    P, F = "risk_thw_paper", "risk_thw_fov"
    labels = (reg or {}).get("labels") or {} if isinstance(reg, Mapping) else {}
    if P in labels and F in labels:
        preds = reg.get("predictors") or {}
        agree = (reg.get("agreement") or {}).get(f"{P}|{F}") or (reg.get("agreement") or {})
        txt = [
            f"the two labels give the same class on {_with_ci(agree, f'class_agreement_at_{t:g}s', pct=True)} "
            f"of the test frames (critical share {_pct(_f(_g(labels, f'{P}|critical_fraction_at_{t:g}s')))} "
            f"with the paper's region, {_pct(_f(_g(labels, f'{F}|critical_fraction_at_{t:g}s')))} with the camera's)"
        ]

        def desc(name: str, lab: str) -> str:
            e = _g(preds, f"{name}|{lab}") or {}
            return (
                f"skill {_with_ci(e, 'skill', '.2f')}, balanced accuracy "
                f"{_with_ci(e, 'balanced_accuracy', pct=True)}, ROC-AUC {_with_ci(e, 'roc_auc')}"
            )

        fov_net = next(
            (v for v, e in sorted(models.items()) if e.get("label") == F and v not in collapsed),
            None,
        )
        sd = next(
            (
                d
                for d in (reg.get("skill_differences") or {}).values()
                if d.get("label_a") == F and d.get("label_b") == P and d.get("a") == fov_net
            ),
            None,
        )
        paper_net = (sd or {}).get("b") or next(
            (v for v, e in sorted(models.items()) if e.get("label") == P and v not in collapsed),
            None,
        )
        for name, lab in ((paper_net, P), (fov_net, F)):
            if name is not None and _g(preds, f"{name}|{lab}") is not None:
                txt.append(f"{name} trained and scored on {lab}: {desc(name, lab)}")
        if _g(preds, f"geometric_sgm|{P}") is not None:
            txt.append(
                f"the geometric SGM baseline scores skill {_with_ci(_g(preds, f'geometric_sgm|{F}'), 'skill', '.2f')} "
                f"on {F} vs {_with_ci(_g(preds, f'geometric_sgm|{P}'), 'skill', '.2f')} on {P}"
            )
        iv = _interval(sd)
        if iv is not None:
            diff = f"{_signed(iv.estimate)} [{_signed(iv.lo)}, {_signed(iv.hi)}]"
            if excludes_zero(iv) and iv.estimate > 0:
                txt.append(
                    f"{fov_net} − {paper_net} skill {diff} (paired): the network explains more of the "
                    "camera-visible risk than of the paper-region risk — consistent with the paper's "
                    "explanation that critical vehicles outside the camera's view limit its accuracy"
                )
            elif excludes_zero(iv):
                txt.append(
                    f"{fov_net} − {paper_net} skill {diff} (paired): the camera-region label is learned "
                    "worse, so the region mismatch does not explain the errors"
                )
            else:
                txt.append(
                    f"{fov_net} − {paper_net} skill {diff} (paired): no significant difference, so this "
                    "run does not show that the region mismatch explains the errors"
                )
        out.append(
            "**Risk metric region (paper vs camera_fov; skill = 1 − MSE / MSE of the training mean "
            "of that label):** " + "; ".join(txt) + "."
        )

    # 9. the headline by situation type
    sit = metrics.get("situations") or {}
    if sit:
        rows = []
        for s, e in sorted(sit.items()):
            p = _g(e, f"predictors|{main_key}") or {}
            sp = _g(e, "predictors|speed_only") or {}
            rows.append(
                f"{s} ({e.get('n_sequences')} seq., {_pct(_f(e.get('critical_share')))} critical): "
                f"recall {_with_ci(p, 'recall', pct=True)}, specificity {_with_ci(p, 'specificity', pct=True)}"
                f" (speed-only {_pct(_f(sp.get('recall')))} / {_pct(_f(sp.get('specificity')))})"
            )
        out.append(
            f"**{main_key} by situation type** (recall / specificity at THW {t:g} s; intervals over the "
            "situation's sequences, wide where it has few): " + "; ".join(rows) + "."
        )

    # 10. targets
    targets = metrics.get("targets") or {}
    if targets:
        rows = []
        for name, e in targets.items():
            v, lo, hi = _f(e.get("value")), _f(e.get("lo")), _f(e.get("hi"))
            ci = f" [{lo:.4g}, {hi:.4g}]" if lo is not None and hi is not None else ""
            why = f" ({e['why']})" if e.get("why") else ""
            who = f" ({e['predictor']})" if e.get("predictor") else ""
            rows.append(
                f"{name}{who} {_num(v, '.4g')}{ci} {e.get('op', '')} {_num(_f(e.get('threshold')), 'g')}: "
                f"{'met' if e.get('met') else 'missed'}{why}"
            )
        n_met = sum(bool(e.get("met")) for e in targets.values())
        out.append(f"**Targets (issue 31; {n_met}/{len(targets)} met):** " + "; ".join(rows) + ".")

    # 11. data
    nf = metrics.get("n_frames")
    if isinstance(nf, Mapping) and nf.get("total"):
        ns = metrics.get("n_sequences") or {}
        seq = f" in {ns.get('train')} / {ns.get('val')} / {ns.get('test')} sequences" if ns else ""
        out.append(
            f"**Data:** {nf.get('total')} frames, {nf.get('orb_outliers_dropped', 0)} dropped by the stereo-pair check "
            f"({_pct(nf.get('orb_outliers_dropped', 0) / nf['total'])}; paper {_pct(1 - PAPER['n_frames'] / 110152)}); "
            f"{nf.get('train')} / {nf.get('val')} / {nf.get('test')} train / val / test frames{seq} "
            "(split by scenario)."
        )
    return "\n".join(f"- {s}" for s in out)
