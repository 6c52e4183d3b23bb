"""Scoring disparity maps against the exact disparity on the same frames, with
sequence-bootstrap intervals (stages stereo_learned and sgm_variants).

:func:`frame_sums` reduces each frame to additive sums per ``<source>/<mask>`` (``common``: the
pixels with ground truth every source estimates; ``own``: each source's own estimated pixels);
:func:`evaluate` turns per-sequence sums into the metrics (EPE px, bad-1, bad-2, density, relative
range error |Z - Z_gt| / Z_gt median and p90 per distance band and on the object pixels at the
critical distances, with the share of those object pixels estimated) and their 95 % intervals,
every metric read from the same resamples.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from traffictwin.stereo.metrics import (
    CRITICAL_M,
    RANGE_EDGES_M,
    depth_error_counts,
    histogram_quantile,
    object_mask,
    range_bin_names,
)

MASKS = ("common", "own")


def critical_objects(gt: np.ndarray, fx_b: float, camera: dict[str, float]) -> np.ndarray:
    """The object pixels (:func:`~traffictwin.stereo.metrics.object_mask`) of exact disparity maps
    ``gt`` (..., H, W) px, 0 = no ground truth; ``fx_b`` focal length px x baseline m;
    ``camera`` with ``cy``, ``fy`` (px) and ``mount_height`` (m)."""
    with np.errstate(divide="ignore"):
        depth = np.where(gt > 0, fx_b / np.maximum(gt, 1e-12), np.inf)
    return object_mask(
        depth, float(camera["cy"]), float(camera["fy"]), float(camera["mount_height"])
    )


def frame_sums(
    disp: dict[str, np.ndarray], gt: np.ndarray, fx_b: float, obj: np.ndarray
) -> dict[str, dict[str, Any]]:
    """Per frame (N first), per ``<source>/<mask>``: pixel counts ``n_gt`` (GT pixels), ``n``
    (evaluated), ``abs`` (sum |d - d_gt| px), ``bad1``, ``bad2`` and the relative-range-error
    histograms ``bands`` (N, 3, E) on :data:`RANGE_EDGES_M` and ``crit`` (N, E) on the object
    pixels ``obj`` at :data:`CRITICAL_M` (:func:`depth_error_counts`), with ``crit_n_gt`` (those
    object pixels) and ``crit_n`` (of them, the ones in the mask)."""
    has = gt > 0
    both = has & np.logical_and.reduce([d >= 0 for d in disp.values()])
    out: dict[str, dict[str, Any]] = {}
    n = len(gt)
    for src, d in disp.items():
        for mask in MASKS:
            m = both if mask == "common" else has & (d >= 0)
            err = np.where(m, np.abs(d - gt), 0.0)
            dm = np.where(m, d, -1.0)  # pixels outside the mask: "no estimate"
            bands = [depth_error_counts(dm[i], gt[i], fx_b, RANGE_EDGES_M) for i in range(n)]
            crit = [
                depth_error_counts(dm[i][obj[i]], gt[i][obj[i]], fx_b, CRITICAL_M) for i in range(n)
            ]
            out[f"{src}/{mask}"] = {
                "n_gt": has.sum((1, 2)).astype(np.int64),
                "n": m.sum((1, 2)).astype(np.int64),
                "abs": err.sum((1, 2), dtype=np.float64),
                "bad1": ((err > 1.0) & m).sum((1, 2)).astype(np.int64),
                "bad2": ((err > 2.0) & m).sum((1, 2)).astype(np.int64),
                "bands": np.stack([b["hist"] for b in bands]),
                "crit": np.stack([c["hist"][0] for c in crit]),
                "crit_n_gt": np.array([c["n_gt"][0] for c in crit], np.int64),
                "crit_n": np.array([c["n_valid"][0] for c in crit], np.int64),
            }
    return out


def statistics(s: dict[str, np.ndarray], w: np.ndarray) -> dict[str, float]:
    """The metrics of per-sequence sums ``s`` weighted by ``w`` (resample counts per sequence)."""
    n = float(w @ s["n"])
    out = {
        "epe": float(w @ s["abs"]) / n if n else float("nan"),
        "bad1": float(w @ s["bad1"]) / n if n else float("nan"),
        "bad2": float(w @ s["bad2"]) / n if n else float("nan"),
        "density": n / float(w @ s["n_gt"]) if float(w @ s["n_gt"]) else float("nan"),
    }
    crit_gt = float(w @ s["crit_n_gt"])
    out["crit_obj_density"] = float(w @ s["crit_n"]) / crit_gt if crit_gt else float("nan")
    crit = np.tensordot(w, s["crit"], 1)
    out["crit_obj_relerr_median"] = histogram_quantile(crit, 0.5)
    out["crit_obj_relerr_p90"] = histogram_quantile(crit, 0.9)
    bands = np.tensordot(w, s["bands"], 1)
    for b, name in enumerate(range_bin_names(RANGE_EDGES_M)):
        out[f"{name}_relerr_median"] = histogram_quantile(bands[b], 0.5)
        out[f"{name}_relerr_p90"] = histogram_quantile(bands[b], 0.9)
    return out


def resample_weights(g: int, n_boot: int, seed: int) -> np.ndarray:
    """(n_boot, g) how often each sequence is drawn in each resample: the resamples
    :func:`traffictwin.stats.statistic_ci` draws for ``g`` clusters from ``seed``."""
    rng = np.random.default_rng(seed)
    return np.stack([np.bincount(rng.integers(0, g, size=g), minlength=g) for _ in range(n_boot)])


def interval(est: float, boot: np.ndarray, level: float = 0.95) -> tuple[float, float, float]:
    """``(estimate, lo, hi)``: the percentile interval of the finite resample values (NaN without
    any), as :func:`traffictwin.stats.statistic_ci` computes it."""
    boot = boot[np.isfinite(boot)]
    if boot.size == 0:
        return est, float("nan"), float("nan")
    a = (1.0 - level) / 2.0
    lo, hi = np.quantile(boot, [a, 1.0 - a])
    return est, float(lo), float(hi)


def evaluate(
    sums: dict[str, dict[str, np.ndarray]],
    sequences: np.ndarray,
    n_boot: int,
    seed: int = 0,
    pairs: tuple[tuple[str, str], ...] = (("learned", "sgm"),),
) -> dict[str, float]:
    """``<source>/<mask>/<metric>`` with ``_lo`` / ``_hi`` (sequence-bootstrap 95 % interval) and,
    for each ``(a, b)`` of ``pairs``, the paired ``diff_<a>_minus_<b>/<mask>/{epe,
    crit_obj_relerr_median}``; ``sums`` per frame (:func:`frame_sums`), ``sequences`` the frame's
    sequence (the bootstrap cluster). Every metric and difference reads the same resamples, each
    computed once (:func:`_stats` of all metrics per resample)."""
    codes, inv = np.unique(sequences, return_inverse=True)
    g = len(codes)
    per_seq = {  # frames summed per sequence: a resample weights the sequences by their counts
        k: {f: np.stack([v[f][inv == j].sum(0) for j in range(g)]) for f in v}
        for k, v in sums.items()
    }
    weights = resample_weights(g, n_boot, seed).astype(np.float64)
    full = {k: statistics(s, np.ones(g)) for k, s in per_seq.items()}
    boot = {  # key -> metric -> (n_boot,) values
        k: {m: np.array(v) for m, v in _columns([statistics(s, w) for w in weights]).items()}
        for k, s in per_seq.items()
    }
    out: dict[str, float] = {"test/frames": int(len(sequences)), "test/sequences": g}
    for key in per_seq:
        for metric, est in full[key].items():
            _, lo, hi = interval(est, boot[key][metric])
            out[f"{key}/{metric}"] = est
            out[f"{key}/{metric}_lo"], out[f"{key}/{metric}_hi"] = lo, hi
    for (first, second), mask in ((p, m) for p in pairs for m in MASKS):
        a, b = f"{first}/{mask}", f"{second}/{mask}"
        for metric in ("epe", "crit_obj_relerr_median"):
            key = f"diff_{first}_minus_{second}/{mask}/{metric}"
            out[key], out[key + "_lo"], out[key + "_hi"] = interval(
                full[a][metric] - full[b][metric], boot[a][metric] - boot[b][metric]
            )
    return out


def _columns(rows: list[dict[str, float]]) -> dict[str, list[float]]:
    """A list of equal-keyed dicts as one list per key."""
    return {k: [r[k] for r in rows] for k in rows[0]}
