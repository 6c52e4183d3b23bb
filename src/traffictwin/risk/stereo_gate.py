"""The promotion gate of the learned stereo network (``traffictwin-stereo``): a registered
version and the champion are scored on the same fixed gate set, the fault-free pairs of one split
of ``data/risk`` (with ``data/disparity``'s SGM for a network that refines it), by the end-point
error (px) of their disparity over the pixels with exact disparity that each marks valid."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np


def load_registered_stereo(uri: str):
    """The :class:`~traffictwin.stereo.network.StereoNet` behind a registry URI (SHA-256 checked,
    ``weights_only``); ``net.meta`` is its sealed meta."""
    from traffictwin.mlops.registry import load_registered
    from traffictwin.risk.stereo_io import load_stereo_model

    return load_registered(uri, load_stereo_model)


def stereo_test_set(
    risk_root: str | Path,
    disparity_root: str | Path | None,
    split: str = "val",
    max_frames: int | None = None,
) -> tuple[dict[str, np.ndarray], str]:
    """The fault-free pairs of ``split`` (``left``, ``right``, ``disp_gt`` and, with
    ``disparity_root``, ``disp_sgm``), ``max_frames`` evenly spaced (None = all), and the gate
    set's fingerprint."""
    from traffictwin.io.shards import Dataset
    from traffictwin.risk.stereo_training import load_pairs

    data = load_pairs(risk_root, split, int(max_frames or 0), disparity=disparity_root)
    risk_fp = Dataset(risk_root, kind="risk", verify=False).manifest_hash()[:16]
    disp_fp = (
        Dataset(disparity_root, kind="disparity", verify=False).manifest_hash()[:8]
        if disparity_root is not None
        else "none"
    )
    return data, f"stereo:{risk_fp}:disp:{disp_fp}:{split}:{len(data['left'])}"


def stereo_scores(disp: np.ndarray, gt: np.ndarray, split: str) -> dict[str, float]:
    """``<split>/epe`` (mean |d - d_gt| px), ``<split>/bad1`` (share > 1 px) over the pixels with
    exact disparity (``gt > 0``) that ``disp`` marks valid (``>= 0``), and ``<split>/density``
    (that share of the exact pixels)."""
    has = gt > 0
    m = has & (disp >= 0)
    err = np.abs(disp - gt)[m].astype(np.float64)
    n = int(m.sum())
    return {
        f"{split}/epe": float(err.mean()) if n else float("nan"),
        f"{split}/bad1": float((err > 1.0).mean()) if n else float("nan"),
        f"{split}/density": n / max(int(has.sum()), 1),
    }


def stereo_evaluator(
    data: Mapping[str, np.ndarray], batch_size: int = 8, split: str = "val"
) -> Callable[[str], dict[str, float]]:
    """``evaluate(model_uri)``: :func:`stereo_scores` of the registered network's disparity
    (:func:`~traffictwin.risk.stereo_inference.learned_disparity`) on the gate set ``data``."""
    from traffictwin.risk.stereo_inference import learned_disparity

    def evaluate(uri: str) -> dict[str, float]:
        net = load_registered_stereo(uri)
        disp, _ = learned_disparity(
            net, data["left"], data["right"], sgm=data.get("disp_sgm"), batch_size=batch_size
        )
        return stereo_scores(disp, data["disp_gt"], split)

    return evaluate
