"""Geometric evidential inverse sensor model: lidar scan -> masses ``(m_F, m_O)`` on a grid.

Per azimuth column of the scan (all 32 channels of one firing direction):

* ``d_obs`` = horizontal distance of the nearest *obstacle* return (a box hit);
* the free range is ``d_obs`` where the column has an obstacle return, else the horizontal
  distance of its farthest *ground* return (0 without any return);
* cells whose centre lies in that column's azimuth bin and closer than ``free range − margin``
  get free evidence ``p_free`` (a beam passed through them before its first obstacle);
* every cell with ``n`` ground returns gets free evidence ``1 − (1 − p_ground)^n`` (returns
  beyond an obstacle's free range included: the ground there was seen);
* every cell with ``n`` obstacle returns gets occupied evidence ``1 − (1 − p_occ)^n``;
* the free and the occupied evidence of a cell are combined with Dempster's rule; cells
  without any evidence stay unknown ``(0, 0)``. Masses are capped at ``mass_cap``.

Returns are classified by what the ray hit (box vs ground plane), the ground truth of the
simulation; beams without a return within range give no evidence. Everything is array
operations (per-column reductions, ``np.bincount``), no per-cell loops.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from traffictwin.grid import GridSpec
from traffictwin.scan import HIT_GROUND, Scan


@dataclass(frozen=True)
class IsmParams:
    """``p_free`` (free mass of a beam-crossed cell), ``p_ground`` / ``p_occ`` (mass per ground /
    obstacle return in a cell), ``margin`` (m kept before an obstacle), ``mass_cap`` (max mass)."""

    p_free: float = 0.6
    p_ground: float = 0.5
    p_occ: float = 0.6
    margin: float = 0.3
    mass_cap: float = 0.98

    def __post_init__(self) -> None:
        for name in ("p_free", "p_ground", "p_occ", "mass_cap"):
            v = getattr(self, name)
            if not 0.0 <= v < 1.0:
                raise ValueError(f"IsmParams.{name} must be in [0, 1), got {v}")
        if self.margin < 0:
            raise ValueError(f"IsmParams.margin must be >= 0 m, got {self.margin}")


@lru_cache(maxsize=8)
def _polar(rows: int, cols: int, cell: float, n_az: int) -> tuple[np.ndarray, np.ndarray]:
    """Range (m) and azimuth column index of every cell centre (sensor at the grid centre)."""
    x, y = GridSpec(rows, cols, cell).cell_centers()
    rho = np.hypot(x, y)
    az = np.arctan2(y, x)
    col = np.floor((az + np.pi) / (2 * np.pi) * n_az).astype(np.int64) % n_az
    return rho, col


def _counts(grid: GridSpec, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Number of points per cell, shape (rows, cols)."""
    r, c = grid.xy_to_rc(x, y)
    r, c = np.rint(r).astype(np.int64), np.rint(c).astype(np.int64)
    ok = (r >= 0) & (r < grid.rows) & (c >= 0) & (c < grid.cols)
    flat = r[ok] * grid.cols + c[ok]
    return np.bincount(flat, minlength=grid.rows * grid.cols).reshape(grid.rows, grid.cols)


def free_ranges(scan: Scan) -> np.ndarray:
    """Free range (m, horizontal) per azimuth column, shape (n_azimuth,)."""
    d = scan.horizontal
    obstacle = scan.hit >= 0
    ground = scan.hit == HIT_GROUND
    d_obs = np.where(obstacle, d, np.inf).min(1)
    d_gnd = np.where(ground, d, 0.0).max(1)
    return np.where(np.isfinite(d_obs), d_obs, d_gnd)


def inverse_sensor_model(scan: Scan, grid: GridSpec, params: IsmParams = IsmParams()) -> np.ndarray:
    """Evidential grid ``(2, rows, cols)`` float32 (m_F, m_O) in the scan's sensor frame."""
    n_az = scan.range.shape[0]
    rho, col = _polar(grid.rows, grid.cols, grid.cell, n_az)
    fr = free_ranges(scan)
    beam_free = rho < (fr[col] - params.margin)
    pts = scan.points
    ground = scan.hit == HIT_GROUND
    obstacle = scan.hit >= 0
    n_g = _counts(grid, pts[..., 0][ground], pts[..., 1][ground])
    n_o = _counts(grid, pts[..., 0][obstacle], pts[..., 1][obstacle])
    m_free = 1.0 - (1.0 - params.p_free * beam_free) * (1.0 - params.p_ground) ** n_g
    m_occ = 1.0 - (1.0 - params.p_occ) ** n_o
    m_free = np.minimum(m_free, params.mass_cap)
    m_occ = np.minimum(m_occ, params.mass_cap)
    # Dempster of (m_free, 0) and (0, m_occ): K = m_free * m_occ < 1 because both are capped
    den = 1.0 - m_free * m_occ
    out = np.stack([m_free * (1.0 - m_occ) / den, m_occ * (1.0 - m_free) / den])
    return out.astype(np.float32)
