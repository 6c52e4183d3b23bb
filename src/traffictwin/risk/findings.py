"""Findings of the risk evaluation as markdown bullets, generated from ``reports/metrics/risk.json``.

:func:`findings` is called by the report stage (``traffictwin.report.render.findings``); every
number comes from the metrics dict, nothing is typed by hand. Missing entries (a variant or a
baseline not evaluated, a metric undefined → ``None``) are skipped, never invented.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from traffictwin.risk.evaluation import PAPER

#: input ablations (variant a vs variant b, scored on the same label), named by what differs:
#: (inputs of a, speed of a, inputs of b, speed of b, what a adds). Variants are found by their
#: inputs in the metrics, never by name (the variants are ``risk_model.run_variants``).
PAPER_INPUTS = ("rgb", "disp_sgm")
ABLATIONS = (
    (("rgb", "disp_sgm"), False, ("rgb",), False, "adding SGM disparity to the image"),
    (("rgb", "disp_sgm"), False, ("disp_sgm",), False, "adding the image to the SGM disparity"),
    (("rgb", "disp_gt"), False, ("rgb", "disp_sgm"), False, "perfect instead of SGM disparity"),
    (("rgb", "disp_sgm"), True, ("rgb", "disp_sgm"), False, "giving the network the subject speed"),
)


def _g(d: Any, path: str) -> Any:
    for k in path.split("|"):
        if not isinstance(d, Mapping) or k not in d:
            return None
        d = d[k]
    return d


def _pct(x: float | None) -> str:
    return "n/a" if x is None else f"{100 * x:.2f} %"


def _num(x: float | None, fmt: str = ".4f") -> str:
    return "n/a" if x is None else format(x, fmt)


def _variant_with(models: Mapping[str, Any], inputs: tuple[str, ...], speed: bool) -> str | None:
    """The first variant with exactly these input channel groups and speed input, if any."""
    for v, e in models.items():
        if tuple(e.get("inputs") or ()) == inputs and bool(e.get("speed")) == speed:
            return v
    return None


def findings(metrics: Mapping[str, Any]) -> str:
    """Markdown bullet list: paper comparison, baselines, which input matters, the region effect."""
    t = (metrics.get("thresholds_s") or [PAPER["threshold_s"]])[0]
    at = f"at_{t:g}s"
    models: Mapping[str, Any] = metrics.get("models", {})
    base: Mapping[str, Any] = metrics.get("baselines", {})
    # the main variant; without one, the paper's network (RGB + SGM disparity on the primary label)
    paper_net = _variant_with(
        {v: e for v, e in models.items() if e.get("label") == metrics.get("primary_label")},
        PAPER_INPUTS,
        False,
    )
    main = metrics.get("main_variant") or paper_net or next(iter(models), None)
    out: list[str] = []
    if main is None:
        return "- No risk network was evaluated."
    m = models[main]
    mse, acc = m.get("test/mse"), _g(m, f"{at}|accuracy")
    n = m.get("test/n")
    if mse is not None:
        rel = "below" if mse < PAPER["test/mse"] else "above"
        out.append(
            f"**Paper comparison ({main}, {n} test frames).** Test MSE {_num(mse, '.5f')} vs the paper's "
            f"{PAPER['test/mse']:.5f} ({mse / PAPER['test/mse']:.2f}× — {rel}); accuracy at THW {t:g} s "
            f"{_pct(acc)} vs the paper's {_pct(PAPER['accuracy'])} and Wang & Kato's {_pct(PAPER['wang_kato_accuracy'])}; "
            f"balanced accuracy {_pct(_g(m, f'{at}|balanced_accuracy'))}, F1 {_num(_g(m, f'{at}|f1'), '.3f')}, "
            f"ROC-AUC {_num(_g(m, f'{at}|roc_auc'), '.3f')}. Critical share of the test frames "
            f"{_pct(_g(m, f'{at}|critical_fraction_true'))} (the paper's data set: "
            f"{_pct(76789 / PAPER['n_frames'])}), so raw accuracies are only comparable with the majority baseline beside them."
        )
    # baselines
    maj, mean, geo = base.get("train_median"), base.get("train_mean"), base.get("geometric")
    parts = []
    if maj is not None:
        parts.append(f"majority class (training median) accuracy {_pct(_g(maj, f'{at}|accuracy'))}")
    if mean is not None:
        parts.append(f"training-mean predictor MSE {_num(mean.get('test/mse'), '.5f')}")
    if geo is not None:
        parts.append(
            f"geometric SGM-corridor baseline MSE {_num(geo.get('test/mse'), '.5f')}, accuracy {_pct(_g(geo, f'{at}|accuracy'))}, "
            f"balanced accuracy {_pct(_g(geo, f'{at}|balanced_accuracy'))}, ROC-AUC {_num(_g(geo, f'{at}|roc_auc'), '.3f')}"
        )
    if parts:
        verdict = []
        if maj is not None and acc is not None and _g(maj, f"{at}|accuracy") is not None:
            d = acc - _g(maj, f"{at}|accuracy")
            verdict.append(
                f"the network is {abs(100 * d):.2f} points {'above' if d >= 0 else 'below'} the majority class"
            )
        if mean is not None and mse is not None and mean.get("test/mse"):
            verdict.append(f"its MSE is {mse / mean['test/mse']:.2f}× the training mean's")
        if geo is not None and mse is not None and geo.get("test/mse") is not None:
            verdict.append(
                f"{'better' if mse < geo['test/mse'] else 'worse'} than the geometric baseline in MSE"
            )
            ga, na = _g(geo, f"{at}|roc_auc"), _g(m, f"{at}|roc_auc")
            if ga is not None and na is not None:
                verdict.append(
                    f"{'but worse' if ga > na else 'and better'} at ranking critical frames (ROC-AUC {na:.3f} vs {ga:.3f})"
                )
        out.append(
            "**Baselines on the same frames:** "
            + "; ".join(parts)
            + (". So " + ", ".join(verdict) + "." if verdict else ".")
        )
    # which input matters (variants scored against the same label as the main one)
    lab = m.get("label")
    same = {
        v: e for v, e in models.items() if e.get("label") == lab and e.get("test/mse") is not None
    }
    if len(same) > 1:
        ranked = sorted(same, key=lambda v: same[v]["test/mse"])
        rows = ", ".join(
            f"{v} {same[v]['test/mse']:.5f} / {_pct(_g(same[v], f'{at}|accuracy'))}" for v in ranked
        )
        out.append(
            f"**Which input matters** (test MSE / accuracy, best first, label {lab}): {rows}."
        )
        cmp = []
        for in_a, sp_a, in_b, sp_b, what in ABLATIONS:
            a, b = _variant_with(same, in_a, sp_a), _variant_with(same, in_b, sp_b)
            if a is not None and b is not None:
                r = same[a]["test/mse"] / same[b]["test/mse"] if same[b]["test/mse"] else None
                if r is not None:
                    eff = "lowers" if r < 1 else "raises"
                    cmp.append(
                        f"{what} {eff} the MSE by {abs(1 - r) * 100:.0f} % ({same[b]['test/mse']:.5f} → {same[a]['test/mse']:.5f})"
                    )
        flat = [
            v
            for v in ranked
            if _g(same[v], f"{at}|roc_auc") is not None
            and abs(_g(same[v], f"{at}|roc_auc") - 0.5) < 0.02
        ]
        if flat:
            cmp.append(
                f"{', '.join(flat)} did not leave the constant predictor in this budget (ROC-AUC ≈ 0.5)"
            )
        if cmp:
            out.append("**Input ablation:** " + "; ".join(cmp) + ".")
    # region
    reg = metrics.get("region")
    P, F = "risk_thw_paper", "risk_thw_fov"
    if (
        isinstance(reg, Mapping)
        and P in (reg.get("labels") or {})
        and F in (reg.get("labels") or {})
    ):
        preds = reg.get("predictors") or {}
        txt = [
            f"the two labels give the same class on {_pct(_g(reg, f'agreement|class_agreement_at_{t:g}s'))} of the test frames "
            f"(critical share {_pct(_g(reg, f'labels|{P}|critical_fraction_at_{t:g}s'))} with the paper's region, "
            f"{_pct(_g(reg, f'labels|{F}|critical_fraction_at_{t:g}s'))} with the camera's)"
        ]

        def desc(name: str, lab: str) -> str:
            e = _g(preds, f"{name}|{lab}") or {}
            return (
                f"skill {_num(e.get('skill'), '.2f')}, balanced accuracy {_pct(e.get('balanced_accuracy'))}, "
                f"ROC-AUC {_num(e.get('roc_auc'), '.3f')}"
            )

        own = {}
        fov_net = next((v for v, e in models.items() if v != main and e.get("label") == F), None)
        for name, lab in ((main, (models.get(main) or {}).get("label", P)), (fov_net, F)):
            if _g(preds, f"{name}|{lab}") is not None:
                own[lab] = _g(preds, f"{name}|{lab}|skill")
                txt.append(f"{name} trained and scored on {lab}: {desc(name, lab)}")
        if _g(preds, f"geometric|{P}") is not None:
            txt.append(
                f"the geometric baseline scores skill {_num(_g(preds, f'geometric|{F}|skill'), '.2f')} on {F} vs "
                f"{_num(_g(preds, f'geometric|{P}|skill'), '.2f')} on {P}"
            )
        if own.get(P) is not None and own.get(F) is not None:
            if own[F] > own[P]:
                txt.append(
                    "the network explains more of the camera-visible risk than of the paper-region risk — consistent "
                    "with the paper's explanation that critical vehicles outside the camera's view limit its accuracy"
                )
            else:
                txt.append(
                    "the camera-region label is not learned better than the paper-region one here, so the region "
                    "mismatch does not explain the errors"
                )
        out.append(
            "**Risk metric region (paper vs camera_fov; skill = 1 − MSE / MSE of the training mean of that label):** "
            + "; ".join(txt)
            + "."
        )
    nf = metrics.get("n_frames")
    if isinstance(nf, Mapping) and nf.get("total"):
        out.append(
            f"**Data:** {nf.get('total')} frames, {nf.get('orb_outliers_dropped', 0)} dropped by the ORB check "
            f"({_pct(nf.get('orb_outliers_dropped', 0) / nf['total'])}; paper {_pct(1 - PAPER['n_frames'] / 110152)}); "
            f"{nf.get('train')} / {nf.get('val')} / {nf.get('test')} train / val / test frames (split by scenario)."
        )
    return "\n".join(f"- {s}" for s in out)
