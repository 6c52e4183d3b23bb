"""Choices made on the validation split (none on test: the test split is read once, for the report).

* :func:`best_cut` — the decision threshold of a predictor's risk score that maximises the
  balanced accuracy of "critical" (THW below a threshold) on validation frames.
* :func:`tune_half_width` — the corridor rule's half-width (m): the candidate with the highest
  validation ROC-AUC (ties: the higher balanced accuracy at the rule's own cut, then the narrower).
* :func:`choose` — the predictor to ship: the highest validation ROC-AUC at the primary
  threshold among the candidates; a tie goes to the simpler one (rule, then hybrid, then network).
* :func:`too_few` — why the validation labels cannot rank candidates at all (fewer than
  :data:`MIN_CLASS_FRAMES` critical or uncritical frames): no choice is then made on validation,
  each falls back to its documented prior (a NaN score never decides what ships).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from traffictwin.risk.baselines import thw_from_distance
from traffictwin.risk.evaluation.scoring import roc_auc
from traffictwin.risk.metric import risk_threshold, thw_to_risk

#: tie-break order of :func:`choose` (simplest first)
SIMPLICITY = ("geometric", "hybrid", "dave2")
#: fewest critical and fewest uncritical validation frames that can rank candidates
MIN_CLASS_FRAMES = 5


def too_few(positive: np.ndarray, min_class: int = MIN_CLASS_FRAMES) -> str | None:
    """Why the validation labels ``positive`` (critical frames) cannot rank candidates: fewer
    than ``min_class`` critical or uncritical frames; None when they can."""
    pos = np.asarray(positive, bool).reshape(-1)
    n_pos = int(pos.sum())
    n_neg = int(pos.size - n_pos)
    if n_pos < min_class:
        return (
            f"not enough validation positives (n={n_pos} critical of {pos.size} frames, "
            f"{min_class} needed)"
        )
    if n_neg < min_class:
        return (
            f"not enough validation negatives (n={n_neg} uncritical of {pos.size} frames, "
            f"{min_class} needed)"
        )
    return None


def balanced_accuracy(positive: np.ndarray, predicted: np.ndarray) -> float:
    """(recall + specificity) / 2; NaN without both classes."""
    pos, pred = np.asarray(positive, bool), np.asarray(predicted, bool)
    if pos.all() or not pos.any():
        return float("nan")
    return float(0.5 * (np.mean(pred[pos]) + np.mean(~pred[~pos])))


def best_cut(positive: np.ndarray, score: np.ndarray, default: float) -> tuple[float, float]:
    """``(cut, balanced accuracy)``: the threshold on ``score`` ("critical" when ``score > cut``)
    with the highest balanced accuracy for ``positive``; candidates are the midpoints between
    consecutive distinct scores and just below the smallest. Ties: the cut nearest ``default``
    (the label's own threshold). Without both classes: ``(default, NaN)``."""
    pos = np.asarray(positive, bool).reshape(-1)
    s = np.asarray(score, np.float64).reshape(-1)
    if pos.shape != s.shape:
        raise ValueError(f"best_cut: {pos.size} labels but {s.size} scores")
    if not np.all(np.isfinite(s)):
        raise ValueError("best_cut: scores must be finite")
    if pos.all() or not pos.any():
        return float(default), float("nan")
    u = np.unique(s)
    cuts = np.concatenate([[u[0] - 1e-9], (u[:-1] + u[1:]) / 2.0]) if u.size > 1 else u - 1e-9
    sp, sn = np.sort(s[pos]), np.sort(s[~pos])
    tpr = 1.0 - np.searchsorted(sp, cuts, "right") / sp.size  # share of positives above the cut
    tnr = np.searchsorted(sn, cuts, "right") / sn.size  # share of negatives at or below it
    ba = 0.5 * (tpr + tnr)
    best = np.flatnonzero(np.isclose(ba, ba.max(), rtol=0, atol=1e-12))
    i = best[np.argmin(np.abs(cuts[best] - default))]
    return float(cuts[i]), float(ba[i])


def tune_half_width(
    distances: np.ndarray,
    speed: np.ndarray,
    positive: np.ndarray,
    half_widths: Sequence[float],
    threshold_s: float,
    prior: float | None = None,
    min_class: int = MIN_CLASS_FRAMES,
) -> tuple[float, list[dict[str, float]]]:
    """The corridor half-width (m) of the rule with free distances ``distances`` (N, K) m for
    ``half_widths`` (K,) and speeds (N,) m/s, scored for ``positive`` (critical at
    ``threshold_s``): highest ROC-AUC, then balanced accuracy at the rule's own cut (THW <
    ``threshold_s``), then the narrower band. Returns the width and the table of every candidate.

    With too few critical or uncritical frames to rank (:func:`too_few`) the width is ``prior``
    (m; the label's own corridor half-width), which need not be a candidate; without a prior
    that is a ValueError."""
    d = np.asarray(distances, np.float64)
    hw = [float(w) for w in half_widths]
    if d.ndim != 2 or d.shape[1] != len(hw):
        raise ValueError(f"tune_half_width: distances {d.shape} for {len(hw)} half-widths")
    risk = thw_to_risk(thw_from_distance(d, np.asarray(speed, np.float64)))
    thr = risk_threshold(threshold_s)
    table = [
        {
            "half_width": w,
            "roc_auc": roc_auc(positive, risk[:, k]),
            "balanced_accuracy": balanced_accuracy(positive, risk[:, k] > thr),
        }
        for k, w in enumerate(hw)
    ]
    reason = too_few(positive, min_class)
    if reason is not None:
        if prior is None:
            raise ValueError(f"tune_half_width: {reason} and no prior half-width")
        return float(prior), table

    def key(r: dict[str, float]) -> tuple[float, float, float]:
        auc, ba = r["roc_auc"], r["balanced_accuracy"]
        return (
            auc if np.isfinite(auc) else -1.0,
            ba if np.isfinite(ba) else -1.0,
            -r["half_width"],
        )

    return max(table, key=key)["half_width"], table


def choose(candidates: Mapping[str, Mapping[str, Any]]) -> str:
    """The candidate (name → ``{"roc_auc": validation AUC, "kind": dave2|hybrid|geometric}``)
    with the highest validation ROC-AUC; ties go to the simpler kind (:data:`SIMPLICITY`).
    Candidates without a finite AUC are never chosen; none with one is a ValueError."""
    if not candidates:
        raise ValueError("choose: no candidate predictors")
    scored = {n: c for n, c in candidates.items() if np.isfinite(float(c["roc_auc"]))}
    if not scored:
        raise ValueError(
            f"choose: no candidate has a finite validation ROC-AUC ({sorted(candidates)})"
        )

    def key(name: str) -> tuple[float, int]:
        c = candidates[name]
        auc = float(c["roc_auc"])
        kind = str(c.get("kind", "dave2"))
        rank = SIMPLICITY.index(kind) if kind in SIMPLICITY else len(SIMPLICITY)
        return (round(auc, 12), -rank)

    return max(scored, key=key)
