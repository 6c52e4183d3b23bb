"""Evidential output, loss and fusion metrics in torch (paper III-A, docs/design.md "Evidential output").

Evidence -> masses (eqs. 3-5): ``alpha = e + 1``, ``S = sum(alpha)``, ``m = e / S``, ``u = K / S``
with ``K = 2`` classes (free, occupied); ``m_F + m_O + u = 1``. Channel axis is ``-3``
(arrays ``(..., 2, H, W)``), channel 0 = free, 1 = occupied.

Loss (eqs. 6-7), per cell ``i`` with label masses ``y`` and ``p = alpha / S``::

    L_i = w_i * sum_A [ (y_A - p_A)^2 + p_A (1 - p_A) / (S + 1) ],   w_i = o_w if y_O > 0.5 else 1

averaged over cells. The KL regulariser of Sensoy et al. (2018), ``KL(Dir(alpha~) || Dir(1))``
with ``alpha~ = y + (1 - y) alpha``, is available (``kl_weight > 0``) but off by default, as in
the paper.

Losses by name (registered in :mod:`traffictwin.fusion.loss_registry`, :data:`LOSSES`,
``fusion_model.loss.name``; :func:`fusion_loss` runs one by name):

- ``mass`` (default): the KL divergence from the label's full mass vector ``(y_F, y_O, y_u)`` to
  the predicted ``(m_F, m_O, u)``, ``L_i = w_i * sum_k y_k (log y_k - log m_k)`` (``y`` clipped to
  [1e-7, 1] as in the metric, ``log m`` from a log-softmax of ``(log e_F, log e_O, log 2)``, so
  it is exact for any evidence). A proper scoring rule for the mass vector: the expected loss is
  smallest at the label's conditional mean, so the total evidence cannot run away (eq. 7's
  failure: as ``S`` grows it only asks for the pignistic probability, so ``u -> 0`` is rewarded).
- ``paper``: eq. 7 exactly (no KL term).
- ``paper_kl``: eq. 7 + ``kl_weight * min(1, epoch / kl_anneal_epochs)`` x the KL regulariser
  (evidential deep learning's annealed recipe, as in EviLOG).

Metrics (docs/design.md "Fusion metrics"; the numpy evaluation implements the same formulas):
``kld`` = KL(label || pred) over ``(m_F, m_O)`` with both clipped to [1e-7, 1], summed over the
two entries and averaged over cells; ``kld_full`` = the same over ``(m_F, m_O, u)``; a cell is
predicted occupied where ``p_O = m_O + u/2 > 0.5``, free where ``p_O < 0.5``; Dice per class over
the cells whose label is known (label ``m_O > 0.5`` -> occupied, label ``m_F > 0.5`` -> free).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import torch
from torchmetrics import Metric

from traffictwin.evidential.masses import (  # noqa: F401 - re-exported (its home is evidential)
    NUM_CLASSES,
    evidence_to_masses,
)
from traffictwin.fusion.loss_registry import LOSSES, MassLoss, PaperKLLoss, PaperLoss

KLD_EPS = 1e-7


def dirichlet_params(e: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``alpha = e + 1`` ``(..., 2, H, W)``, strength ``S (..., 1, H, W)``, expected probability ``p = alpha / S``."""
    alpha = e + 1.0
    s = alpha.sum(dim=-3, keepdim=True)
    return alpha, s, alpha / s


def kl_dirichlet_uniform(alpha: torch.Tensor) -> torch.Tensor:
    """``KL(Dir(alpha) || Dir(1, ..., 1))`` per cell, over the class axis -3 -> ``(..., H, W)``."""
    k = alpha.shape[-3]
    s = alpha.sum(dim=-3)
    return (
        torch.lgamma(s)
        - torch.lgamma(torch.tensor(float(k), dtype=alpha.dtype, device=alpha.device))
        - torch.lgamma(alpha).sum(dim=-3)
        + ((alpha - 1.0) * (torch.digamma(alpha) - torch.digamma(s).unsqueeze(-3))).sum(dim=-3)
    )


