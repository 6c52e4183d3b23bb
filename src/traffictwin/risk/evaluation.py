"""Metrics for the risk network (Feth et al., sec. 4) and the evaluation of several predictors.

Risk scale (DESIGN.md "Risk metric"; the conversions live in :mod:`traffictwin.risk.metric`):
``risk = min(1 / THW, 20) / 20``; no vehicle ahead or speed 0 → risk 0. A situation is *critical*
when THW < t (paper: t = 1.5 s), i.e. when ``risk > risk_threshold(t)`` (= 1/30 at 1.5 s, 1/20 at
1.0 s).

Reported per predictor against a label column: MSE and MAE of the normalised risk (the paper's
"testing average error" is the MSE: 0.01470), the THW error in seconds (risk → THW, both capped at
``thw_cap`` s so "no vehicle" is finite), and at each threshold the confusion matrix laid out as
the paper's Table 1 (rows predicted, columns actual), accuracy (paper 72.87 %; Wang & Kato 70.77 %),
balanced accuracy, precision/recall/F1 of the critical class and ROC-AUC of the predicted risk as a
score for "critical".
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from traffictwin.risk.baselines import constant_predictions, geometric_risk
from traffictwin.risk.dataset import SPLITS
from traffictwin.risk.metric import CRITICAL_THW, risk_threshold, risk_to_thw

#: the paper's figures (sec. 4, Table 1) and the related work's best accuracy
PAPER = {
    "test/mse": 0.01470,
    "accuracy": 0.7287,
    "wang_kato_accuracy": 0.7077,
    "threshold_s": 1.5,
    "confusion": {"tp": 67052, "fp": 19069, "fn": 9737, "tn": 10312},
    "n_frames": 106170,
}
#: default THW thresholds (s): the paper's critical threshold first, then 1 s
THRESHOLDS_S = (CRITICAL_THW, 1.0)


def regression_metrics(y: np.ndarray, p: np.ndarray, thw_cap: float = 10.0) -> dict[str, float]:
    """``test/mse``, ``test/mae``, ``test/rmse`` (normalised risk) and THW errors in s (capped)."""
    y, p = _check(y, p)
    e = p - y
    ty, tp = risk_to_thw(y, thw_cap), risk_to_thw(p, thw_cap)
    crit = y > risk_threshold(CRITICAL_THW)
    return {
        "test/mse": float(np.mean(e**2)),
        "test/mae": float(np.mean(np.abs(e))),
        "test/rmse": float(np.sqrt(np.mean(e**2))),
        "test/thw_mae_s": float(np.mean(np.abs(tp - ty))),
        "test/thw_median_ae_s": float(np.median(np.abs(tp - ty))),
        "test/thw_mae_critical_s": float(np.mean(np.abs(tp - ty)[crit]))
        if crit.any()
        else float("nan"),
        "test/n": int(len(y)),
    }


def classification_metrics(
    y: np.ndarray, p: np.ndarray, thw_s: float = CRITICAL_THW
) -> dict[str, Any]:
    """Critical-vs-uncritical metrics at THW threshold ``thw_s``; the critical class is positive."""
    y, p = _check(y, p)
    thr = risk_threshold(thw_s)
    a, b = y > thr, p > thr
    tp, fp = int(np.sum(a & b)), int(np.sum(~a & b))
    fn, tn = int(np.sum(a & ~b)), int(np.sum(~a & ~b))
    n = max(len(y), 1)
    prec = tp / (tp + fp) if tp + fp else 0.0
    rec = tp / (tp + fn) if tp + fn else 0.0
    spec = tn / (tn + fp) if tn + fp else 0.0
    f1 = 2 * prec * rec / (prec + rec) if prec + rec else 0.0
    if a.all() or not a.any():
        bal = float("nan")
        auc = float("nan")  # undefined with a single actual class
    else:
        bal = 0.5 * (rec + spec)
        auc = roc_auc(a, p)
    return {
        "threshold_s": float(thw_s),
        "risk_threshold": float(thr),
        "confusion": {"tp": tp, "fp": fp, "fn": fn, "tn": tn},
        "confusion_pct": {
            k: 100.0 * v / n for k, v in {"tp": tp, "fp": fp, "fn": fn, "tn": tn}.items()
        },
        "accuracy": (tp + tn) / n,
        "balanced_accuracy": bal,
        "precision": prec,
        "recall": rec,
        "specificity": spec,
        "f1": f1,
        "roc_auc": auc,
        "critical_fraction_true": float(np.mean(a)) if len(a) else float("nan"),
        "critical_fraction_pred": float(np.mean(b)) if len(b) else float("nan"),
    }


def roc_auc(positive: np.ndarray, score: np.ndarray) -> float:
    """Area under the ROC curve (ties count half; the Mann–Whitney U statistic), NaN for one class."""
    positive = np.asarray(positive, bool)
    score = np.asarray(score, np.float64)
    n_pos, n_neg = int(positive.sum()), int((~positive).sum())
    if n_pos == 0 or n_neg == 0:
        return float("nan")
    from scipy.stats import rankdata

    ranks = rankdata(score)  # average ranks for ties
    return float((ranks[positive].sum() - n_pos * (n_pos + 1) / 2) / (n_pos * n_neg))


def evaluate(
    y: np.ndarray,
    p: np.ndarray,
    thresholds_s: Sequence[float] = THRESHOLDS_S,
    thw_cap: float = 10.0,
) -> dict[str, Any]:
    """Regression metrics plus ``at_<t>s`` classification metrics for every threshold."""
    out: dict[str, Any] = regression_metrics(y, p, thw_cap)
    for t in thresholds_s:
        out[f"at_{t:g}s"] = classification_metrics(y, p, t)
    return out


def confusion_labels(
    y: np.ndarray, p: np.ndarray, thw_s: float = CRITICAL_THW
) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame class names (``critical``/``uncritical``) of actual and predicted risk."""
    thr = risk_threshold(thw_s)
    names = np.array(["uncritical", "critical"])
    return names[(np.asarray(y) > thr).astype(int)], names[(np.asarray(p) > thr).astype(int)]


