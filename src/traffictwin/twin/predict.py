"""The predictive hazard measure: time to conflict (TTC) with the motion predicted from consecutive maps.

Beside the time headway (THW: free corridor distance / ego speed, the map frozen in time), the twin
predicts where the occupied cells go:

1. **motion** (:func:`cell_velocities`, cell tracking): the previous map is warped into the
   current ego frame by the ego's known pose change (:func:`traffictwin.evidential.warp.warp_masses`;
   static structure then stays put); the occupied cells (``m_O >= occ_threshold``) of both maps
   form 8-connected components (OpenCV); each current component at most ``max_extent`` m long
   (longer ones — walls, buildings — are static) is matched to the mutually nearest previous one
   of similar area (ratio 0.5-2) within the largest plausible displacement ``max_speed * dt``;
   its velocity is the centroid displacement / ``dt`` (m/s, ego frame, over the ground). Slower
   than ``min_speed``, unmatched or faster than ``max_speed``: static. (Dense optical flow —
   OpenCV Farneback / DIS — was tried first: on blobs of a few cells, such as a pedestrian,
   moving more than their size per frame it under-estimates the motion several-fold.)
2. **time to conflict** (:func:`time_to_conflict`): every occupied cell (the ego's own footprint
   grown by ``self_margin`` ignored) is extrapolated at constant velocity at the times
   ``tau = 0, step_s, ..., horizon_s``; a predicted position in the ego's corridor (lateral
   distance to the path <= lane width / 2 + margin) ahead of the ego's front (gap ``g`` = arc
   length - half the ego's length > 0) is a conflict at ``max(tau, g / v_ego)`` — when the ego,
   driving on at its speed, reaches it (the object entered the corridor by ``tau``). Points
   behind the ego's rear are not extrapolated: a follower's straight line cuts through the
   corridor of a turning ego (a constant false conflict, found in the open sequences' truth). TTC is the
   earliest conflict ``<= horizon_s`` (inf: none; ego speed 0: none). At ``tau = 0`` the
   candidates are the THW's (same corridor, same cells), so TTC <= THW whenever THW <= horizon:
   a static map gives TTC = THW, a cell predicted to enter the corridor ahead gives an earlier TTC.

A map *warns predictively* when TTC < ``warn_s`` (``twin.ttc_warn_s`` + ``twin.reaction_s``). The true counterpart (``ttc_true`` of the
twin data, :func:`box_points`) applies :func:`time_to_conflict` to points on the simulator's boxes
with their true velocities. Units: m, s, m/s. Vectorised NumPy / OpenCV, no per-cell loops.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from traffictwin.evidential.warp import warp_masses
from traffictwin.geometry import relative_pose
from traffictwin.grid import GridSpec
from traffictwin.risk.metric import project_on_path

__all__ = [
    "PredictSettings",
    "MapReading",
    "cell_velocities",
    "time_to_conflict",
    "map_ttc",
    "box_points",
]


@dataclass(frozen=True)
class PredictSettings:
    """Motion and TTC settings: speeds below ``min_speed`` (m/s) are static, above ``max_speed``
    (m/s) not tracked (a wrong match); only components at most ``max_extent`` m long are tracked;
    extrapolation every ``step_s`` s up to ``horizon_s`` s; warning below ``warn_s`` s."""

    min_speed: float = 1.0
    max_speed: float = 15.0
    max_extent: float = 6.0
    step_s: float = 0.1
    horizon_s: float = 2.0
    warn_s: float = field(kw_only=True)

    def __post_init__(self) -> None:
        if not 0 <= self.min_speed < self.max_speed:
            raise ValueError(
                f"need 0 <= min_speed < max_speed (m/s), got {self.min_speed}, {self.max_speed}"
            )
        if self.max_extent <= 0:
            raise ValueError(f"need max_extent > 0 (m), got {self.max_extent}")
        if self.step_s <= 0 or self.horizon_s < 0 or self.warn_s <= 0:
            raise ValueError(
                f"need step_s > 0, horizon_s >= 0, warn_s > 0 (s), got {self.step_s}, "
                f"{self.horizon_s}, {self.warn_s}"
            )


def _components(occ: np.ndarray) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    """8-connected components of a bool map: count (incl. background 0), labels, stats, centroids."""
    return cv2.connectedComponentsWithStats(occ.astype(np.uint8), connectivity=8)


def cell_velocities(
    prev_masses: np.ndarray | None,
    masses: np.ndarray,
    ego_prev: np.ndarray,
    ego_now: np.ndarray,
    dt: float,
    grid: GridSpec,
    occ_threshold: float,
    p: PredictSettings,
) -> np.ndarray:
    """Velocity ``(H, W, 2)`` (vx, vy m/s in the current ego frame, over the ground) of every cell
    of the map ``masses (2, H, W)`` from the previous map ``prev_masses`` (None: zeros) and the
    ego's world poses ``ego_prev``, ``ego_now`` (x m, y m, yaw rad), ``dt`` s apart (module
    docstring, step 1). Zero outside occupied components and for static ones."""
    H, W = grid.shape
    v = np.zeros((H, W, 2), np.float32)
    if prev_masses is None or dt <= 0:
        return v
    occ = np.asarray(masses[1]) >= occ_threshold
    if not occ.any():
        return v
    prev = warp_masses(np.asarray(prev_masses), relative_pose(ego_now, ego_prev), grid)
    occ_prev = prev[1] >= occ_threshold
    if not occ_prev.any():
        return v
    n, labels, st, cen = _components(occ)
    m, _, st_p, cen_p = _components(occ_prev)
    # candidates: objects up to max_extent long (walls and buildings are static structure)
    ext = np.maximum(st[:, cv2.CC_STAT_WIDTH], st[:, cv2.CC_STAT_HEIGHT]) * grid.cell
    ext_p = np.maximum(st_p[:, cv2.CC_STAT_WIDTH], st_p[:, cv2.CC_STAT_HEIGHT]) * grid.cell
    a, a_p = st[:, cv2.CC_STAT_AREA].astype(float), st_p[:, cv2.CC_STAT_AREA].astype(float)
    ok = (ext <= p.max_extent) & (np.arange(n) > 0)
    ok_p = (ext_p <= p.max_extent) & (np.arange(m) > 0)
    # centroid distances (cells), gated by the largest plausible displacement and the area ratio
    d = np.hypot(cen[:, None, 0] - cen_p[None, :, 0], cen[:, None, 1] - cen_p[None, :, 1])
    gate = p.max_speed * dt / grid.cell + 1.0
    ratio = a[:, None] / np.maximum(a_p[None, :], 1.0)
    d = np.where(ok[:, None] & ok_p[None, :] & (ratio >= 0.5) & (ratio <= 2.0), d, np.inf)
    if not np.isfinite(d).any():
        return v
    j = np.argmin(d, axis=1)  # nearest previous component of each current one
    i_back = np.argmin(d, axis=0)  # and the reverse: only mutual nearest pairs are tracked
    idx = np.arange(n)
    matched = np.isfinite(d[idx, j]) & (d[idx, j] <= gate) & (i_back[j] == idx)
    dc, dr = cen[:, 0] - cen_p[j, 0], cen[:, 1] - cen_p[j, 1]  # cells moved (col, row)
    # x = (rows/2 - r - 0.5) cell, y = (cols/2 - c - 0.5) cell: one row down = -cell in x
    vx, vy = -dr * grid.cell / dt, -dc * grid.cell / dt
    speed = np.hypot(vx, vy)
    keep = matched & (speed >= p.min_speed) & (speed <= p.max_speed)
    vx, vy = np.where(keep, vx, 0.0), np.where(keep, vy, 0.0)
    v[..., 0] = vx[labels]
    v[..., 1] = vy[labels]
    v[~occ] = 0.0
    return v


def time_to_conflict(
    xy: np.ndarray,
    vel: np.ndarray,
    path: np.ndarray,
    lane_width: float,
    speed: float,
    subject_length: float,
    p: PredictSettings,
    corridor_margin: float = 0.0,
) -> float:
    """The earliest conflict (s) of points ``xy (M, 2)`` moving at ``vel (M, 2)`` (m, m/s, ego
    frame) with the ego driving along ``path (K, 2)`` at ``speed`` m/s (module docstring, step 2);
    inf when none within ``p.horizon_s``."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    vel = np.asarray(vel, np.float64).reshape(-1, 2)
    if len(xy) == 0 or not speed > 0:
        return float("inf")
    tau = np.arange(0.0, p.horizon_s + 1e-9, p.step_s)
    # a point behind the ego's rear (a vehicle following it) is no forward conflict: extrapolated
    # in a straight line it would cut through the corridor of an ego that turns
    moving = np.any(vel != 0, axis=1) & (xy[:, 0] >= -subject_length / 2)
    # static points need tau = 0 only: their position does not change
    q0 = xy
    q1 = (xy[moving][None] + tau[1:, None, None] * vel[moving][None]).reshape(-1, 2)
    t1 = np.repeat(tau[1:], int(moving.sum()))
    q = np.concatenate([q0, q1])
    t = np.concatenate([np.zeros(len(q0)), t1])
    half = float(lane_width) / 2 + corridor_margin
    # only the part of the path the ego can reach within the horizon matters (gap <= v * horizon):
    # a cheap bounding-box test first, the projection on the path for the points inside it only
    path = np.asarray(path, np.float64)
    seg = np.hypot(*np.diff(path, axis=0).T)
    reach = subject_length / 2 + speed * p.horizon_s + half
    k = int(np.searchsorted(np.r_[0.0, np.cumsum(seg)], reach)) + 2
    lo, hi = path[:k].min(0) - half, path[:k].max(0) + half
    near = np.all((q >= lo) & (q <= hi), axis=1)
    if not near.any():
        return float("inf")
    q, t = q[near], t[near]
    lat, arc, _ = project_on_path(q, path)
    gap = arc - subject_length / 2
    inside = (lat <= half) & (gap > 0)
    if not inside.any():
        return float("inf")
    c = np.maximum(t[inside], gap[inside] / speed)
    ttc = float(c.min())
    return ttc if ttc <= p.horizon_s + 1e-9 else float("inf")


