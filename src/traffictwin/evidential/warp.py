"""SE(2) warping of evidential grid maps (prealignment, labels) with OpenCV.

``warp_masses(m, rel_pose, grid)`` resamples map 2 (in its own sensor frame) into map 1's
frame, given the pose ``(x, y, yaw)`` (m, rad) of map 2's sensor in map 1's frame. For every
cell of the output the source position in map 2 is ``R(yaw)^T (p1 − t)``; masses are
interpolated bilinearly (``cv2.warpAffine`` with ``WARP_INVERSE_MAP``), cells whose source lies
outside map 2 are unknown (border value 0 → ``(m_F, m_O) = (0, 0)``). Bilinear interpolation
is a convex combination of masses on the simplex (unknown included), so the output stays on it;
rounding is cleaned by clipping to [0, 1] and renormalising cells with ``m_F + m_O > 1``.
"""

from __future__ import annotations

import cv2
import numpy as np

from traffictwin.evidential.masses import clean_masses
from traffictwin.geometry import se2_matrix
from traffictwin.grid import GridSpec


def pixel_from_metric(grid: GridSpec) -> np.ndarray:
    """3x3 matrix: sensor-frame (x, y, 1) in m -> OpenCV pixel (col, row, 1)."""
    return np.array(
        [
            [0.0, -1.0 / grid.cell, grid.cols / 2 - 0.5],
            [-1.0 / grid.cell, 0.0, grid.rows / 2 - 0.5],
            [0.0, 0.0, 1.0],
        ]
    )


def warp_matrix(rel_pose: np.ndarray, grid: GridSpec) -> np.ndarray:
    """2x3 affine map: output pixel (col, row) of map 1 -> source pixel of map 2."""
    P = pixel_from_metric(grid)
    T = se2_matrix(*np.asarray(rel_pose, dtype=np.float64).reshape(3))
    M = P @ np.linalg.inv(T) @ np.linalg.inv(P)
    return M[:2]


def warp_masses(
    m: np.ndarray, rel_pose: np.ndarray, grid: GridSpec, interpolation: int = cv2.INTER_LINEAR
) -> np.ndarray:
    """Warp mass grid ``m (2, H, W)`` (map 2's frame) into map 1's frame; see module docstring."""
    m = np.asarray(m)
    if m.shape != (2, grid.rows, grid.cols):
        raise ValueError(
            f"warp_masses: expected masses of shape (2, {grid.rows}, {grid.cols}), got {m.shape}"
        )
    rel_pose = np.asarray(rel_pose, dtype=np.float64).reshape(-1)
    if rel_pose.shape != (3,) or not np.all(np.isfinite(rel_pose)):
        raise ValueError(
            f"warp_masses: rel_pose must be finite (x m, y m, yaw rad), got {rel_pose}"
        )
    src = np.ascontiguousarray(np.moveaxis(m.astype(np.float32, copy=False), 0, -1))
    out = cv2.warpAffine(
        src,
        warp_matrix(rel_pose, grid),
        (grid.cols, grid.rows),
        flags=interpolation | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=(0.0, 0.0, 0.0, 0.0),
    )
    # float rounding only; on a contiguous copy (twice as fast as on the strided transpose)
    return clean_masses(np.ascontiguousarray(out.transpose(2, 0, 1)))
