"""Evidential mass grids on Θ = {F, O}: the one validator and the one cleaner.

Layout (every module of the project): channel axis ``-3`` of size 2 — ``(2, H, W)`` or batched
``(N, 2, H, W)`` — channel 0 = ``m_F``, 1 = ``m_O``; the mass of Θ (unknown) is
``u = 1 − m_F − m_O``. A valid grid is finite, on the simplex: ``m_F, m_O ≥ 0`` and
``m_F + m_O ≤ 1`` (so ``u ≥ 0``).

- :func:`check_masses` — *validate* input (files, arguments): raises ``ValueError`` naming the
  input and the expected form; never changes values.
- :func:`clean_masses` — *sanitise* a computed result whose only defect is float rounding:
  clip to [0, 1] and renormalise the cells with ``m_F + m_O > 1`` onto the simplex (NumPy or
  torch, dtype kept).
- :func:`unknown_mass` — ``u = clip(1 − m_F − m_O, 0, 1)``.
- :func:`evidence_to_masses` — the evidential network's output ``e ≥ 0`` to masses
  (``α = e + 1``, ``S = Σα``, ``m = e/S``, ``u = 2/S``; docs/design.md "Evidential output").
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = [
    "NUM_CLASSES",
    "TOL",
    "check_masses",
    "clean_masses",
    "evidence_to_masses",
    "unknown_mass",
]

NUM_CLASSES = 2  # free, occupied (the evidential network's output channels)
TOL = 1e-5  # default tolerance of check_masses on the bounds of the simplex


def _is_torch(x: Any) -> bool:
    return type(x).__module__.startswith("torch")


def check_masses(m: Any, name: str = "masses", tol: float = TOL) -> np.ndarray:
    """Return ``m`` as a float NumPy array after checking it is a valid mass grid.

    Expected: channel axis ``-3`` of size 2 (``(2, H, W)`` or ``(N, 2, H, W)``), finite values,
    ``m_F, m_O ≥ 0`` and ``m_F + m_O ≤ 1`` up to ``tol``. Integer input is converted to float32.
    Raises ``ValueError`` naming ``name``, what is wrong (how many cells, where) and the
    expected form.
    """
    m = np.asarray(m)
    if m.ndim < 3 or m.shape[-3] != 2:
        raise ValueError(
            f"{name}: expected masses (m_F, m_O) with a channel axis of size 2 at -3 "
            f"((2,H,W) or (N,2,H,W)), got shape {m.shape}"
        )
    if not np.issubdtype(m.dtype, np.floating):
        m = m.astype(np.float32)
    bad = ~np.isfinite(m)
    if bad.any():
        raise ValueError(
            f"{name}: {int(bad.sum())} NaN/inf value(s) (first at index {tuple(int(i) for i in np.argwhere(bad)[0])}); "
            "expected finite masses (m_F, m_O)"
        )
    total = m[..., 0, :, :] + m[..., 1, :, :]
    neg = (m < -tol).any(axis=-3)
    over = (total > 1 + tol) | (m > 1 + tol).any(axis=-3)
    if neg.any() or over.any():
        raise ValueError(
            f"{name}: masses outside the simplex at {int((neg | over).sum())} cell(s) "
            f"(need m_F, m_O >= 0 and m_F + m_O <= 1 within {tol:g}; "
            f"min mass {float(m.min()):.4g}, max m_F + m_O {float(total.max()):.4g})"
        )
    return m


def clean_masses(m: Any) -> Any:
    """Rounding clean-up of computed masses: clip to [0, 1], then divide every cell with
    ``m_F + m_O > 1`` by that sum. NumPy arrays keep their (float) dtype; torch tensors stay tensors."""
    if _is_torch(m):
        import torch

        m = m.clamp(0.0, 1.0)
        s = m.sum(dim=-3, keepdim=True)
        return torch.where(s > 1, m / s.clamp_min(1.0), m)
    m = np.asarray(m)
    dtype = m.dtype if np.issubdtype(m.dtype, np.floating) else np.dtype(np.float32)
    m = np.clip(m, 0.0, 1.0).astype(dtype, copy=False)  # a new array: divided in place below
    s = m.sum(axis=-3, keepdims=True)
    over = s > 1
    if over.any():  # most maps have no such cell: skip the full-grid pass
        np.divide(m, s, out=m, where=over)
    return m


def unknown_mass(m: np.ndarray) -> np.ndarray:
    """``u = clip(1 − m_F − m_O, 0, 1)`` of masses ``(…, 2, H, W)`` → ``(…, H, W)``."""
    return np.clip(1.0 - m[..., 0, :, :] - m[..., 1, :, :], 0.0, 1.0)


def evidence_to_masses(e: Any) -> tuple[Any, Any]:
    """Evidences ``e >= 0`` ``(..., 2, H, W)`` -> masses ``m (..., 2, H, W)`` and uncertainty ``u (..., H, W)``.

    Works on torch tensors and numpy arrays (returns the same type). ``m + u`` sums to 1 per cell.
    """
    if _is_torch(e):
        if e.shape[-3] != NUM_CLASSES:
            raise ValueError(
                f"evidence must have {NUM_CLASSES} channels on axis -3, got shape {tuple(e.shape)}"
            )
        s = (e + 1.0).sum(dim=-3, keepdim=True)
        return e / s, (NUM_CLASSES / s).squeeze(-3)
    arr = np.asarray(e)
    if arr.ndim < 3 or arr.shape[-3] != NUM_CLASSES:
        raise ValueError(
            f"evidence must have {NUM_CLASSES} channels on axis -3, got shape {arr.shape}"
        )
    if np.any(arr < 0):
        raise ValueError("evidence must be >= 0 (the network ends in a ReLU)")
    s = (arr + 1.0).sum(axis=-3, keepdims=True)
    return arr / s, np.squeeze(NUM_CLASSES / s, axis=-3)
