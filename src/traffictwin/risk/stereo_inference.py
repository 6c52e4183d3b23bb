"""The learned stereo network at inference on user pairs: its disparity with the spread mask
applied exactly as the ``stereo_learned`` stage applies it (px, ``-1`` where the spread exceeds
the threshold calibrated on validation, ``spread_threshold_px`` of the sealed model meta), and a
per-pixel confidence in [0, 1] for users of either source."""

from __future__ import annotations

from typing import Any

import numpy as np

from traffictwin.risk.stereo_io import predict


def spread_threshold(net: Any) -> float:
    """The model's spread threshold (px) from its sealed meta; ``ValueError`` if absent."""
    meta = getattr(net, "meta", None) or {}
    try:
        thr = float(meta["spread_threshold_px"])
    except (KeyError, TypeError, ValueError):
        raise ValueError(
            "the stereo model's meta has no numeric 'spread_threshold_px' (load it with "
            "load_stereo_model, which reads the sealed meta)"
        ) from None
    if not thr > 0:
        raise ValueError(f"the stereo model's 'spread_threshold_px' must be > 0, got {thr}")
    return thr


def learned_disparity(
    net: Any,
    left: np.ndarray,
    right: np.ndarray,
    sgm: np.ndarray | None = None,
    batch_size: int = 8,
) -> tuple[np.ndarray, np.ndarray]:
    """``(disparity, spread)`` (N, H, W) float32 px of BGR uint8 pairs (N, H, W, 3): the
    network's disparity, ``-1`` where its spread exceeds :func:`spread_threshold`. A ``base:
    sgm`` model refines ``sgm`` (N, H, W) px (SGM's map of the same pairs, ``-1`` invalid)."""
    thr = spread_threshold(net)
    disp, spread = predict(net, left, right, batch_size, sgm=sgm)
    return np.where(spread <= thr, disp, -1.0).astype(np.float32), spread


def disparity_confidence(
    disp: np.ndarray, spread: np.ndarray | None = None, threshold: float | None = None
) -> np.ndarray:
    """Per-pixel confidence float32 in [0, 1] of a disparity map (px, ``< 0`` invalid): 0 where
    invalid; without ``spread`` (SGM, which grades none) 1 on every valid pixel; with the
    network's ``spread`` (px) and its ``threshold`` (px) ``1 - spread / threshold``."""
    valid = np.asarray(disp) >= 0
    if spread is None:
        return valid.astype(np.float32)
    if threshold is None or not threshold > 0:
        raise ValueError(f"disparity_confidence: threshold must be > 0 px, got {threshold}")
    conf = np.clip(1.0 - np.asarray(spread, np.float64) / float(threshold), 0.0, 1.0)
    return np.where(valid, conf, 0.0).astype(np.float32)
