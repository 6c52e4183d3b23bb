"""Fusion metrics (docs/design.md "Fusion metrics"), vectorised over batches of evidential grid maps.

Masses: ``(N, 2, H, W)`` (or a single ``(2, H, W)``, treated as ``N = 1``), channel 0 = ``m_F``,
1 = ``m_O``, ``u = 1 − m_F − m_O``. ``label`` and ``pred`` share the layout.

- **KLD (a)** ``kld_fo``: KL(label ‖ pred) over the two masses ``(m_F, m_O)``, both clipped to
  ``[eps, 1]`` (eps = 1e-7), summed over the two channels and averaged over cells — the Keras
  ``KLDivergence`` definition the authors' group uses in its public code.
- **KLD (b)** ``kld_fou``: KL over the full vector ``(m_F, m_O, u)``, same clipping, summed over
  the three entries, averaged over cells.
- **Classification.** Pignistic ``p_O = m_O + u/2``; predicted occupied where ``p_O > 0.5``,
  predicted free where ``p_O < 0.5`` (``p_O = 0.5``, e.g. a fully unknown cell, is neither and
  so counts as a miss for both classes). A cell's label is known where ``y_O > 0.5`` (occupied)
  or ``y_F > 0.5`` (free); only known cells count. Per class ``c``: TP = pred c ∧ label c,
  FP = pred c ∧ label other, FN = ¬pred c ∧ label c; precision = TP/(TP+FP), recall =
  TP/(TP+FN), Dice = 2TP/(2TP+FP+FN) (NaN where the denominator is 0).
- **Mean uncertainty** ``u_mean``: mean of ``u`` over all cells (and ``u_mean_known`` over
  label-known cells).
- **AUROC of u for errors** (:class:`UncertaintyAUROC`): over label-known cells, positives are
  wrongly classified cells (predicted class ≠ label class, ``p_O = 0.5`` counts as wrong),
  scores are ``u``; AUROC = P(u_wrong > u_right) + ½ P(tie), from streaming histograms of ``u``
  (``bins`` bins on [0, 1]; values in the same bin count as ties).

Per-sample values come from :func:`per_sample_metrics`; :func:`aggregate` pools them (KLD mean /
median / quantiles over samples, P/R/Dice from pooled counts = micro average, plus the mean of
per-sample Dice). :func:`pose_error_bins` bins samples by the actual pose error drawn.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from traffictwin.evidential.masses import unknown_mass

__all__ = [
    "EPS",
    "as_batch",
    "p_occupied",
    "kld_fo",
    "kld_fou",
    "label_classes",
    "confusion_counts",
    "prf",
    "per_sample_metrics",
    "UncertaintyAUROC",
    "u_error_histograms",
    "auroc_from_hist",
    "auroc_with_counts",
    "AUROC_MIN_WRONG",
    "AUROC_MIN_PAIRS",
    "aggregate",
    "pose_error_bins",
    "COUNT_KEYS",
]

EPS = 1e-7
CLASSES = ("occ", "free")
COUNT_KEYS = tuple(f"{k}_{c}" for c in CLASSES for k in ("tp", "fp", "fn"))


def as_batch(m: np.ndarray, name: str = "masses") -> np.ndarray:
    """``(2,H,W)`` → ``(1,2,H,W)``; ``(N,2,H,W)`` unchanged; anything else → ``ValueError`` naming ``name``."""
    m = np.asarray(m)
    if m.ndim == 3:
        m = m[None]
    if m.ndim != 4 or m.shape[1] != 2:
        raise ValueError(f"{name}: expected masses (2,H,W) or (N,2,H,W), got shape {m.shape}")
    return m


def _pair(label: np.ndarray, pred: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    label = as_batch(label, "label")
    pred = as_batch(pred, "pred")
    if label.shape != pred.shape:
        raise ValueError(f"label {label.shape} and pred {pred.shape} must have the same shape")
    return label.astype(np.float64, copy=False), pred.astype(np.float64, copy=False)


def p_occupied(m: np.ndarray) -> np.ndarray:
    """Pignistic probability of "occupied" ``p_O = m_O + u/2`` (paper eq. 2), shape ``(N,H,W)``."""
    m = as_batch(m)
    return m[:, 1] + 0.5 * unknown_mass(m)


def _kl_terms(y: np.ndarray, p: np.ndarray, eps: float) -> np.ndarray:
    y = np.clip(y, eps, 1.0)
    p = np.clip(p, eps, 1.0)
    return y * np.log(y / p)


def kld_fo(label: np.ndarray, pred: np.ndarray, eps: float = EPS) -> np.ndarray:
    """KLD definition (a): Σ over (m_F, m_O) of y·log(y/p), clipped to [eps, 1], mean over cells → ``(N,)``."""
    y, p = _pair(label, pred)
    return _kl_terms(y, p, eps).sum(axis=1).mean(axis=(1, 2))


def kld_fou(label: np.ndarray, pred: np.ndarray, eps: float = EPS) -> np.ndarray:
    """KLD definition (b): over the full vector (m_F, m_O, u), clipped to [eps, 1], mean over cells → ``(N,)``."""
    y, p = _pair(label, pred)
    yy = np.concatenate([y, unknown_mass(y)[:, None]], axis=1)
    pp = np.concatenate([p, unknown_mass(p)[:, None]], axis=1)
    return _kl_terms(yy, pp, eps).sum(axis=1).mean(axis=(1, 2))


def label_classes(label: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Boolean ``(occupied, free)`` label maps ``(N,H,W)``: ``y_O > 0.5`` / ``y_F > 0.5``."""
    y = as_batch(label, "label")
    return y[:, 1] > 0.5, y[:, 0] > 0.5


