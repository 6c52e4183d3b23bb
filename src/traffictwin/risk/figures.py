"""Figures of the risk network (matplotlib, Agg): the paper's Figs. 5–7 and Table 1 as images.

* :func:`plot_training_curves` — training and validation loss over training steps, one panel
  per training objective (each in its own units), then every variant's validation MSE of the
  normalised risk (Figs. 5–6);
* :func:`plot_scatter` — predicted vs true risk with the critical threshold lines;
* :func:`plot_examples` — test frames (left image + SGM disparity) with true and predicted risk (Fig. 7);
* :func:`plot_confusion` — the 2×2 confusion matrix laid out as Table 1 (rows predicted, cols actual);
* :func:`plot_roc` — ROC curves of the headline network and the baselines on the same frames
  (the GT-disparity rule dashed; a split without critical or uncritical frames says so);
* :func:`evaluation_figures` — all five for the evaluate_risk stage (paths: :class:`EvaluationFigurePaths`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from traffictwin.io.atomic import save_figure  # noqa: E402
from traffictwin.risk.charts import roc_points  # noqa: E402
from traffictwin.risk.evaluation import (  # noqa: E402
    GT_INPUT,
    PAPER,
    example_indices,
    main_series,
)
from traffictwin.risk.metric import risk_threshold  # noqa: E402

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


def _say_empty(ax: plt.Axes, text: str) -> None:
    """An empty chart says why, centred in its axes (``gid`` ``"empty"``), instead of drawing nothing."""
    ax.text(
        0.5,
        0.5,
        text,
        transform=ax.transAxes,
        ha="center",
        va="center",
        wrap=True,
        fontsize=10,
        color="0.25",
        gid="empty",
    )


def plot_training_curves(
    histories: Mapping[str, pd.DataFrame],
    path: str | Path,
    paper_test_mse: float | None = None,
    objectives: Mapping[str, str | None] | None = None,
) -> None:
    """``histories``: variant → DataFrame with ``step``, ``train/loss`` and (optional) ``val/loss``
    (the variant's objective's loss) and ``val/mse`` (MSE of the normalised risk, from
    train_risk); ``objectives``: variant → its training objective (``mse`` where missing, the
    evaluation's default).

    One panel per objective present (its training loss solid, validation loss dashed, y axis
    named after that objective: :data:`OBJECTIVE_LOSS`), then one panel of every run's
    validation MSE of the normalised risk, comparable across objectives. The paper's test MSE
    (``paper_test_mse``, an MSE of normalised risk) is drawn only on panels in those units: the
    ``mse`` objective's and the validation MSE. A run keeps its colour in every panel."""
    objectives = objectives or {}
    runs = {n: h for n, h in histories.items() if len(h)}
    obj_of = {n: str(objectives.get(n) or "mse") for n in runs}
    order = [o for o in OBJECTIVE_LOSS if o in obj_of.values()]
    order += sorted({o for o in obj_of.values() if o not in OBJECTIVE_LOSS})
    colour = {n: f"C{i % 10}" for i, n in enumerate(histories)}
    n_panels = len(order) + 1
    fig, axes = plt.subplots(1, n_panels, figsize=(5.5 * n_panels, 4), squeeze=False)
    axes = axes[0]
    for ax, obj in zip(axes, order):
        for name in (n for n in runs if obj_of[n] == obj):
            h = runs[name]
            for col, ls, label in (
                ("train/loss", "-", name),
                ("val/loss", "--", f"{name} (validation)"),
            ):
                if col in h.columns:
                    ax.plot(h["step"], h[col], color=colour[name], lw=1.2, ls=ls, label=label)
        ax.set_title(
            f"{OBJECTIVE_NAME.get(obj, f'objective {obj}')}\n"
            "training loss (solid), validation loss (dashed)",
            fontsize=10,
        )
        ax.set_ylabel(OBJECTIVE_LOSS.get(obj, f"loss of objective {obj}"))
        if obj == "mse" and paper_test_mse is not None:
            ax.axhline(paper_test_mse, color="k", ls=":", lw=1, label="paper test MSE")
    val = axes[-1]
    for name, h in runs.items():
        if "val/mse" in h.columns:
            val.plot(h["step"], h["val/mse"], color=colour[name], lw=1.2, label=name)
    val.set_title("validation MSE of normalised risk (every run)", fontsize=10)
    val.set_ylabel(VAL_MSE_LABEL)
    if paper_test_mse is not None and val.lines:
        val.axhline(paper_test_mse, color="k", ls=":", lw=1, label="paper test MSE")
    for ax in axes:
        ax.set_xlabel("training step")
        if ax.lines:
            ax.set_yscale("log")
            shown = [ln for ln in ax.lines if not ln.get_label().endswith(" (validation)")]
            ax.legend(handles=shown, fontsize=8)
        ax.grid(alpha=0.3)
    if not runs:
        _say_empty(val, "no training history to draw")
    elif not any("val/mse" in h.columns for h in runs.values()):
        _say_empty(val, "no validation MSE in the training histories")
    fig.tight_layout()
    save_figure(fig, path, dpi=110, bbox_inches="tight")


def plot_scatter(
    y: np.ndarray,
    preds: Mapping[str, np.ndarray],
    path: str | Path,
    threshold: float,
    title: str = "",
) -> None:
    """Predicted vs true normalised risk for one or more predictors; dashed lines = critical
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
        ax.set_xlim(0, hi)
        ax.set_ylim(min(0.0, float(np.min(p))), hi)
        ax.set_xlabel(f"true risk (1, symlog: linear below {lin:.3g})")
        ax.set_ylabel("predicted risk (1, symlog)")
        ax.set_title(name)
        ax.grid(alpha=0.3)
    if title:
        fig.suptitle(title)
    fig.tight_layout()  # the panels' axis labels clear their neighbours
    save_figure(fig, path, dpi=110, bbox_inches="tight")


def plot_examples(
    examples: Sequence[dict], path: str | Path, disp_max: float | None = None
) -> None:
    """Each example: ``left`` (H,W,3) BGR uint8, ``disp`` (H,W) px (≤0 invalid), ``true``, ``pred``, ``title``."""
    n = len(examples)
    fig, axes = plt.subplots(n, 2, figsize=(10, 2.8 * n), squeeze=False)
    for row, ex in zip(axes, examples):
        row[0].imshow(ex["left"][..., ::-1])
        row[0].set_title(
            f"{ex.get('title', '')}: true {ex['true']:.2f}, predicted {ex['pred']:.2f}", fontsize=9
        )
        d = np.where(ex["disp"] > 0, ex["disp"], np.nan)
        vmax = disp_max if disp_max else (float(np.nanmax(d)) if np.isfinite(d).any() else 1.0)
        im = row[1].imshow(d, cmap="viridis", vmin=0, vmax=vmax)
        row[1].set_title("SGM disparity (px; yellow = near)", fontsize=9)
        fig.colorbar(im, ax=row[1], fraction=0.025)
        for ax in row:
            ax.axis("off")
    save_figure(fig, path, dpi=110, bbox_inches="tight")


def plot_confusion(confusion: Mapping[str, int], path: str | Path, title: str = "") -> None:
    """2×2 matrix like the paper's Table 1: rows predicted (critical, uncritical), columns actual."""
    m = np.array(
        [[confusion["tp"], confusion["fp"]], [confusion["fn"], confusion["tn"]]], dtype=float
    )
    n = max(m.sum(), 1.0)
    fig, ax = plt.subplots(figsize=(4.8, 4))
    ax.imshow(m / n, cmap="Blues", vmin=0, vmax=1)
    for (i, j), c in np.ndenumerate(m):
        text = f"{int(c)}\n({100 * c / n:.2f} %)"
        ax.text(j, i, text, ha="center", va="center", color="white" if c / n > 0.5 else "black")
    ax.set_xticks([0, 1], ["actual critical", "actual uncritical"])
    ax.set_yticks([0, 1], ["predicted\ncritical", "predicted\nuncritical"])
    ax.set_title(title or "confusion matrix")
    save_figure(fig, path, dpi=110, bbox_inches="tight")


def plot_roc(
    positive: np.ndarray,
    scores: Mapping[str, np.ndarray],
    path: str | Path,
    title: str = "",
    auc: Mapping[str, float | None] | None = None,
) -> None:
    """ROC curves (false vs true positive rate, dimensionless) of each predictor's risk as a score
    for ``positive`` (critical) test frames; the GT-disparity rule dashed, the chance diagonal
    dotted; legend entries carry ``auc`` when given. Without critical or without uncritical frames
    (e.g. a small test split) the ROC is undefined: the axes say so and draw no curve."""
    fig, ax = plt.subplots(figsize=(5.2, 4.8))
    pos = np.asarray(positive, bool).ravel()
    n_pos, n_neg = int(pos.sum()), int((~pos).sum())
    if n_pos == 0 or n_neg == 0 or not scores:
        if not scores:
            why = "no predictor to draw"
        elif pos.size == 0:
            why = "no frames in the test split: ROC undefined"
        else:
            missing, other = (
                ("critical", "uncritical") if n_pos == 0 else ("uncritical", "critical")
            )
            why = f"no {missing} frames in the test split\n(all {pos.size} are {other})"
            why += ": ROC undefined"
        _say_empty(ax, why)
    else:
        for name, score in scores.items():
            fpr, tpr = roc_points(pos, score)
            a = (auc or {}).get(name)
            label = f"{name} (AUC {a:.3f})" if a is not None else name
            ax.plot(fpr, tpr, ls="--" if name in GT_INPUT else "-", lw=1.4, label=label)
        ax.plot([0, 1], [0, 1], color="0.6", ls=":", lw=1, label="chance")
        ax.legend(fontsize=8, loc="lower right")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1.01)
    ax.set_xlabel("false positive rate (uncritical frames called critical)")
    ax.set_ylabel("true positive rate (critical frames detected)")
    ax.set_title(title or "ROC on the test frames")
    ax.grid(alpha=0.3)
    save_figure(fig, path, dpi=110, bbox_inches="tight")


