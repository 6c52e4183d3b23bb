"""The suite's first step: every model's and baseline's per-frame risk on the evaluated split.

Networks and hybrids predict shard by shard (:meth:`RiskSource.iter_arrays`); the corridor rules
run on the same shards; the constant and speed-only baselines are fitted on the training split of
each label column and predicted on the evaluated frames.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from traffictwin.risk.baselines import constant_predictions, fit_speed_only, geometric_risk
from traffictwin.risk.evaluation.settings import RULE_INPUTS, SuiteSettings
from traffictwin.risk.metric import risk_threshold
from traffictwin.risk.predictor import RiskFrames

#: per-frame columns of frames.csv copied into the prediction table (when present)
FRAME_COLUMNS = ("scenario", "situation", "template", "t", "speed", "thw")


@dataclass
class SuitePredictions:
    """Per-frame risk (normalised) of every predictor on the evaluated frames.

    ``table``: the per-frame DataFrame (``frame_id``, :data:`FRAME_COLUMNS`, labels,
    ``pred_<variant>``, ``pred_<baseline>`` on the primary label, ``geometric_*_distance_m``);
    ``labels``: label column → true risk; ``label_of``: variant → the label it is scored against;
    ``baselines``: label → baseline → predicted risk; ``baseline_info``: label → baseline → what
    was fitted (risk.json)."""

    table: Any
    labels: dict[str, np.ndarray]
    label_of: dict[str, str]
    baselines: dict[str, dict[str, np.ndarray]]
    baseline_info: dict[str, dict[str, dict[str, Any]]]

    def prediction(self, name: str, label: str) -> np.ndarray:
        """Predicted risk of model ``name`` (its own column) or of baseline ``name`` on ``label``."""
        if name in self.label_of:
            return self.table[f"pred_{name}"].to_numpy()
        return self.baselines[label][name]


def _checked_frames(source: Any, split: str) -> tuple[Any, str]:
    """The frames of ``split`` and the frame table's path (errors: empty, no ``scenario``)."""
    frames = source.split_frames(split)
    fpath = str(source.risk.root / "frames.csv")
    if len(frames) == 0:
        raise ValueError(f"{source.risk.root}: split '{split}' has no frames after the ORB check")
    if "scenario" not in frames.columns:
        raise ValueError(f"{fpath}: column 'scenario' (the sequence = bootstrap cluster) missing")
    return frames, fpath


def _label_columns(
    models: Mapping[str, Any], settings: SuiteSettings, columns: Any
) -> tuple[list[str], dict[str, str]]:
    """The evaluated label columns (primary, present regions, the models' own) and each model's."""
    primary = settings.primary_label
    label_of = {v: str(m.meta.get("label") or primary) for v, m in models.items()}
    labels = [primary]
    labels += [c for c in settings.region_labels if c not in labels and c in columns]
    labels += [lab for lab in label_of.values() if lab not in labels]
    return labels, label_of


def _predict_models(
    models: Mapping[str, Any], arr: Mapping[str, np.ndarray], sp: np.ndarray, batch_size: int
) -> dict[str, np.ndarray]:
    """Every model's risk on one shard's arrays ``arr`` (each reads the disparity it names;
    what several compute alike, e.g. the hybrids' corridor profile, is computed once)."""
    frames = RiskFrames.of_arrays(arr, sp)
    return {v: m.predict_frames(frames, batch_size) for v, m in models.items()}


