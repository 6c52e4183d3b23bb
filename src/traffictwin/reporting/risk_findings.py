"""Findings of the risk evaluation as markdown bullets, generated from ``reports/metrics/risk.json``.

:func:`findings` is called by the report stage (``traffictwin.reporting.report.findings``); every
number comes from the metrics dict, nothing is typed by hand. Missing entries (a variant or a
baseline not evaluated, a metric undefined → ``None``) are skipped, never invented.
"""

from __future__ import annotations

from typing import Any, Mapping

from ..evaluation.risk_metrics import PAPER

VARIANT_NAMES = {
    "rgbd": "RGB + SGM disparity (the paper's input)",
    "rgb": "RGB only",
    "disp": "SGM disparity only",
    "gtdisp": "RGB + ground-truth disparity (perfect stereo)",
    "rgbd_speed": "RGB + SGM disparity + speed",
    "rgbd_fov": "RGB + SGM disparity, camera_fov label",
}


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


def findings(metrics: Mapping[str, Any]) -> str:
    """Markdown bullet list: paper comparison, baselines, which input matters, the region effect."""
    t = (metrics.get("thresholds_s") or [PAPER["threshold_s"]])[0]
    at = f"at_{t:g}s"
    models: Mapping[str, Any] = metrics.get("models", {})
    base: Mapping[str, Any] = metrics.get("baselines", {})
    main = metrics.get("main_variant") or ("rgbd" if "rgbd" in models else next(iter(models), None))
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
            f"balanced accuracy {_pct(_g(geo, f'{at}|balanced_accuracy'))}"
        )
    if parts:
        verdict = []
        if maj is not None and acc is not None and _g(maj, f"{at}|accuracy") is not None:
            d = acc - _g(maj, f"{at}|accuracy")
            verdict.append(f"the network is {abs(100 * d):.2f} points {'above' if d >= 0 else 'below'} the majority class")
        if mean is not None and mse is not None and mean.get("test/mse"):
            verdict.append(f"its MSE is {mse / mean['test/mse']:.2f}× the training mean's")
        if geo is not None and mse is not None and geo.get("test/mse") is not None:
            verdict.append(f"{'better' if mse < geo['test/mse'] else 'worse'} than the geometric baseline in MSE")
        out.append("**Baselines on the same frames:** " + "; ".join(parts) + (". So " + ", ".join(verdict) + "." if verdict else "."))
    # which input matters (variants scored against the same label as the main one)
    lab = m.get("label")
    same = {v: e for v, e in models.items() if e.get("label") == lab and e.get("test/mse") is not None}
    if len(same) > 1:
        ranked = sorted(same, key=lambda v: same[v]["test/mse"])
        rows = ", ".join(
            f"{v} {same[v]['test/mse']:.5f} / {_pct(_g(same[v], f'{at}|accuracy'))}" for v in ranked
        )
        out.append(f"**Which input matters** (test MSE / accuracy, best first, label {lab}): {rows}.")
        cmp = []
        for a, b, what in (
            ("rgbd", "rgb", "adding SGM disparity to the image"),
            ("rgbd", "disp", "adding the image to the SGM disparity"),
            ("gtdisp", "rgbd", "perfect instead of SGM disparity"),
            ("rgbd_speed", "rgbd", "giving the network the subject speed"),
        ):
            if a in same and b in same:
                r = same[a]["test/mse"] / same[b]["test/mse"] if same[b]["test/mse"] else None
                if r is not None:
                    eff = "lowers" if r < 1 else "raises"
                    cmp.append(f"{what} {eff} the MSE by {abs(1 - r) * 100:.0f} % ({same[b]['test/mse']:.5f} → {same[a]['test/mse']:.5f})")
        if cmp:
            out.append("**Input ablation:** " + "; ".join(cmp) + ".")
    # region
    reg = metrics.get("region")
    if isinstance(reg, Mapping):
        labs = list((reg.get("labels") or {}).keys())
        agree = _g(reg, f"agreement|class_agreement_at_{t:g}s")
        txt = []
        if len(labs) == 2:
            a, b = labs
            txt.append(
                f"the two labels give the same class on {_pct(agree)} of the test frames "
                f"(critical share {_pct(_g(reg, f'labels|{a}|critical_fraction_at_{t:g}s'))} with {a}, "
                f"{_pct(_g(reg, f'labels|{b}|critical_fraction_at_{t:g}s'))} with {b})"
            )
            preds = reg.get("predictors") or {}
            for name in (main, "rgbd_fov", "geometric"):
                p = preds.get(name)
                if not p or a not in p or b not in p:
                    continue
                txt.append(
                    f"{name}: accuracy {_pct(p[a].get('accuracy'))} against {a} vs {_pct(p[b].get('accuracy'))} against {b} "
                    f"(MSE {_num(p[a].get('test/mse'), '.5f')} vs {_num(p[b].get('test/mse'), '.5f')})"
                )
            pm, pf = _g(preds, f"{main}|{a}|accuracy"), _g(preds, f"{main}|{b}|accuracy")
            if pm is not None and pf is not None:
                better = b if pf > pm else a
                txt.append(
                    f"the camera sees the situation better described by **{better}** — "
                    + ("consistent with the paper's explanation that risk outside the camera's view limits accuracy"
                       if better == b else "the region mismatch does not explain the errors here")
                )
        if txt:
            out.append("**Risk metric region (paper vs camera_fov):** " + "; ".join(txt) + ".")
    nf = metrics.get("n_frames")
    if isinstance(nf, Mapping) and nf.get("total"):
        out.append(
            f"**Data:** {nf.get('total')} frames, {nf.get('orb_outliers_dropped', 0)} dropped by the ORB check "
            f"({_pct(nf.get('orb_outliers_dropped', 0) / nf['total'])}; paper {_pct(1 - PAPER['n_frames'] / 110152)}); "
            f"{nf.get('train')} / {nf.get('val')} / {nf.get('test')} train / val / test frames (split by scenario)."
        )
    return "\n".join(f"- {s}" for s in out)