def evidential_loss_map(
    e: torch.Tensor, y: torch.Tensor, occupied_weight: float = 3.0, kl_weight: float = 0.0
) -> torch.Tensor:
    """Per-cell loss ``(..., H, W)`` of eqs. (6)-(7) (+ ``kl_weight`` x the KL regulariser).

    ``e``: evidences ``(..., 2, H, W)``; ``y``: label masses ``(..., 2, H, W)`` (free, occupied).
    """
    if e.shape != y.shape:
        raise ValueError(f"evidence shape {tuple(e.shape)} != label shape {tuple(y.shape)}")
    alpha, s, p = dirichlet_params(e)
    per = ((y - p) ** 2 + p * (1.0 - p) / (s + 1.0)).sum(dim=-3)
    loss = _occupied_weighted(per, y, occupied_weight)
    if kl_weight > 0:
        alpha_t = y + (1.0 - y) * alpha
        loss = loss + kl_weight * kl_dirichlet_uniform(alpha_t)
    return loss


def evidential_loss(
    e: torch.Tensor, y: torch.Tensor, occupied_weight: float = 3.0, kl_weight: float = 0.0
) -> torch.Tensor:
    """Mean over cells (and batch) of :func:`evidential_loss_map`."""
    return evidential_loss_map(e, y, occupied_weight, kl_weight).mean()


def log_masses(e: torch.Tensor) -> torch.Tensor:
    """``log (m_F, m_O, u)`` ``(..., 3, H, W)`` of evidences ``e >= 0`` ``(..., 2, H, W)``, stable for any ``e``.

    ``m_k = e_k / (e_F + e_O + 2)``, ``u = 2 / (...)`` = softmax of ``(log e_F, log e_O, log 2)``;
    ``e = 0`` gives ``log m = log(1e-30)`` (finite).
    """
    log_e = torch.log(e.clamp_min(1e-30))
    two = torch.full_like(log_e[..., :1, :, :], math.log(NUM_CLASSES))
    return torch.log_softmax(torch.cat([log_e, two], dim=-3), dim=-3)


def mass_loss_map(
    e: torch.Tensor, y: torch.Tensor, occupied_weight: float = 1.0, eps: float = KLD_EPS
) -> torch.Tensor:
    """Per-cell ``w_i * KL(y || m)`` over the full mass vector ``(F, O, u)`` -> ``(..., H, W)``.

    ``e``: evidences ``(..., 2, H, W)``; ``y``: label masses ``(..., 2, H, W)``; ``w_i = o_w`` where
    ``y_O > 0.5`` else 1. The label is clipped to [eps, 1] (as KLD(b)); the prediction is exact.
    """
    if e.shape != y.shape:
        raise ValueError(f"evidence shape {tuple(e.shape)} != label shape {tuple(y.shape)}")
    yf = with_uncertainty(y).clamp(eps, 1.0)
    per = (yf * (torch.log(yf) - log_masses(e))).sum(dim=-3)
    return _occupied_weighted(per, y, occupied_weight)


def _occupied_weighted(per: torch.Tensor, y: torch.Tensor, occupied_weight: float) -> torch.Tensor:
    if occupied_weight == 1.0:
        return per
    w = torch.where(
        y[..., 1, :, :] > 0.5,
        torch.as_tensor(float(occupied_weight), dtype=per.dtype, device=per.device),
        torch.ones((), dtype=per.dtype, device=per.device),
    )
    return w * per


def mass_loss(
    e: torch.Tensor, y: torch.Tensor, s: MassLoss, epoch: int | None = None
) -> torch.Tensor:
    """Loss ``mass``: mean of :func:`mass_loss_map` with o_w ``s.occupied_weight``."""
    return mass_loss_map(e, y, s.occupied_weight).mean()


def paper_loss(
    e: torch.Tensor, y: torch.Tensor, s: PaperLoss, epoch: int | None = None
) -> torch.Tensor:
    """Loss ``paper``: eq. 7 (:func:`evidential_loss` without the KL term)."""
    return evidential_loss(e, y, s.occupied_weight, 0.0)


def paper_kl_loss(
    e: torch.Tensor, y: torch.Tensor, s: PaperKLLoss, epoch: int | None = None
) -> torch.Tensor:
    """Loss ``paper_kl``: eq. 7 + ``kl_weight * min(1, epoch / kl_anneal_epochs)`` x the KL
    regulariser; ``epoch`` None (the validation loss): eq. 7 alone."""
    w = 0.0
    if epoch is not None and s.kl_weight > 0:
        w = s.kl_weight * min(1.0, epoch / max(1, s.kl_anneal_epochs))
    return evidential_loss(e, y, s.occupied_weight, w)