def _run_predictors(
    source: Any, models: Mapping[str, Any], frames: Any, settings: SuiteSettings
) -> tuple[Any, dict[str, np.ndarray], dict[str, np.ndarray]]:
    """``frames`` in shard order, each model's predictions and the corridor rules' outputs
    (``<rule>``: risk, ``<rule>_distance_m``: distance ahead, m) on them."""
    from traffictwin.risk.source import input_keys

    have = source.disparity_keys
    rules = [(n, k) for n, k in RULE_INPUTS if k in have] if settings.geometric else []
    keys: list[str] = sorted(
        {k for m in models.values() for k in input_keys(m.cfg)} | {k for _, k in rules}
    )
    preds: dict[str, list[np.ndarray]] = {v: [] for v in models}
    extra: dict[str, list[np.ndarray]] = {}
    order: list[np.ndarray] = []
    for rows, arr in source.iter_arrays(frames, keys):
        sp = rows["speed"].to_numpy(np.float32)
        for v, p in _predict_models(models, arr, sp, settings.batch_size).items():
            preds[v].append(p)
        if settings.geometric is not None:
            for name, k in rules:
                d, _, r = geometric_risk(arr[k], sp, source.camera, settings.rule(name))
                extra.setdefault(f"{name}_distance_m", []).append(d)
                extra.setdefault(name, []).append(r)
        order.append(rows.index.to_numpy())
    frames = frames.loc[np.concatenate(order)].reset_index(drop=True)
    model_pred = {v: np.concatenate(parts).astype(np.float64) for v, parts in preds.items()}
    rule_pred = {k: np.concatenate(v).astype(np.float64) for k, v in extra.items()}
    return frames, model_pred, rule_pred


def _fit_baselines(
    train: Any, label: str, speed: np.ndarray, settings: SuiteSettings, fpath: str
) -> tuple[dict[str, np.ndarray], dict[str, dict[str, Any]]]:
    """Constant and speed-only baselines of ``label`` fitted on ``train``, predicted at ``speed``
    (m/s, the evaluated frames), and what was fitted."""
    from traffictwin.risk.source import check_label

    ty = check_label(train, label, fpath).astype(np.float64)
    consts = constant_predictions(ty, len(speed))
    so = fit_speed_only(train["speed"].to_numpy(np.float64), ty)
    pred = {
        "train_mean": consts["train_mean"].astype(np.float64),
        "train_median": consts["train_median"].astype(np.float64),
        "speed_only": so.predict(speed),
    }
    info = {
        "train_mean": {"value": float(consts["train_mean"][0])},
        "train_median": {"value": float(consts["train_median"][0])},
        "speed_only": {
            "n_knots": int(so.speed_knots.size),
            f"critical_speed_at_{settings.t0:g}s": so.critical_speed(risk_threshold(settings.t0)),
        },
    }
    return pred, info


def predict_suite(
    source: Any, models: Mapping[str, Any], settings: SuiteSettings
) -> SuitePredictions:
    """Predict every model and baseline on ``settings.split`` of ``source``
    (:class:`traffictwin.risk.source.RiskSource`)."""
    import pandas as pd

    from traffictwin.risk.source import check_label

    frames, fpath = _checked_frames(source, settings.split)
    labels, label_of = _label_columns(models, settings, frames.columns)
    frames, model_pred, rule_pred = _run_predictors(source, models, frames, settings)
    table = pd.DataFrame({"frame_id": frames["frame_id"].to_numpy()})
    for c in (*FRAME_COLUMNS, *labels):
        if c in frames.columns:
            table[c] = frames[c].to_numpy()
    for v, p in model_pred.items():
        table[f"pred_{v}"] = p
    ys = {lab: check_label(frames, lab, fpath).astype(np.float64) for lab in labels}
    train = source.split_frames("train")
    if len(train) == 0:
        raise ValueError(f"{fpath}: the training split is empty (baselines are fitted on it)")
    speed = frames["speed"].to_numpy(np.float64)
    base_pred: dict[str, dict[str, np.ndarray]] = {}
    base_info: dict[str, dict[str, dict[str, Any]]] = {}
    for lab in labels:
        base_pred[lab], base_info[lab] = _fit_baselines(train, lab, speed, settings, fpath)
        for g, _ in RULE_INPUTS:
            if g in rule_pred:
                base_pred[lab][g] = rule_pred[g]
                base_info[lab][g] = {"params": dict(settings.rule(g).__dict__)}
    table["pred_speed_only"] = base_pred[settings.primary_label]["speed_only"]
    for g, _ in RULE_INPUTS:
        if g in rule_pred:
            table[f"pred_{g}"] = rule_pred[g]
            table[f"{g}_distance_m"] = rule_pred[f"{g}_distance_m"]
    return SuitePredictions(table, ys, label_of, base_pred, base_info)