def label_agreement(
    a: np.ndarray, b: np.ndarray, thresholds_s: Sequence[float] = THRESHOLDS_S
) -> dict[str, Any]:
    """How two label columns (e.g. paper vs camera_fov region) differ: MSE and class agreement."""
    a, b = _check(a, b)
    out: dict[str, Any] = {
        "mse": float(np.mean((a - b) ** 2)),
        "fraction_equal": float(np.mean(np.isclose(a, b))),
    }
    for t in thresholds_s:
        thr = risk_threshold(t)
        out[f"class_agreement_at_{t:g}s"] = float(np.mean((a > thr) == (b > thr)))
    return out


def _check(y: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    y = np.asarray(y, np.float64).ravel()
    p = np.asarray(p, np.float64).ravel()
    if y.shape != p.shape:
        raise ValueError(f"labels and predictions differ in length: {y.shape} vs {p.shape}")
    if len(y) == 0:
        raise ValueError("no frames to evaluate (empty test split after the ORB check?)")
    if not (np.all(np.isfinite(y)) and np.all(np.isfinite(p))):
        raise ValueError("labels/predictions contain non-finite values")
    return y, p


def summarise_paper_comparison(metrics: Mapping[str, Any]) -> dict[str, float]:
    """Differences to the paper for one predictor's metrics (positive = worse MSE / better accuracy)."""
    at = metrics.get(f"at_{CRITICAL_THW:g}s", {})
    return {
        "mse_minus_paper": float(metrics["test/mse"]) - PAPER["test/mse"],
        "accuracy_minus_paper": float(at.get("accuracy", float("nan"))) - PAPER["accuracy"],
        "accuracy_minus_wang_kato": float(at.get("accuracy", float("nan")))
        - PAPER["wang_kato_accuracy"],
    }


# --------------------------------------------------------------------------------------------
# the whole evaluation: networks + baselines on the same test frames
# --------------------------------------------------------------------------------------------


def evaluate_suite(
    source: Any,
    models: Mapping[str, Any],
    *,
    primary_label: str,
    region_labels: Sequence[str] = ("risk_thw_paper", "risk_thw_fov"),
    thresholds_s: Sequence[float] = THRESHOLDS_S,
    thw_cap: float = 10.0,
    geometric: Any = None,
    batch_size: int = 256,
    split: str = "test",
) -> tuple[dict[str, Any], Any]:
    """Predict every model and baseline on ``split`` of ``source`` and compute the metrics.

    ``source``: :class:`traffictwin.risk.training.RiskSource`; ``models``: variant →
    :class:`traffictwin.risk.model_io.RiskModel` (its ``meta["label"]`` is the column it is scored
    against); ``geometric``: :class:`~traffictwin.risk.baselines.GeometricParams` (``None`` = skip).
    Returns ``(metrics, predictions)``: the risk.json dict and a per-frame DataFrame
    (``frame_id``, labels, ``speed``, ``pred_<variant>``, ``pred_geometric``, ``geometric_distance_m``).
    """
    import pandas as pd

    from traffictwin.risk.training import check_label, input_keys

    frames = source.split_frames(split)
    if len(frames) == 0:
        raise ValueError(f"{source.risk.root}: split '{split}' has no frames after the ORB check")
    fpath = str(source.risk.root / "frames.csv")
    labels = [primary_label] + [
        c for c in region_labels if c != primary_label and c in frames.columns
    ]
    for m in models.values():
        lab = m.meta.get("label", primary_label)
        if lab not in labels:
            labels.append(lab)
    keys: list[str] = sorted(
        {k for m in models.values() for k in input_keys(m.cfg)}
        | ({"disp_sgm"} if geometric else set())
    )
    preds: dict[str, list[np.ndarray]] = {f"pred_{v}": [] for v in models}
    geo_d: list[np.ndarray] = []
    order: list[np.ndarray] = []
    for rows, arr in source.iter_arrays(frames, keys):
        sp = rows["speed"].to_numpy(np.float32)
        for v, m in models.items():
            preds[f"pred_{v}"].append(
                m.predict(
                    arr.get("left"),
                    arr.get("disp_sgm"),
                    arr.get("disp_gt"),
                    speed=sp,
                    batch_size=batch_size,
                )
            )
        if geometric is not None:
            d, _, r = geometric_risk(arr["disp_sgm"], sp, source.camera, geometric)
            geo_d.append(d)
            preds.setdefault("pred_geometric", []).append(r)
        order.append(rows.index.to_numpy())
    ix = np.concatenate(order)
    frames = frames.loc[ix].reset_index(drop=True)
    out = pd.DataFrame({"frame_id": frames["frame_id"].to_numpy()})
    for c in ("scenario", "t", "speed", "thw", *labels):
        if c in frames.columns:
            out[c] = frames[c].to_numpy()
    for k, parts in preds.items():
        out[k] = np.concatenate(parts).astype(np.float64)
    if geo_d:
        out["geometric_distance_m"] = np.concatenate(geo_d)
    ys = {lab: check_label(frames, lab, fpath) for lab in labels}
    train = source.split_frames("train")

    def ev(y: np.ndarray, p: np.ndarray) -> dict[str, Any]:
        return evaluate(y, p, thresholds_s, thw_cap)

    metrics: dict[str, Any] = {
        "paper": PAPER,
        "split": split,
        "primary_label": primary_label,
        "thresholds_s": [float(t) for t in thresholds_s],
        "thw_cap_s": float(thw_cap),
        "n_frames": {
            "total": int(source.n_total),
            "orb_outliers_dropped": int(source.n_orb_outliers),
            **{s: int((source.frames["split"] == s).sum()) for s in SPLITS},
        },
        "models": {},
        "baselines": {},
    }
    for v, m in models.items():
        lab = m.meta.get("label", primary_label)
        entry = {
            "label": lab,
            "inputs": list(m.cfg.inputs),
            "speed": bool(m.cfg.use_speed),
            **{
                k: m.meta[k]
                for k in (
                    "n_parameters",
                    "train_seconds",
                    "best_val_mse",
                    "best_step",
                    "steps",
                    "n_train",
                )
                if k in m.meta
            },
        }
        entry.update(ev(ys[lab], out[f"pred_{v}"].to_numpy()))
        entry["vs_paper"] = summarise_paper_comparison(entry)
        metrics["models"][v] = entry
    consts = {lab: constant_predictions(check_label(train, lab, fpath), len(out)) for lab in labels}
    for name in ("train_mean", "train_median"):
        metrics["baselines"][name] = {
            "label": primary_label,
            "value": float(consts[primary_label][name][0]),
            **ev(ys[primary_label], consts[primary_label][name]),
        }
    if geometric is not None:
        metrics["baselines"]["geometric"] = {
            "label": primary_label,
            **ev(ys[primary_label], out["pred_geometric"].to_numpy()),
        }
        metrics["baselines"]["geometric"]["params"] = dict(geometric.__dict__)
    # --- the risk metric region: paper vs camera_fov --------------------------------------
    present = [c for c in region_labels if c in ys]
    if len(present) == 2:
        a, b = present
        t0 = thresholds_s[0]
        region: dict[str, Any] = {
            "labels": {
                lab: {
                    "mean": float(np.mean(ys[lab])),
                    f"critical_fraction_at_{t0:g}s": float(np.mean(ys[lab] > risk_threshold(t0))),
                }
                for lab in present
            },
            "agreement": label_agreement(ys[a], ys[b], thresholds_s),
            "predictors": {},
        }
        cands = {f"pred_{v}": v for v in models}
        if geometric is not None:
            cands["pred_geometric"] = "geometric"
        for col, name in cands.items():
            region["predictors"][name] = {}
            for lab in present:
                e = ev(ys[lab], out[col].to_numpy())
                at = e[f"at_{t0:g}s"]
                region["predictors"][name][lab] = {
                    "test/mse": e["test/mse"],
                    "test/mae": e["test/mae"],
                    "accuracy": at["accuracy"],
                    "balanced_accuracy": at["balanced_accuracy"],
                    "f1": at["f1"],
                    "roc_auc": at["roc_auc"],
                }
        for name in ("train_mean", "train_median"):
            for lab in present:
                e = ev(ys[lab], consts[lab][name])
                region["predictors"].setdefault(name, {})[lab] = {
                    "test/mse": e["test/mse"],
                    "test/mae": e["test/mae"],
                    "accuracy": e[f"at_{t0:g}s"]["accuracy"],
                }
        # skill = 1 - MSE / MSE of the training-mean predictor of the same label (R²-like; 0 = no better
        # than a constant, 1 = perfect): comparable across labels whose spread and critical share differ
        for per in region["predictors"].values():
            for lab, e in per.items():
                ref = region["predictors"]["train_mean"][lab]["test/mse"]
                e["skill"] = 1.0 - e["test/mse"] / ref if ref > 0 else float("nan")
        metrics["region"] = region
    return _finite_or_none(metrics), out


def main_series(
    metrics: Mapping[str, Any], pred: Any, variant: str
) -> tuple[str, np.ndarray, np.ndarray]:
    """(label, true risk, predicted risk) of ``variant`` on the test frames of ``pred``
    (:func:`evaluate_suite`'s outputs)."""
    label = metrics["models"][variant]["label"]
    return label, pred[label].to_numpy(), pred[f"pred_{variant}"].to_numpy()


def example_indices(y: np.ndarray, p: np.ndarray, thw_s: float) -> tuple[int, int]:
    """The paper's Fig. 7 frames: the best-predicted critical frame (the best frame when none is
    critical) and the worst-predicted frame (the second worst when that is the same frame)."""
    err = np.abs(p - y)
    crit = np.flatnonzero(y > risk_threshold(thw_s))
    good = int(crit[np.argmin(err[crit])]) if len(crit) else int(np.argmin(err))
    bad = (
        int(np.argsort(err)[-2])
        if int(np.argmax(err)) == good and len(err) > 1
        else int(np.argmax(err))
    )
    return good, bad


def confusion_table(frame_id: Any, y: np.ndarray, p: np.ndarray, thw_s: float) -> Any:
    """``frame_id``, ``actual``, ``predicted`` class per frame (the ``dvc plots`` confusion data)."""
    import pandas as pd

    actual, predicted = confusion_labels(y, p, thw_s)
    return pd.DataFrame({"frame_id": frame_id, "actual": actual, "predicted": predicted})


def tracking_metrics(metrics: Mapping[str, Any], variant: str) -> dict[str, float]:
    """Test metrics of ``variant`` to add to its training run: MSE, MAE, THW MAE and, at the
    primary threshold, accuracy, balanced accuracy, F1 and ROC-AUC (undefined ones left out)."""
    e = metrics["models"][variant]
    vals = {k: e[k] for k in ("test/mse", "test/mae", "test/thw_mae_s") if e.get(k) is not None}
    at = e.get(f"at_{metrics['thresholds_s'][0]:g}s", {})
    for k in ("accuracy", "balanced_accuracy", "f1", "roc_auc"):
        if at.get(k) is not None:
            vals[f"test/{k}"] = at[k]
    return vals


def _finite_or_none(obj: Any) -> Any:
    """JSON-safe: NaN/inf floats → None (strict JSON has no NaN), recursively."""
    if isinstance(obj, Mapping):
        return {k: _finite_or_none(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite_or_none(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        return f if np.isfinite(f) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj
