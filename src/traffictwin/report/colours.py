"""The one colour map of evidential masses, shared by every figure and preview that shows a map:
``RGB = m_F * FREE + m_O * OCC + u * UNKNOWN`` (``u = 1 - m_F - m_O`` unless given), so free is
green, occupied red, unknown grey and a cell split between free and occupied olive.
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


def legend_strip_bgr8(width: int, height: int = 22) -> np.ndarray:
    """A white BGR uint8 strip ``(height, width, 3)`` with the legend of this colour map (a swatch
    and its label per entry, OpenCV text), for images drawn without matplotlib (CLI previews)."""
    import cv2

    strip = np.full((height, width, 3), 255, np.uint8)
    x, pad, font = 4, max(2, height // 5), cv2.FONT_HERSHEY_SIMPLEX
    for label, colour in LEGEND:
        bgr = tuple(int(v) for v in np.round(colour[::-1] * 255))
        cv2.rectangle(strip, (x, pad), (x + height - 2 * pad, height - pad), bgr, thickness=-1)
        x += height - 2 * pad + 4
        cv2.putText(strip, label, (x, height - pad - 1), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
        x += cv2.getTextSize(label, font, 0.4, 1)[0][0] + 12
    return strip


def legend_handles() -> list:
    """Matplotlib patches for free / occupied / unknown in this colour map (``ax.legend(handles=...)``)."""
    from matplotlib.patches import Patch

    return [Patch(color=c, label=label) for label, c in LEGEND]


def map_extent(rows: int, cols: int, cell: float) -> tuple[float, float, float, float]:
    """``imshow`` extent (m) of a ``rows x cols`` grid of ``cell`` m with the sensor at the centre:
    x (forward) up, y (left) to the left, as in :mod:`traffictwin.grid` (row 0 front, col 0 left)."""
    length, width = rows * cell, cols * cell
    return (width / 2, -width / 2, -length / 2, length / 2)


def show_masses(ax, m: np.ndarray, cell: float, u: np.ndarray | None = None, title: str = ""):
    """Draw masses ``(2, H, W)`` on ``ax`` in this colour map, axes in metres (``cell`` m per cell):
    x forward (up), y left (+ to the left). Returns the ``AxesImage``."""
    rows, cols = np.shape(m)[-2:]
    img = ax.imshow(
        masses_to_rgb(m, u),
        extent=map_extent(rows, cols, cell),
        origin="upper",
        interpolation="nearest",
    )
    ax.set_xlabel("y (m, + = left)")
    ax.set_ylabel("x (m, forward)")
    if title:
        ax.set_title(title)
    return img