def fusion_loss(
    name: str, e: torch.Tensor, y: torch.Tensor, settings: Any, epoch: int | None = None
) -> torch.Tensor:
    """Mean over cells and batch of registered loss ``name`` (:data:`LOSSES`) with ``settings``
    (its settings dataclass, or a mapping of its fields) at training ``epoch`` (0-based; None:
    the validation loss, without regularisers)."""
    if name not in LOSSES:
        raise ValueError(f"unknown fusion loss {name!r}; expected one of {list(LOSSES)}")
    loss = LOSSES[name]
    if isinstance(settings, Mapping):
        settings = loss.settings(**settings)
    return loss.function()(e, y, settings, epoch)


# ---------------------------------------------------------------------------------------------
# metrics (torch; per-sample values so that an epoch mean weights every pair equally)


def kld(pred_m: torch.Tensor, label_m: torch.Tensor, eps: float = KLD_EPS) -> torch.Tensor:
    """KL(label || pred) on ``(m_F, m_O)`` clipped to [eps, 1], mean over cells -> ``(...)`` per map."""
    y = label_m.clamp(eps, 1.0)
    p = pred_m.clamp(eps, 1.0)
    return (y * torch.log(y / p)).sum(dim=-3).mean(dim=(-2, -1))


def with_uncertainty(m: torch.Tensor) -> torch.Tensor:
    """``(..., 2, H, W)`` masses -> ``(..., 3, H, W)`` = ``(m_F, m_O, u = clip(1 - m_F - m_O, 0, 1))``."""
    return torch.cat([m, (1.0 - m.sum(dim=-3, keepdim=True)).clamp(0.0, 1.0)], dim=-3)


def kld_full(pred_m: torch.Tensor, label_m: torch.Tensor, eps: float = KLD_EPS) -> torch.Tensor:
    """KL(label || pred) over the full ``(m_F, m_O, u)`` vector, clipped to [eps, 1], mean over cells."""
    return kld(with_uncertainty(pred_m), with_uncertainty(label_m), eps)


def pignistic_occupied(m: torch.Tensor) -> torch.Tensor:
    """``p_O = m_O + u / 2`` ``(..., H, W)``."""
    u = (1.0 - m.sum(dim=-3)).clamp(0.0, 1.0)
    return m[..., 1, :, :] + 0.5 * u


def confusion_counts(pred_m: torch.Tensor, label_m: torch.Tensor) -> torch.Tensor:
    """Counts over known label cells: ``[tp_occ, fp_occ, fn_occ, tp_free, fp_free, fn_free]`` (float64, summed).

    Predicted occupied ⇔ ``p_O > 0.5``, free ⇔ ``p_O < 0.5``; label occupied ⇔ ``y_O > 0.5``,
    free ⇔ ``y_F > 0.5``; cells with neither label are ignored.
    """
    p_o = pignistic_occupied(pred_m)
    lab_occ = label_m[..., 1, :, :] > 0.5
    lab_free = label_m[..., 0, :, :] > 0.5
    pred_occ = p_o > 0.5
    pred_free = p_o < 0.5
    out = torch.stack(
        [
            (pred_occ & lab_occ).sum(),
            (pred_occ & lab_free).sum(),
            (~pred_occ & lab_occ).sum(),
            (pred_free & lab_free).sum(),
            (pred_free & lab_occ).sum(),
            (~pred_free & lab_free).sum(),
        ]
    )
    return out.to(torch.float64)


def dice_from_counts(counts: torch.Tensor) -> dict[str, float]:
    """Precision, recall, Dice for occupied and free from :func:`confusion_counts` (NaN when undefined)."""
    c = counts.tolist()
    out: dict[str, float] = {}
    for name, (tp, fp, fn) in (("occ", c[0:3]), ("free", c[3:6])):
        out[f"precision_{name}"] = tp / (tp + fp) if tp + fp > 0 else float("nan")
        out[f"recall_{name}"] = tp / (tp + fn) if tp + fn > 0 else float("nan")
        out[f"dice_{name}"] = 2 * tp / (2 * tp + fp + fn) if 2 * tp + fp + fn > 0 else float("nan")
    return out


class ConfusionCounts(Metric):
    """:func:`confusion_counts` summed over batches (and DDP ranks); ``compute`` -> the 6 counts (float64)."""

    full_state_update = False

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.add_state("counts", default=torch.zeros(6, dtype=torch.float64), dist_reduce_fx="sum")

    def update(self, pred_m: torch.Tensor, label_m: torch.Tensor) -> None:
        self.counts += confusion_counts(pred_m, label_m).to(self.counts.device)

    def compute(self) -> torch.Tensor:
        return self.counts
