"""Figures of the risk network (matplotlib, Agg): the paper's Figs. 5–7 and Table 1 as images, and
the ROC of every predictor; :func:`evaluation_figures` draws them all from the evaluate_risk stage's
outputs (stage plot_data)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from itertools import product
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from traffictwin.io.atomic import pyplot, save_figure
from traffictwin.risk.charts import roc_points
from traffictwin.risk.evaluation import GT_INPUT, PAPER, example_indices, main_series
from traffictwin.risk.metric import risk_threshold

plt = pyplot()

#: y-axis name of each training objective's loss (:data:`traffictwin.risk.dave2.OBJECTIVES`):
#: ``train/loss`` and ``val/loss`` are in these units; ``val/mse`` is always the MSE of the
#: normalised risk (dimensionless, in [0, 1]), whatever the objective.
OBJECTIVE_LOSS: dict[str, str] = {
    "mse": "loss: MSE of normalised risk (dimensionless)",
    "log_thw": "loss: MSE of log THW ((log s)²)",
    "mse_bce": "loss: MSE of normalised risk + weighted cross-entropy of 'critical' (dimensionless)",
}
#: plain-language name of each objective (panel titles)
OBJECTIVE_NAME: dict[str, str] = {
    "mse": "objective mse (the paper's: MSE of normalised risk)",
    "log_thw": "objective log_thw (MSE of log time headway)",
    "mse_bce": "objective mse_bce (MSE + critical/uncritical head)",
}
VAL_MSE_LABEL = "MSE of normalised risk (dimensionless)"
VALIDATION = " (validation)"  # a validation loss's legend label ends so (left out of the legend)
LOSS_LINES = (("train/loss", "-", ""), ("val/loss", "--", VALIDATION))  # column, style, label tail
EMPTY = dict(ha="center", va="center", wrap=True, fontsize=10, color="0.25", gid="empty")


def _say_empty(ax: Any, text: str) -> None:
    """An empty chart says why, centred in its axes (``gid`` ``"empty"``), instead of drawing nothing."""
    ax.text(0.5, 0.5, text, transform=ax.transAxes, **EMPTY)


def plot_training_curves(
    histories: Mapping[str, pd.DataFrame],
    path: str | Path,
    paper_test_mse: float | None = None,
    objectives: Mapping[str, str | None] | None = None,
) -> None:
    """``histories``: variant → DataFrame with ``step``, ``train/loss`` and (optional) ``val/loss``
    (its objective's loss) and ``val/mse`` (MSE of the normalised risk); ``objectives``: variant →
    its training objective (``mse`` where missing).

    One panel per objective (training loss solid, validation loss dashed, y axis named after the
    objective: :data:`OBJECTIVE_LOSS`), then every run's validation MSE of the normalised risk.
    The paper's test MSE (an MSE of normalised risk) is drawn only on panels in those units. A run
    keeps its colour in every panel."""
    runs = {n: h for n, h in histories.items() if len(h)}
    obj_of = {n: str((objectives or {}).get(n) or "mse") for n in runs}
    order = [o for o in OBJECTIVE_LOSS if o in obj_of.values()]
    order += sorted({o for o in obj_of.values() if o not in OBJECTIVE_LOSS})
    colour = {n: f"C{i % 10}" for i, n in enumerate(histories)}
    has_val = any("val/mse" in h.columns for h in runs.values())
    fig, axes = plt.subplots(1, len(order) + 1, figsize=(5.5 * len(order) + 5.5, 4), squeeze=False)
    for ax, obj in zip(axes[0], [*order, None]):  # None: the validation MSE of every run
        cols = LOSS_LINES if obj else [("val/mse", "-", "")]
        for name, (col, ls, tail) in product([n for n in runs if obj in (None, obj_of[n])], cols):
            if col in runs[name].columns:
                h = runs[name]
                ax.plot(h["step"], h[col], color=colour[name], lw=1.2, ls=ls, label=name + tail)
        if obj:
            name = OBJECTIVE_NAME.get(obj, f"objective {obj}")
            ax.set_title(f"{name}\ntraining loss (solid), validation loss (dashed)", fontsize=10)
            ax.set_ylabel(OBJECTIVE_LOSS.get(obj, f"loss of objective {obj}"))
        else:
            ax.set_title("validation MSE of normalised risk (every run)", fontsize=10)
            ax.set_ylabel(VAL_MSE_LABEL)
        if paper_test_mse is not None and (obj == "mse" or (obj is None and has_val)):
            ax.axhline(paper_test_mse, color="k", ls=":", lw=1, label="paper test MSE")
        ax.set_xlabel("training step")
        if ax.lines:
            ax.set_yscale("log")
            shown = [ln for ln in ax.lines if not ln.get_label().endswith(VALIDATION)]
            ax.legend(handles=shown, fontsize=8)
        ax.grid(alpha=0.3)
    if not runs:
        _say_empty(axes[0, -1], "no training history to draw")
    elif not has_val:
        _say_empty(axes[0, -1], "no validation MSE in the training histories")
    fig.tight_layout()
    save_figure(fig, path)


def plot_scatter(
    y: np.ndarray, preds: Mapping[str, np.ndarray], path: str | Path, threshold: float, title: str
) -> None:
    """Predicted vs true normalised risk, one panel per predictor; dashed lines = critical
    threshold. Most frames have a risk near 0 (nothing close ahead): both axes are symmetric-log,
    linear below a tenth of the threshold, so the frames around the threshold spread out."""
    fig, axes = plt.subplots(1, len(preds), figsize=(4.2 * len(preds), 4), squeeze=False)
    hi = float(max(np.max(y), *(np.max(p) for p in preds.values()), threshold * 2)) * 1.05
    lin = threshold / 10
    for ax, (name, p) in zip(axes[0], preds.items()):
        ax.scatter(y, p, s=6, alpha=0.5)
        ax.plot([0, hi], [0, hi], "k-", lw=0.8)
        ax.axvline(threshold, color="r", ls="--", lw=0.8)
        ax.axhline(threshold, color="r", ls="--", lw=0.8)
        ax.set_xscale("symlog", linthresh=lin)
        ax.set_yscale("symlog", linthresh=lin)
        ax.set(xlim=(0, hi), ylim=(min(0.0, float(np.min(p))), hi), title=name)
        ax.set_xlabel(f"true risk (1, symlog: linear below {lin:.3g})")
        ax.set_ylabel("predicted risk (1, symlog)")
        ax.grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()  # the panels' axis labels clear their neighbours
    save_figure(fig, path)


def plot_examples(
    risk: Any, disparity: Any, pred: pd.DataFrame, y: np.ndarray, yhat: np.ndarray, t0: float, path
) -> None:
    """Paper Fig. 7 of the predictions ``pred`` (true ``y``, predicted ``yhat``): the best-predicted
    critical frame, then the worst-predicted one (:func:`~traffictwin.risk.evaluation.example_indices`,
    THW ``t0`` s), each its left image (risk data ``risk``) beside its SGM disparity (``disparity``)."""
    good, bad = example_indices(y, yhat, t0)
    table = risk.table("frames.csv")
    frames = table.set_index(table["frame_id"].astype(str))
    rows = list(dict.fromkeys((good, bad)))
    fig, axes = plt.subplots(len(rows), 2, figsize=(10, 2.8 * len(rows)), squeeze=False)
    for (img, disp), i in zip(axes, rows):
        f = str(pred.at[i, "frame_id"])
        shard, k = int(frames.at[f, "shard"]), int(frames.at[f, "idx"])
        what = "well predicted" if i == good else "worst prediction"
        img.imshow(risk.load_shard(shard)["left"][k][..., ::-1])
        img.set_title(f"{what} (frame {f}): true {y[i]:.2f}, predicted {yhat[i]:.2f}", fontsize=9)
        d = disparity.load_shard(shard)["disp_sgm"][k]
        d = np.where(d > 0, d, np.nan)  # ≤ 0: invalid
        vmax = np.nanmax(d) if np.isfinite(d).any() else 1
        im = disp.imshow(d, cmap="viridis", vmin=0, vmax=vmax)
        disp.set_title("SGM disparity (px; yellow = near)", fontsize=9)
        fig.colorbar(im, ax=disp, fraction=0.025)
        img.axis("off")
        disp.axis("off")
    save_figure(fig, path)


def plot_confusion(confusion: Mapping[str, int], path: str | Path, title: str) -> None:
    """2×2 matrix like the paper's Table 1: rows predicted (critical, uncritical), columns actual."""
    m = np.array([[confusion[k] for k in row] for row in (("tp", "fp"), ("fn", "tn"))], float)
    n = max(m.sum(), 1.0)
    fig, ax = plt.subplots(figsize=(4.8, 4))
    ax.imshow(m / n, cmap="Blues", vmin=0, vmax=1)
    for (i, j), c in np.ndenumerate(m):
        text = f"{int(c)}\n({100 * c / n:.2f} %)"
        ax.text(j, i, text, ha="center", va="center", color="white" if c / n > 0.5 else "black")
    ax.set_xticks([0, 1], ["actual critical", "actual uncritical"])
    ax.set_yticks([0, 1], ["predicted\ncritical", "predicted\nuncritical"])
    ax.set_title(title)
    save_figure(fig, path)


def plot_roc(
    positive: np.ndarray,
    scores: Mapping[str, np.ndarray],
    path: str | Path,
    title: str = "ROC on the test frames",
    auc: Mapping[str, float | None] | None = None,
) -> None:
    """ROC curves (false vs true positive rate) of each predictor's risk as a score for
    ``positive`` (critical) frames; the GT-disparity rule dashed, the chance diagonal dotted;
    legend entries carry ``auc`` when given. Without critical or without uncritical frames the
    ROC is undefined: the axes say so and draw no curve."""
    fig, ax = plt.subplots(figsize=(5.2, 4.8))
    pos = np.asarray(positive, bool).ravel()
    if not scores:
        _say_empty(ax, "no predictor to draw")
    elif pos.size == 0:
        _say_empty(ax, "no frames in the test split: ROC undefined")
    elif pos.all() or not pos.any():
        lack, have = ("uncritical", "critical") if pos.all() else ("critical", "uncritical")
        _say_empty(
            ax, f"no {lack} frames in the test split\n(all {pos.size} are {have}): ROC undefined"
        )
    else:
        for name, score in scores.items():
            a = (auc or {}).get(name)
            label = f"{name} (AUC {a:.3f})" if a is not None else name
            ls = "--" if name in GT_INPUT else "-"
            ax.plot(*roc_points(pos, score), ls=ls, lw=1.4, label=label)
        ax.plot([0, 1], [0, 1], color="0.6", ls=":", lw=1, label="chance")
        ax.legend(fontsize=8, loc="lower right")
    ax.set(xlim=(0, 1), ylim=(0, 1.01), title=title)
    ax.set_xlabel("false positive rate (uncritical frames called critical)")
    ax.set_ylabel("true positive rate (critical frames detected)")
    ax.grid(alpha=0.3)
    save_figure(fig, path)


@dataclass(frozen=True)
class EvaluationFigurePaths:
    """Where :func:`evaluation_figures` writes each figure (PNG)."""

    curves: str | Path
    scatter: str | Path
    confusion: str | Path
    examples: str | Path
    roc: str | Path


def evaluation_figures(
    risk: Any,
    disparity: Any,
    metrics: Mapping[str, Any],
    pred: pd.DataFrame,
    histories: Mapping[str, pd.DataFrame],
    main_variant: str,
    paths: EvaluationFigurePaths,
    shipped: tuple[str, str] | None = None,
) -> None:
    """The figures of :func:`~traffictwin.risk.evaluation.evaluate_suite`'s ``metrics`` and
    per-frame ``pred`` (as risk.json and risk_predictions.csv) at the primary THW threshold, to
    ``paths``: every variant's training ``curves`` (``histories``); ``main_variant``'s ``scatter``
    beside the speed-only and SGM-rule baselines, ``confusion`` matrix and Fig. 7 ``examples``
    (images from the Datasets ``risk`` and its SGM ``disparity``); the ``roc`` of its seeds and the
    baselines (baselines only when the headline is on the primary label). ``shipped`` (model key,
    legend name): the shipped predictor, drawn first in the scatter and the ROC when there."""
    t0 = metrics["thresholds_s"][0]
    at, models = f"at_{t0:g}s", metrics["models"]
    main_label, y, yhat = main_series(metrics, pred, main_variant)
    same_label = main_label == metrics.get("primary_label", main_label)
    bases = [b for b in ("speed_only", "geometric_sgm", "geometric_gt") if f"pred_{b}" in pred]
    bases = bases if same_label else []
    ok = shipped and same_label and shipped[0] in models and f"pred_{shipped[0]}" in pred
    ship = shipped if ok else None
    first = {ship[1]: pred[f"pred_{ship[0]}"].to_numpy()} if ship else {}
    objectives = {v: models.get(v, {}).get("objective") for v in histories}
    plot_training_curves(histories, paths.curves, PAPER["test/mse"], objectives)
    scatter = {b: pred[f"pred_{b}"].to_numpy() for b in bases if b != "geometric_gt"}
    preds = {**first, main_variant: yhat, **scatter}
    plot_scatter(y, preds, paths.scatter, risk_threshold(t0), f"test frames, label {main_label}")
    # the ROC of the headline's runs: each seed, the collapsed ones left out
    group = metrics.get("groups", {}).get(main_variant, {}).get("members") or [main_variant]
    runs = [v for v in group if not models.get(v, {}).get("collapsed")] or [main_variant]
    scores = {**first, **{v: pred[f"pred_{v}"].to_numpy() for v in [*runs, *bases]}}
    auc = {ship[1]: models[ship[0]][at].get("roc_auc")} if ship else {}
    auc |= {v: models[v][at].get("roc_auc") for v in runs}
    auc |= {b: metrics["baselines"][b][at].get("roc_auc") for b in bases}
    title = f"critical (THW < {t0:g} s) on the test frames, label {main_label}"
    plot_roc(y > risk_threshold(t0), scores, paths.roc, title, auc)
    cm = models[main_variant][at]
    title = f"{main_variant}: THW {t0:g} s (accuracy {cm['accuracy']:.1%})"
    plot_confusion(cm["confusion"], paths.confusion, title)
    plot_examples(risk, disparity, pred, y, yhat, t0, paths.examples)