@dataclass(frozen=True)
class MapReading:
    """How a risk measure reads an evidential map in the ego's frame: its ``grid``, the cells
    with ``m_O >= occ_threshold`` are obstacles, the ego's footprint (``subject_length`` x
    ``subject_width`` m) grown by ``self_margin`` m is ignored, and the corridor is the lane plus
    ``corridor_margin`` m on each side."""

    grid: GridSpec
    occ_threshold: float
    self_margin: float
    subject_length: float
    subject_width: float
    corridor_margin: float = 0.0


def map_ttc(
    masses: np.ndarray,
    vel: np.ndarray,
    path: np.ndarray,
    lane_width: float,
    speed: float,
    reading: MapReading,
    p: PredictSettings,
) -> float:
    """TTC (s) read from a map ``(2, H, W)`` in the ego's frame with the cell velocities ``vel
    (H, W, 2)`` of :func:`cell_velocities` (the ego's footprint grown by ``self_margin`` m ignored,
    as the THW does)."""
    r, c = np.nonzero(np.asarray(masses[1]) >= reading.occ_threshold)
    if len(r) == 0:
        return float("inf")
    x, y = reading.grid.rc_to_xy(r, c)
    own = (np.abs(x) <= reading.subject_length / 2 + reading.self_margin) & (
        np.abs(y) <= reading.subject_width / 2 + reading.self_margin
    )
    xy = np.stack([x[~own], y[~own]], 1)
    return time_to_conflict(
        xy,
        vel[r[~own], c[~own]],
        path,
        lane_width,
        speed,
        reading.subject_length,
        p,
        reading.corridor_margin,
    )


