"""Alternative combination rules on Θ = {F, O}: Yager's rule and Denœux's normalised cautious rule.

Masses are arrays with the channel axis at ``-3`` (``(2, H, W)`` or batched ``(N, 2, H, W)``),
channel 0 = ``m_F``, 1 = ``m_O``, ``u = 1 − m_F − m_O`` (the mass of Θ), the same layout as
:mod:`traffictwin.evidential.dempster`. Every function is vectorised over cells and batches.

**Yager** (1987). The unnormalised conjunctive combination, with the conflict
``K = m_F1·m_O2 + m_O1·m_F2`` moved to Θ instead of being normalised away::

    m_F = m_F1·m_F2 + m_F1·u2 + u1·m_F2
    m_O = m_O1·m_O2 + m_O1·u2 + u1·m_O2
    u   = u1·u2 + K

Total conflict (``K = 1``) therefore gives the vacuous mass ``(0, 0)`` (fully unknown).

**Normalised cautious rule** (Denœux 2008, "Conjunctive and disjunctive combination of belief
functions induced by nondistinct bodies of evidence", AIJ 172). A non-dogmatic mass function
(``u > 0``) is the Dempster combination of simple mass functions ``A^{w(A)}`` (mass ``1 − w`` on A,
``w`` on Θ), its canonical decomposition; the weights come from the commonalities
``q(A) = Σ_{B ⊇ A} m(B)``: ``w(A) = Π_{B ⊇ A} q(B)^{(−1)^{|B|−|A|+1}}``. On Θ = {F, O}:
``q({F}) = m_F + u``, ``q({O}) = m_O + u``, ``q(Θ) = u``, hence::

    w_F = u / (m_F + u),   w_O = u / (m_O + u)         (both in (0, 1]: always separable)

The normalised cautious rule keeps, per focal set, the *smaller* weight (the more committed
simple component, never counting the same evidence twice) and recombines with Dempster::

    w_F = min(w_F1, w_F2),  w_O = min(w_O1, w_O2)
    F^{w_F} ⊕ O^{w_O}:  m_F = (1 − w_F)·w_O / Z,  m_O = w_F·(1 − w_O) / Z,  u = w_F·w_O / Z,
    Z = 1 − (1 − w_F)(1 − w_O) = w_F + w_O − w_F·w_O.

It is idempotent (``m ⊘ m = m``): with ``w_F = u/(m_F+u)``, ``w_O = u/(m_O+u)`` one gets
``Z = u / ((m_F+u)(m_O+u))`` and the three masses reduce to ``(m_F, m_O, u)``.
Dogmatic inputs (``u = 0``) have no canonical decomposition; they are handled as the limit
``u → 0`` by flooring ``u`` at ``eps`` inside the weights (so ``(1, 0)`` stays ``(1, 0)`` up to
``eps``). Two contradicting dogmatic inputs (``(1, 0)`` with ``(0, 1)``) give ``(½, ½)`` — all
mass on the conflict between the two classes, none on Θ (again a limit, written down and tested).
"""

from __future__ import annotations

import numpy as np

from traffictwin.evidential.masses import check_masses, unknown_mass

__all__ = ["yager", "cautious", "conjunctive_weights"]


def _split(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return m[..., 0, :, :], m[..., 1, :, :], unknown_mass(m)


def yager(m1: np.ndarray, m2: np.ndarray) -> np.ndarray:
    """Yager's rule: conjunctive combination with the conflict assigned to Θ (unknown).

    ``m1``, ``m2``: masses (…, 2, H, W) (broadcastable); returns the same layout, float32.
    """
    m1 = check_masses(m1, "m1")
    m2 = check_masses(m2, "m2")
    f1, o1, u1 = _split(m1)
    f2, o2, u2 = _split(m2)
    mf = f1 * f2 + f1 * u2 + u1 * f2
    mo = o1 * o2 + o1 * u2 + u1 * o2
    out = np.stack([mf, mo], axis=-3)
    return np.clip(out, 0.0, 1.0).astype(np.float32)


def conjunctive_weights(m: np.ndarray, eps: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """Canonical-decomposition weights ``(w_F, w_O)`` of masses ``m`` (…, 2, H, W) on Θ = {F, O}.

    ``w_F = u / (m_F + u)``, ``w_O = u / (m_O + u)`` with ``u`` floored at ``eps`` (dogmatic limit).
    Each weight lies in (0, 1]; 1 means "no evidence for that class".
    """
    m = np.asarray(m, dtype=np.float64)
    f, o, u = _split(m)
    u = np.maximum(u, eps)
    return u / (f + u), u / (o + u)


def cautious(m1: np.ndarray, m2: np.ndarray, eps: float = 1e-9) -> np.ndarray:
    """Denœux's normalised cautious rule (idempotent); see the module docstring for the derivation.

    ``m1``, ``m2``: masses (…, 2, H, W) (broadcastable); ``eps``: floor of ``u`` inside the
    weights (dogmatic inputs). Returns the same layout, float32.
    """
    m1 = check_masses(m1, "m1")
    m2 = check_masses(m2, "m2")
    wf1, wo1 = conjunctive_weights(m1, eps)
    wf2, wo2 = conjunctive_weights(m2, eps)
    wf = np.minimum(wf1, wf2)
    wo = np.minimum(wo1, wo2)
    z = wf + wo - wf * wo  # = 1 − (1 − w_F)(1 − w_O) > 0 since both weights > 0
    mf = (1.0 - wf) * wo / z
    mo = wf * (1.0 - wo) / z
    out = np.stack([mf, mo], axis=-3)
    return np.clip(out, 0.0, 1.0).astype(np.float32)
