"""Dempster's rule of combination and the pignistic transform on Θ = {F, O} (paper eq. 1, 2).

Masses are arrays with the channel axis at ``-3`` (``(2, H, W)`` or batched ``(N, 2, H, W)``):
channel 0 = ``m_F``, 1 = ``m_O``; the mass of Θ (unknown) is ``u = 1 − m_F − m_O``. NumPy
arrays and torch tensors are both accepted (the result has the input's type and dtype).

Dempster::

    K   = m_F1·m_O2 + m_O1·m_F2                         (conflict)
    n_F = m_F1·m_F2 + m_F1·u2 + u1·m_F2,   n_O = m_O1·m_O2 + m_O1·u2 + u1·m_O2,   n_Θ = u1·u2
    m_F = n_F / (1 − K),   m_O = n_O / (1 − K)

**Numerically stable denominator.** ``1 − K`` equals ``n_F + n_O + n_Θ`` (the unnormalised
product's masses sum to ``1 − K``); this implementation divides by that sum of non-negative terms,
which keeps its relative precision as ``K → 1``, where ``1 − K`` cancels in float32 (e.g.
``(1 − 1e-4, 0) ⊕ (0, 1 − 1e-4)``: ``1 − K`` = 2e-4 from two numbers near 1).

**Total conflict** (``n_F + n_O + n_Θ < eps``, e.g. ``(1, 0) ⊕ (0, 1)``): the rule is undefined; this
implementation returns the *vacuous* mass ``(0, 0)`` (``u = 1``, "nothing is known") for those
cells — the same answer as Yager's rule in :mod:`traffictwin.evidential.rules` at ``K = 1``.

Pignistic: ``p_O = m_O + u / 2``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from traffictwin.evidential.masses import clean_masses

EPS = 1e-7


def _is_torch(x: Any) -> bool:
    return type(x).__module__.startswith("torch")


def _check_pair(m1: Any, m2: Any) -> None:
    for name, m in (("m1", m1), ("m2", m2)):
        if m.ndim < 3 or m.shape[-3] != 2:
            raise ValueError(
                f"dempster: {name} must have the channel axis of size 2 at -3 ((2,H,W) or (N,2,H,W)), got shape {tuple(m.shape)}"
            )
    if tuple(m1.shape[-2:]) != tuple(m2.shape[-2:]):
        raise ValueError(
            f"dempster: grid shapes differ: m1 {tuple(m1.shape)} vs m2 {tuple(m2.shape)}"
        )


def dempster(m1: Any, m2: Any, eps: float = EPS) -> Any:
    """Dempster's combination of two mass grids (see module docstring; broadcasting over leading axes)."""
    torch_in = _is_torch(m1) or _is_torch(m2)
    if not torch_in:
        m1, m2 = np.asarray(m1), np.asarray(m2)
    _check_pair(m1, m2)
    f1, o1 = m1[..., 0, :, :], m1[..., 1, :, :]
    f2, o2 = m2[..., 0, :, :], m2[..., 1, :, :]
    u1, u2 = 1 - f1 - o1, 1 - f2 - o2
    num_f = f1 * f2 + f1 * u2 + u1 * f2
    num_o = o1 * o2 + o1 * u2 + u1 * o2
    den = num_f + num_o + u1 * u2  # = 1 - K without the cancellation of 1 - K near K = 1
    if torch_in:
        import torch

        ok = den > eps
        safe = torch.where(ok, den, torch.ones_like(den))
        mf = torch.where(ok, num_f / safe, torch.zeros_like(den))
        mo = torch.where(ok, num_o / safe, torch.zeros_like(den))
        return clean_masses(torch.stack([mf, mo], dim=-3))
    ok = den > eps
    safe = np.where(ok, den, 1)
    mf = np.where(ok, num_f / safe, 0)
    mo = np.where(ok, num_o / safe, 0)
    dtype = np.result_type(m1.dtype, m2.dtype)
    return clean_masses(np.stack([mf, mo], axis=-3).astype(dtype, copy=False))


def conflict(m1: Any, m2: Any) -> Any:
    """Conflict ``K = m_F1·m_O2 + m_O1·m_F2`` per cell, shape ``(..., H, W)``."""
    return m1[..., 0, :, :] * m2[..., 1, :, :] + m1[..., 1, :, :] * m2[..., 0, :, :]


def pignistic(m: Any) -> Any:
    """Pignistic occupancy probability ``p_O = m_O + (1 − m_F − m_O) / 2``, shape ``(..., H, W)``."""
    if not _is_torch(m):
        m = np.asarray(m)
    if m.ndim < 3 or m.shape[-3] != 2:
        raise ValueError(
            f"pignistic: masses must have the channel axis of size 2 at -3, got shape {tuple(m.shape)}"
        )
    return m[..., 1, :, :] + (1 - m[..., 0, :, :] - m[..., 1, :, :]) / 2


def vacuous(shape: tuple[int, int], dtype: Any = np.float32) -> np.ndarray:
    """The all-unknown mass grid ``(2, H, W)`` of zeros."""
    return np.zeros((2, *shape), dtype=dtype)
