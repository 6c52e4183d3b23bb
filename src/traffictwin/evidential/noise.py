"""Pose-noise model (docs/design.md "Pose noise", paper III-C).

A configuration gives ``r`` (m) and ``alpha`` (deg): the 98 % two-sided intervals of zero-mean
Gaussians on x, y and yaw, drawn independently: ``sigma_xy = r / 2.326``,
``sigma_yaw = radians(alpha) / 2.326`` (2.326 = the standard normal's 99 % quantile).

Noise is drawn as standard-normal vectors ``z (N, 3)`` from a seed that depends only on the
pair id and the draw number (:func:`standard_normal_draws`), then scaled per configuration
(:func:`scale_noise`): the same pair gets the same noise *direction* in every configuration,
so evaluations across configurations are comparable and configuration A is exactly noise-free.
The noise is added to map 2's world pose (:func:`apply_pose_noise`).
"""

from __future__ import annotations

from dataclasses import MISSING, dataclass

import numpy as np

from traffictwin.config import spec

Z98 = 2.326  # two-sided 98 % interval half-width of N(0, 1) (the 99 % quantile)


def noise_sigmas(r: float, alpha_deg: float) -> tuple[float, float]:
    """Per-axis standard deviations: (sigma_xy in m, sigma_yaw in rad)."""
    if r < 0 or alpha_deg < 0:
        raise ValueError(
            f"pose noise: r (m) and alpha (deg) must be >= 0, got r={r}, alpha={alpha_deg}"
        )
    return float(r) / Z98, float(np.deg2rad(alpha_deg)) / Z98


def standard_normal_draws(
    seed: int, pair_ids: np.ndarray, draw: int | np.ndarray = 0
) -> np.ndarray:
    """Standard-normal ``(N, 3)`` draws, row i depending only on ``(seed, pair_ids[i], draw[i])``
    (``draw`` a scalar or an array broadcastable to ``pair_ids``)."""
    pair_ids = np.asarray(pair_ids, dtype=np.int64).reshape(-1)
    draws = np.broadcast_to(np.asarray(draw, dtype=np.int64), pair_ids.shape)
    out = np.empty((len(pair_ids), 3))
    for i, (pid, d) in enumerate(zip(pair_ids, draws)):
        out[i] = np.random.default_rng(
            np.random.SeedSequence([int(seed), int(pid), int(d), 7003])
        ).standard_normal(3)
    return out


def scale_noise(z: np.ndarray, r: float, alpha_deg: float) -> np.ndarray:
    """Scale standard-normal draws ``z (N, 3)`` to pose noise (dx m, dy m, dyaw rad)."""
    s_xy, s_yaw = noise_sigmas(r, alpha_deg)
    return np.asarray(z, dtype=np.float64) * np.array([s_xy, s_xy, s_yaw])


def noise_scales(
    seed: int,
    pair_ids: np.ndarray,
    draw: int | np.ndarray,
    sigmas: np.ndarray,
    kind: str = "mixture",
) -> np.ndarray:
    """Per-row noise scales ``(N, 3)`` (sigma_x m, sigma_y m, sigma_yaw rad) of a training-noise
    distribution over pose-noise configurations (docs/design.md "One model per task").

    ``sigmas (K, 3)``: the per-axis sigmas of the K configurations (:func:`noise_sigmas`).
    ``kind``: ``mixture`` — each row takes the sigmas of one configuration, chosen uniformly;
    ``scaled`` — the largest configuration's sigmas (the last row) times ``s ~ U(0, 1)``. Row ``i``
    depends only on ``(seed, pair_ids[i], draw[i])`` (its own random stream, independent of the
    standard-normal direction of :func:`standard_normal_draws`), so a pair keeps its noise level
    wherever it is generated."""
    sigmas = np.asarray(sigmas, dtype=np.float64).reshape(-1, 3)
    if not len(sigmas):
        raise ValueError("noise_scales: sigmas must name at least one configuration")
    if kind not in NOISE_KINDS:
        raise ValueError(f"noise_scales: kind must be one of {NOISE_KINDS}, got {kind!r}")
    pair_ids = np.asarray(pair_ids, dtype=np.int64).reshape(-1)
    draws = np.broadcast_to(np.asarray(draw, dtype=np.int64), pair_ids.shape)
    u = np.array(
        [
            np.random.default_rng(
                np.random.SeedSequence([int(seed), int(p), int(d), 7019])
            ).random()
            for p, d in zip(pair_ids, draws)
        ]
    )
    if kind == "mixture":
        return sigmas[np.minimum((u * len(sigmas)).astype(np.int64), len(sigmas) - 1)]
    return u[:, None] * sigmas[-1][None, :]


NOISE_KINDS = ("mixture", "scaled")


def apply_pose_noise(pose: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """World pose(s) ``(…, 3)`` plus noise ``(…, 3)``; yaw wrapped to [-pi, pi)."""
    out = np.asarray(pose, dtype=np.float64) + np.asarray(noise, dtype=np.float64)
    out[..., 2] = (out[..., 2] + np.pi) % (2 * np.pi) - np.pi
    return out


@dataclass
class PoseNoise:
    """A pose-noise configuration (``configurations.<name>`` of the params): the 98 % two-sided
    intervals ``r`` (m, per axis) and ``alpha`` (deg) of :func:`noise_sigmas`."""

    r: float = spec(MISSING, min=0.0)
    alpha: float = spec(MISSING, min=0.0, max=180.0)
