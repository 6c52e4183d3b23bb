"""Pose-noise models of the twin's evaluation: fresh per-frame noise, or a persistent GNSS-like bias.

A configuration ``(r m, alpha deg)`` scales standard-normal draws into a pose error
(:func:`traffictwin.evidential.noise.scale_noise`). The model decides which draws:

- ``frame``: ``z[t, k] = noise_z[t, k]`` — drawn afresh every frame (the fusion data's model);
- ``bias``: ``z[t, k] = sqrt(s) * bias_z[k] + sqrt(1 - s) * noise_z[t, k]`` with ``s =
  bias_share`` — a per-sequence bias of vehicle k that persists over the sequence, plus per-frame
  jitter; every draw keeps unit variance, so both models have the configuration's marginal error
  and differ only in how it persists (a twin whose registration fails keeps its ghost).
"""

from __future__ import annotations

import numpy as np

__all__ = ["NOISE_MODELS", "pose_noise_z"]

NOISE_MODELS = ("frame", "bias")


def pose_noise_z(
    noise_z: np.ndarray, bias_z: np.ndarray | None, model: str, bias_share: float = 0.8
) -> np.ndarray:
    """Standard-normal pose draws ``(T, N, 3)`` of ``model`` (see the module docstring) from the
    per-frame draws ``noise_z (T, N, 3)`` and the per-sequence ones ``bias_z (N, 3)``."""
    if model not in NOISE_MODELS:
        raise ValueError(
            f"pose noise model {model!r} unknown; expected one of {list(NOISE_MODELS)}"
        )
    if not 0.0 <= bias_share <= 1.0:
        raise ValueError(f"bias_share must be in [0, 1], got {bias_share}")
    z = np.asarray(noise_z, dtype=np.float64)
    if model == "frame":
        return z.copy()
    if bias_z is None:
        raise ValueError("the 'bias' pose noise model needs the sequence's bias draws (bias_z)")
    b = np.asarray(bias_z, dtype=np.float64)
    if b.shape != z.shape[1:]:
        raise ValueError(f"bias_z: expected shape {z.shape[1:]}, got {b.shape}")
    return np.sqrt(bias_share) * b[None] + np.sqrt(1.0 - bias_share) * z