def box_points(
    corners: np.ndarray, velocity: np.ndarray, ego_pose: np.ndarray, spacing: float = 0.25
) -> tuple[np.ndarray, np.ndarray]:
    """Points on the outlines of boxes ``corners (B, 4, 2)`` (world, m) every ``spacing`` m and
    their velocities ``velocity (B, 2)`` (world, m/s), both in the frame of ``ego_pose``:
    ``(xy (M, 2), vel (M, 2))``."""
    corners = np.asarray(corners, np.float64)
    B = len(corners)
    if B == 0:
        return np.zeros((0, 2)), np.zeros((0, 2))
    a = corners.reshape(-1, 2)  # the 4 B edges: from a corner to the next one
    d = (np.roll(corners, -1, axis=1) - corners).reshape(-1, 2)
    n = np.maximum(np.ceil(np.hypot(d[:, 0], d[:, 1]) / spacing).astype(np.int64), 1)
    edge = np.repeat(np.arange(len(a)), n)  # each edge sampled at its own spacing
    start = np.cumsum(n) - n
    frac = (np.arange(int(n.sum())) - start[edge]) / n[edge]
    pts = a[edge] + frac[:, None] * d[edge]
    c, si = np.cos(ego_pose[2]), np.sin(ego_pose[2])
    rot = np.array([[c, si], [-si, c]])  # world -> ego
    xy = (pts - ego_pose[:2]) @ rot.T
    vel = np.asarray(velocity, np.float64)[:, :2][edge // 4] @ rot.T
    return xy, vel