@dataclass(frozen=True)
class EvaluationFigurePaths:
    """Where :func:`evaluation_figures` writes each figure (PNG); no ROC figure when ``roc`` is None."""

    curves: str | Path
    scatter: str | Path
    confusion: str | Path
    examples: str | Path
    roc: str | Path | None = None


def _examples(
    source: Any, pred: pd.DataFrame, y: np.ndarray, yhat: np.ndarray, t0: float
) -> list[dict]:
    """The Fig. 7 examples (:func:`plot_examples`): the best-predicted critical frame, then the
    worst-predicted frame (:func:`~traffictwin.risk.evaluation.example_indices`, THW ``t0`` s)."""
    good, bad = example_indices(y, yhat, t0)
    wanted = {str(pred.at[i, "frame_id"]): i for i in (good, bad)}
    sel = source.frames[source.frames["frame_id"].astype(str).isin(wanted)]
    raw = {}
    for rows, arr in source.iter_arrays(sel, ["left", "disp_sgm"]):
        for j, fid in enumerate(rows["frame_id"].astype(str)):
            raw[fid] = (arr["left"][j], arr["disp_sgm"][j])
    return [
        {
            "left": raw[f][0],
            "disp": raw[f][1],
            "true": float(y[i]),
            "pred": float(yhat[i]),
            "title": ("well predicted" if i == good else "worst prediction") + f" (frame {f})",
        }
        for f, i in sorted(wanted.items(), key=lambda kv: kv[1] != good)
    ]