def confusion_counts(label: np.ndarray, pred: np.ndarray) -> dict[str, np.ndarray]:
    """Per-sample TP/FP/FN for both classes over label-known cells; int64 arrays ``(N,)`` keyed ``tp_occ`` …"""
    y, p = _pair(label, pred)
    lab_o, lab_f = label_classes(y)
    po = p_occupied(p)
    pred_o, pred_f = po > 0.5, po < 0.5
    s = lambda a: a.sum(axis=(1, 2)).astype(np.int64)  # noqa: E731
    return {
        "tp_occ": s(pred_o & lab_o),
        "fp_occ": s(pred_o & lab_f),
        "fn_occ": s(~pred_o & lab_o),
        "tp_free": s(pred_f & lab_f),
        "fp_free": s(pred_f & lab_o),
        "fn_free": s(~pred_f & lab_f),
        "n_known": s(lab_o | lab_f),
    }


def prf(
    tp: np.ndarray | float, fp: np.ndarray | float, fn: np.ndarray | float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Precision, recall, Dice from counts (NaN where a denominator is 0)."""
    tp, fp, fn = (np.asarray(v, dtype=np.float64) for v in (tp, fp, fn))
    with np.errstate(invalid="ignore", divide="ignore"):
        precision = np.where(tp + fp > 0, tp / np.maximum(tp + fp, 1), np.nan)
        recall = np.where(tp + fn > 0, tp / np.maximum(tp + fn, 1), np.nan)
        dice = np.where(2 * tp + fp + fn > 0, 2 * tp / np.maximum(2 * tp + fp + fn, 1), np.nan)
    return precision, recall, dice


def per_sample_metrics(
    label: np.ndarray, pred: np.ndarray, eps: float = EPS
) -> dict[str, np.ndarray]:
    """Every per-sample metric as arrays ``(N,)``: KLDs, counts, P/R/Dice per class, mean u."""
    y, p = _pair(label, pred)
    out: dict[str, np.ndarray] = {"kld_fo": kld_fo(y, p, eps), "kld_fou": kld_fou(y, p, eps)}
    counts = confusion_counts(y, p)
    out.update(counts)
    for c in CLASSES:
        pr, rc, dc = prf(counts[f"tp_{c}"], counts[f"fp_{c}"], counts[f"fn_{c}"])
        out[f"precision_{c}"], out[f"recall_{c}"], out[f"dice_{c}"] = pr, rc, dc
    u = unknown_mass(p)
    lab_o, lab_f = label_classes(y)
    known = lab_o | lab_f
    out["u_mean"] = u.mean(axis=(1, 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        out["u_mean_known"] = np.where(
            known.sum(axis=(1, 2)) > 0,
            (u * known).sum(axis=(1, 2)) / np.maximum(known.sum(axis=(1, 2)), 1),
            np.nan,
        )
    return out


def auroc_from_hist(pos: np.ndarray, neg: np.ndarray) -> float | np.ndarray:
    """AUROC = P(score_pos > score_neg) + ½ P(equal bin) from two histograms over the same bins.

    ``pos``, ``neg``: ``(bins,)`` → a float; or ``(..., bins)`` (e.g. one histogram per bootstrap
    resample) → an array of the leading shape. NaN where a class is empty.
    """
    pos = np.asarray(pos, dtype=np.float64)
    neg = np.asarray(neg, dtype=np.float64)
    if pos.shape != neg.shape:
        raise ValueError(f"auroc_from_hist: pos {pos.shape} and neg {neg.shape} differ")
    n_pos, n_neg = pos.sum(axis=-1), neg.sum(axis=-1)
    neg_below = np.cumsum(neg, axis=-1) - neg  # negatives in strictly lower bins
    num = (pos * (neg_below + 0.5 * neg)).sum(axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where((n_pos > 0) & (n_neg > 0), num / np.maximum(n_pos * n_neg, 1e-300), np.nan)
    return float(out) if out.ndim == 0 else out


AUROC_MIN_WRONG = 100  # fewer wrong cells than this: AUROC(u) is not reported (too few wrong cells)
AUROC_MIN_PAIRS = (
    10  # ... nor with wrong cells in fewer pairs than this (one pair's errors are one event)
)


def auroc_with_counts(
    pos: np.ndarray,
    neg: np.ndarray,
    min_wrong: int = AUROC_MIN_WRONG,
    min_pairs: int = AUROC_MIN_PAIRS,
) -> dict[str, float | int | bool]:
    """AUROC of u as a detector of wrong cells, with the counts behind it.

    ``pos`` / ``neg``: per-pair histograms of u on wrongly / rightly classified label-known cells
    ``(N, bins)`` (:func:`u_error_histograms`). Returns ``u_auroc`` (NaN unless ``u_auroc_enough``),
    ``u_auroc_n_wrong`` / ``u_auroc_n_right`` (cells), ``u_auroc_pairs_wrong`` (pairs with at
    least one wrong cell) and ``u_auroc_enough``: at least ``min_wrong`` wrong cells in at least
    ``min_pairs`` pairs, and at least one right cell. Below that an AUROC ranks a handful of
    cells (often of one or two pairs) and says nothing about the uncertainty: it is withheld.
    """
    pos = np.atleast_2d(np.asarray(pos, dtype=np.int64))
    neg = np.atleast_2d(np.asarray(neg, dtype=np.int64))
    if pos.shape != neg.shape:
        raise ValueError(f"auroc_with_counts: pos {pos.shape} and neg {neg.shape} differ")
    n_wrong, n_right = int(pos.sum()), int(neg.sum())
    pairs = int((pos.sum(axis=1) > 0).sum())
    enough = n_wrong >= min_wrong and pairs >= min_pairs and n_right > 0
    value = auroc_from_hist(pos.sum(axis=0), neg.sum(axis=0)) if enough else float("nan")
    return {
        "u_auroc": float(value),
        "u_auroc_n_wrong": n_wrong,
        "u_auroc_n_right": n_right,
        "u_auroc_pairs_wrong": pairs,
        "u_auroc_enough": bool(enough),
    }


def u_error_histograms(
    label: np.ndarray, pred: np.ndarray, bins: int
) -> tuple[np.ndarray, np.ndarray]:
    """Per-sample histograms of ``u`` (``bins`` bins on [0, 1]) over label-known cells that are
    wrongly (``pos``) / rightly (``neg``) classified: two int64 arrays ``(N, bins)``."""
    y, p = _pair(label, pred)
    lab_o, lab_f = label_classes(y)
    known = lab_o | lab_f
    po = p_occupied(p)
    right = (lab_o & (po > 0.5)) | (lab_f & (po < 0.5))
    wrong = known & ~right
    n = y.shape[0]
    idx = np.minimum((unknown_mass(p) * bins).astype(np.int64), bins - 1)
    idx = np.clip(idx, 0, bins - 1) + bins * np.arange(n)[:, None, None]  # one bin range per sample
    pos = np.bincount(idx[wrong], minlength=n * bins).reshape(n, bins)
    neg = np.bincount(idx[known & right], minlength=n * bins).reshape(n, bins)
    return pos, neg


@dataclass
class UncertaintyAUROC:
    """Streaming AUROC of the uncertainty ``u`` as a detector of wrongly classified label-known cells.

    With ``keep_samples`` it also keeps each sample's histograms (:meth:`sample_histograms`), the
    input of a cluster-bootstrap interval of the AUROC.
    """

    bins: int = 4096
    pos: np.ndarray = field(default=None)  # type: ignore[assignment]  # histogram of u on wrong cells
    neg: np.ndarray = field(default=None)  # type: ignore[assignment]  # histogram of u on right cells
    keep_samples: bool = False
    _samples: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list, repr=False)

    def __post_init__(self) -> None:
        if self.bins < 2:
            raise ValueError(f"UncertaintyAUROC.bins must be >= 2, got {self.bins}")
        self.pos = np.zeros(self.bins, np.int64) if self.pos is None else self.pos
        self.neg = np.zeros(self.bins, np.int64) if self.neg is None else self.neg

    def update(self, label: np.ndarray, pred: np.ndarray) -> None:
        """Add a batch of maps (label and prediction masses)."""
        pos, neg = u_error_histograms(label, pred, self.bins)
        self.pos += pos.sum(axis=0)
        self.neg += neg.sum(axis=0)
        if self.keep_samples:
            self._samples.append((pos, neg))

    def sample_histograms(self) -> tuple[np.ndarray, np.ndarray]:
        """``(pos, neg)`` per sample ``(N, bins)`` in update order (needs ``keep_samples``)."""
        if not self.keep_samples:
            raise ValueError("UncertaintyAUROC: per-sample histograms need keep_samples=True")
        if not self._samples:
            z = np.zeros((0, self.bins), np.int64)
            return z, z.copy()
        return (
            np.concatenate([p for p, _ in self._samples]),
            np.concatenate([n for _, n in self._samples]),
        )

    @property
    def n_wrong(self) -> int:
        return int(self.pos.sum())

    @property
    def n_right(self) -> int:
        return int(self.neg.sum())

    def value(self) -> float:
        """AUROC (NaN when there is no wrong or no right cell)."""
        return auroc_from_hist(self.pos, self.neg)


def _finite(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    return a[np.isfinite(a)]


def aggregate(samples: Mapping[str, Sequence[float] | np.ndarray]) -> dict[str, float]:
    """Pool per-sample metrics (columns as produced by :func:`per_sample_metrics`) into one dict.

    KLDs: mean, median, 25/75 % quantiles over samples; P/R/Dice: from pooled counts (micro
    average) plus ``dice_<c>_sample_mean``; ``u_mean``: mean over samples; ``n``: sample count.
    """
    n = len(np.asarray(samples["kld_fo"]))
    out: dict[str, float] = {"n": float(n)}
    if n == 0:
        return out
    for k in ("kld_fo", "kld_fou"):
        v = _finite(samples[k])
        out[f"{k}_mean"] = float(v.mean()) if v.size else float("nan")
        out[f"{k}_median"] = float(np.median(v)) if v.size else float("nan")
        out[f"{k}_q25"] = float(np.quantile(v, 0.25)) if v.size else float("nan")
        out[f"{k}_q75"] = float(np.quantile(v, 0.75)) if v.size else float("nan")
    for c in CLASSES:
        tp, fp, fn = (float(np.sum(samples[f"{k}_{c}"])) for k in ("tp", "fp", "fn"))
        pr, rc, dc = prf(tp, fp, fn)
        out[f"precision_{c}"], out[f"recall_{c}"], out[f"dice_{c}"] = (
            float(pr),
            float(rc),
            float(dc),
        )
        d = _finite(samples[f"dice_{c}"])
        out[f"dice_{c}_sample_mean"] = float(d.mean()) if d.size else float("nan")
    for k in ("u_mean", "u_mean_known"):
        if k in samples:
            v = _finite(samples[k])
            out[k] = float(v.mean()) if v.size else float("nan")
    return out


def pose_error_bins(
    noise: np.ndarray, trans_edges_m: Iterable[float], rot_edges_deg: Iterable[float]
) -> tuple[np.ndarray, np.ndarray, list[str], list[str]]:
    """Bin samples by the pose error drawn: ``noise`` (N, 3) = (dx m, dy m, dyaw rad).

    Translation error = ``hypot(dx, dy)`` (m), rotation error = ``|dyaw|`` (deg). Edges are
    increasing; the last bin is open (``≥ last edge``). Returns ``(trans_bin, rot_bin)`` indices
    ``(N,)`` and the bin labels (e.g. ``"0-0.5m"``, ``">=5m"``).
    """
    noise = np.asarray(noise, dtype=np.float64).reshape(-1, 3)
    te = np.asarray(list(trans_edges_m), dtype=np.float64)
    re = np.asarray(list(rot_edges_deg), dtype=np.float64)
    for name, e in (("trans_edges_m", te), ("rot_edges_deg", re)):
        if e.size < 1 or e[0] != 0 or np.any(np.diff(e) <= 0):
            raise ValueError(
                f"pose_error_bins: {name} must start at 0 and increase strictly, got {e.tolist()}"
            )
    t = np.hypot(noise[:, 0], noise[:, 1])
    r = np.degrees(np.abs(noise[:, 2]))
    tb = np.searchsorted(te, t, side="right") - 1
    rb = np.searchsorted(re, r, side="right") - 1

    def labels(e: np.ndarray, unit: str) -> list[str]:
        out = [f"{e[i]:g}-{e[i + 1]:g}{unit}" for i in range(len(e) - 1)]
        return out + [f">={e[-1]:g}{unit}"]

    return tb, rb, labels(te, "m"), labels(re, "deg")
