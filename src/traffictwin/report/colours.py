"""The one colour map of evidential masses, shared by every figure and preview that shows a map.

free = green, occupied = red, unknown = grey, mixed by mass:
``RGB = m_F * FREE + m_O * OCC + u * UNKNOWN`` (``u = 1 - m_F - m_O`` unless given). A pure
free cell is green, a pure occupied cell red, an unobserved cell grey; a cell split between
free and occupied is olive. :func:`legend_handles` gives the matching legend entries.
"""

from __future__ import annotations

import numpy as np

FREE = np.array([0.15, 0.75, 0.2])
OCC = np.array([0.85, 0.1, 0.1])
UNKNOWN = np.array([0.5, 0.5, 0.5])
LEGEND = (("free (m_F = 1)", FREE), ("occupied (m_O = 1)", OCC), ("unknown (u = 1)", UNKNOWN))


def masses_to_rgb(m: np.ndarray, u: np.ndarray | None = None) -> np.ndarray:
    """``(2, H, W)`` masses ``(m_F, m_O)`` (and optionally ``u`` ``(H, W)``) -> ``(H, W, 3)`` float
    RGB in [0, 1]."""
    m = np.asarray(m, np.float64)
    if m.ndim != 3 or m.shape[0] != 2:
        raise ValueError(f"masses_to_rgb: expected masses of shape (2, H, W), got {m.shape}")
    u = 1.0 - m[0] - m[1] if u is None else np.asarray(u, np.float64)
    rgb = m[0][..., None] * FREE + m[1][..., None] * OCC + u[..., None] * UNKNOWN
    return np.clip(rgb, 0.0, 1.0)


def masses_to_bgr8(m: np.ndarray, u: np.ndarray | None = None) -> np.ndarray:
    """:func:`masses_to_rgb` as an OpenCV BGR uint8 image ``(H, W, 3)``."""
    return np.clip(masses_to_rgb(m, u)[..., ::-1] * 255.0 + 0.5, 0, 255).astype(np.uint8)


def legend_handles() -> list:
    """Matplotlib patches for free / occupied / unknown in this colour map (``ax.legend(handles=...)``)."""
    from matplotlib.patches import Patch

    return [Patch(color=c, label=label) for label, c in LEGEND]