def evaluation_figures(
    source: Any,
    metrics: Mapping[str, Any],
    pred: pd.DataFrame,
    histories: Mapping[str, pd.DataFrame],
    main_variant: str,
    paths: EvaluationFigurePaths,
    shipped: tuple[str, str] | None = None,
) -> None:
    """The evaluation's figures from :func:`~traffictwin.risk.evaluation.evaluate_suite`'s
    ``metrics`` and per-frame ``pred`` on ``source`` (a
    :class:`~traffictwin.risk.training.RiskSource`), written to ``paths``: training ``curves`` of
    every variant (``histories``), the ``scatter`` of ``main_variant`` and the speed-only and
    geometric SGM baselines, its ``confusion`` matrix, the Fig. 7 ``examples`` (best critical /
    worst frame) and the ``roc`` curves of the headline (each seed) vs the baselines, at the
    primary THW threshold. Baselines are shown against the primary label: the headline's when it is.
    ``shipped``: (model key in ``metrics``/``pred``, legend name) of the shipped predictor, drawn
    first in the scatter and the ROC when its predictions are there."""
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
    title = f"test frames, label {main_label}"
    plot_scatter(
        y, {**first, main_variant: yhat, **scatter}, paths.scatter, risk_threshold(t0), title
    )
    if paths.roc is not None:  # the headline's runs: each seed, the collapsed ones left out
        group = metrics.get("groups", {}).get(main_variant, {}).get("members") or [main_variant]
        runs = [v for v in group if not models.get(v, {}).get("collapsed")] or [main_variant]
        scores = {**first, **{v: pred[f"pred_{v}"].to_numpy() for v in [*runs, *bases]}}
        auc = {ship[1]: models[ship[0]][at].get("roc_auc")} if ship else {}
        auc |= {v: models[v][at].get("roc_auc") for v in runs}
        auc |= {b: metrics["baselines"][b][at].get("roc_auc") for b in bases}
        plot_roc(
            y > risk_threshold(t0),
            scores,
            paths.roc,
            title=f"critical (THW < {t0:g} s) on the test frames, label {main_label}",
            auc=auc,
        )
    cm = models[main_variant][at]
    title = f"{main_variant}: THW {t0:g} s (accuracy {cm['accuracy']:.1%})"
    plot_confusion(cm["confusion"], paths.confusion, title=title)
    plot_examples(_examples(source, pred, y, yhat, t0), paths.examples)
