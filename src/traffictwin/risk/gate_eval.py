"""Promotion-gate evaluation of risk networks: a fixed test set and an ``evaluate(model_uri)``.

The gate (:mod:`traffictwin.mlops.gate`) re-evaluates challenger and champion with the same
callable; this one predicts with a registered model (its own preprocessing) on the raw
ORB-passed test frames and scores with :func:`traffictwin.risk.evaluation.evaluate`. Models are
loaded with :func:`traffictwin.mlops.registry.load_registered` (SHA-256 checked, ``weights_only``)
and :func:`traffictwin.risk.model_io.load_risk_model`; a model whose recorded config this version
cannot build is known-incompatible (:func:`config_incompatibility`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from traffictwin.mlops.gate import GateError


def config_incompatibility(meta: Mapping[str, Any]) -> str | None:
    """Why a risk model whose ``model_meta.json`` is ``meta`` cannot be built by this version
    (its ``config`` is missing or not a valid :class:`~traffictwin.risk.dave2.Dave2Config`, or
    for a corridor rule / hybrid not a valid architecture);
    ``None`` if it can. Any valid config runs on the raw test frames (they are resized to it)."""
    from traffictwin.risk.dave2 import Dave2Config

    cfg = meta.get("config")
    if not isinstance(cfg, Mapping):
        return "its model_meta.json has no network 'config'"
    if cfg.get("kind") in ("hybrid", "geometric"):  # the corridor hybrid / rule (risk.predictors)
        from traffictwin.risk.predictors import architecture_problem

        return architecture_problem(cfg)
    try:
        Dave2Config.from_dict(dict(cfg))
    except (TypeError, ValueError, KeyError) as exc:
        return f"its network config is not valid here ({exc})"
    return None


def load_registered_risk(uri: str):
    """The :class:`~traffictwin.risk.model_io.RiskModel` behind a registry URI (SHA-256 checked,
    ``weights_only``); its ``meta`` is the model's ``model_meta.json``."""
    from traffictwin.mlops.registry import load_registered
    from traffictwin.risk.model_io import load_risk_model

    return load_registered(uri, load_risk_model, check=config_incompatibility)


def risk_test_set(
    risk_root: str | Path,
    disparity_root: str | Path,
    orb_csv: str | Path | None,
    split: str = "val",
    max_frames: int | None = None,
) -> tuple[dict[str, np.ndarray], str]:
    """Raw frames of the ORB-passed split (``left``, ``disp_sgm``, ``disp_gt``, ``speed`` and every
    ``risk*`` label column as ``label:<column>``), the first ``max_frames`` by frame id, and the
    fingerprint."""
    import pandas as pd

    from traffictwin.io.shards import sha256_file
    from traffictwin.risk.source import RiskSource

    src = RiskSource(risk_root, disparity_root, orb_csv)
    frames = src.split_frames(split).sort_values("frame_id", kind="stable")
    if max_frames:
        frames = frames.iloc[:max_frames]
    parts: dict[str, list[np.ndarray]] = {"left": [], "disp_sgm": [], "disp_gt": []}
    rows_all = []
    for rows, arrays in src.iter_arrays(frames, ["left", "disp_sgm", "disp_gt"]):
        for k in parts:
            parts[k].append(arrays[k])
        rows_all.append(rows)
    if not rows_all:
        raise GateError(f"{risk_root}: no ORB-passed frames in split '{split}' to evaluate on")
    rows = pd.concat(rows_all)
    data = {k: np.concatenate(v) for k, v in parts.items()}
    data["speed"] = rows["speed"].to_numpy(np.float32)
    for c in rows.columns:
        if c.startswith("risk"):
            data[f"label:{c}"] = rows[c].to_numpy(np.float32)
    orb_fp = sha256_file(orb_csv)[:8] if orb_csv else "none"
    disp_fp = src.disparity.manifest_hash()[:8] if src.disparity else "none"
    fp = f"risk:{src.risk.manifest_hash()[:16]}:disp:{disp_fp}:orb:{orb_fp}:{split}:{len(rows)}"
    return data, fp


def risk_evaluator(
    data: Mapping[str, np.ndarray],
    label: str,
    thresholds_s: Sequence[float],
    thw_cap: float = 10.0,
    batch_size: int = 256,
    split: str = "val",
) -> Callable[[str], dict[str, float]]:
    """``evaluate(model_uri)``: predicted risk of the registered model on the raw frames of
    ``split`` (the gate's: validation, the test split is read once by the evaluation), scored with
    :func:`traffictwin.risk.evaluation.evaluate` against ``label``.

    Returns ``<split>/mse``, ``<split>/mae``, … and ``<split>/accuracy`` (+
    ``<split>/balanced_accuracy``, ``<split>/roc_auc``) at the first threshold."""
    from traffictwin.risk import evaluation as rm

    key = f"label:{label}"
    if key not in data:
        have = sorted(k[6:] for k in data if k.startswith("label:"))
        raise GateError(f"risk label column '{label}' not in frames.csv (has {have})")
    y = np.asarray(data[key], np.float32)

    def evaluate(uri: str) -> dict[str, float]:
        rmodel = load_registered_risk(uri)
        p = rmodel.predict(
            left_bgr=data["left"],
            disp_sgm=data["disp_sgm"],
            disp_gt=data["disp_gt"],
            speed=data["speed"],
            batch_size=batch_size,
        )
        res = rm.evaluate(y, p, thresholds_s=tuple(thresholds_s), thw_cap=thw_cap)
        out = {
            k.replace("test/", f"{split}/", 1): float(v)
            for k, v in res.items()
            if isinstance(v, (int, float))
        }
        first = res[f"at_{float(thresholds_s[0]):g}s"]
        out[f"{split}/accuracy"] = float(first["accuracy"])
        out[f"{split}/balanced_accuracy"] = float(first["balanced_accuracy"])
        out[f"{split}/roc_auc"] = float(first["roc_auc"])
        return out

    return evaluate
