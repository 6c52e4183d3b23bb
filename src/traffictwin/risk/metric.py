"""Risk Metric Calculator on a grid map (paper 003 section 3.4; docs/design.md "Risk metric").

For one frame: the other vehicles are transformed into the subject's frame and drawn into
a bird's-eye grid map (:class:`~traffictwin.grid.GridSpec`, subject reference point = footprint
centre at the grid centre, row 0 = front). Like the paper's RMC only their *border cells*
are filled (``cv2.polylines``; ``fill="filled"`` uses ``cv2.fillPoly``) — the nearest cell of
a vehicle is always on its border, so both give the same distance.

The free distance to a vehicle = the least Euclidean distance from the subject's front
bumper segment to the centre of one of its cells inside the *region* (the border cell that
holds the vehicle's near edge has its centre within half a cell of it, so the estimate is
unbiased with a quantisation error <= cell/2 plus the line-drawing's). Regions:

* ``corridor`` (the headline label; the classic time headway): the subject's driving corridor
  ahead — cells within ``lane_width / 2 + corridor_margin`` of the path the subject will drive
  (its lane's centreline ahead, given per frame; a straight line along +x when none is given).
  The free distance is measured *along the path*, from the front bumper (arc length
  ``subject_length / 2``) to the cell's projection onto it, so a parked car at the roadside or
  a vehicle in the next lane does not count, while a lead vehicle, a car cutting in (once its
  edge crosses into the corridor) or a pedestrian crossing the lane does.
* ``paper``: everything ahead of the front bumper line within the grid (x > l/2). Under the
  pessimistic turn assumption the subject may steer towards any vehicle ahead, and the
  straight line is the shortest path to it: this is the worst time headway of the paper,
  which also counts a vehicle right next to the subject as soon as any part of it is ahead
  of the bumper (the paper's Fig. 7 discussion).
* ``camera_fov``: the part of that region the front camera sees: bearing from the camera
  (mounted ``mount_x`` ahead of the reference point) within +-hfov/2 (occlusion ignored).

Metrics (seconds; inf when nothing is ahead / nothing closes in):

* THW = d_min / v_subject (v = 0 -> inf);
* TTC = min_k d_k / (v_subject - v_k . e_k) over vehicles closing in (e_k = unit vector from
  the bumper to vehicle k's nearest cell, v_k its velocity): constant velocity, heading
  towards the target (pessimistic turn);
* WTTC = min_k d_k / (v_subject + |v_k|): worst case, the target may move straight at the
  subject at its current speed (cf. Wachenfeld et al. 2016, simplified to current speeds).

Each becomes a risk in [0, 1] as ``min(1 / T, 20) / 20`` (T = inf -> 0, T = 0 -> 1).
Critical <=> THW < t <=> risk > :func:`risk_threshold` (t) (t: the primary THW threshold, the first of
``evaluation.risk.thresholds_s``, :func:`primary`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from traffictwin.grid import GridSpec
from traffictwin.sim.scene import VEHICLE_CLASSES, Boxes

REGIONS = ("corridor", "paper", "camera_fov")
CLIP = 20.0  # 1/s: the upper limit of 1/T before normalisation
_SHIFT = 4


def risk_from_time(t: np.ndarray | float, clip: float = CLIP) -> np.ndarray | float:
    """``min(1/t, clip) / clip`` (t in s; inf -> 0, 0 -> 1); vectorised."""
    t = np.asarray(t, dtype=np.float64)
    with np.errstate(divide="ignore"):
        inv = np.where(t > 0, 1.0 / np.where(t > 0, t, 1.0), np.inf)
    out = np.minimum(inv, clip) / clip
    return float(out) if out.ndim == 0 else out


def thw_to_risk(thw: np.ndarray) -> np.ndarray:
    """Normalised risk (float32 array) from THW (s): :func:`risk_from_time` with NaN (no vehicle) -> 0."""
    thw = np.asarray(thw, dtype=np.float64)
    return np.where(np.isnan(thw), 0.0, risk_from_time(thw)).astype(np.float32)


def risk_to_thw(risk: np.ndarray | float, cap: float = 10.0) -> np.ndarray:
    """THW (s) from normalised risk, capped at ``cap`` s (risk <= 0 — no vehicle — gives ``cap``)."""
    r = np.asarray(risk, dtype=np.float64)
    with np.errstate(divide="ignore"):
        thw = np.where(r > 0, 1.0 / (CLIP * np.maximum(r, 1e-12)), np.inf)
    return np.minimum(thw, cap)


def primary(thresholds_s: Sequence[float]) -> float:
    """The primary THW threshold (s): the first of ``thresholds_s`` (config
    ``evaluation.risk.thresholds_s``), the one that defines the critical frames."""
    if not thresholds_s:
        raise ValueError("thresholds_s: expected at least one THW threshold (s), got none")
    return float(thresholds_s[0])


def risk_threshold(thw_s: float) -> float:
    """Normalised risk above which a frame is critical for a THW threshold ``thw_s`` (s)
    (``min(1/thw_s, 20) / 20``)."""
    if not thw_s > 0:
        raise ValueError(f"THW threshold must be > 0 s, got {thw_s}")
    return min(1.0 / thw_s, CLIP) / CLIP


@dataclass(frozen=True)
class RiskConfig:
    """Subject footprint (m), region, camera geometry for ``camera_fov`` (deg, m), fill mode,
    whether pedestrians count as obstacles (the paper: vehicles only), and the corridor: the lane
    width used when a frame gives none (m) and the margin added on each side (m, may be < 0)."""

    subject_length: float = 4.5
    subject_width: float = 1.8
    region: str = "paper"
    hfov_deg: float = 60.0
    mount_x: float = 1.2
    fill: str = "border"
    include_pedestrians: bool = False
    lane_width: float = 3.5
    corridor_margin: float = 0.0

    def __post_init__(self) -> None:
        if self.region not in REGIONS:
            raise ValueError(f"risk region must be one of {REGIONS}, got {self.region!r}")
        if self.fill not in ("border", "filled"):
            raise ValueError(f"risk fill must be 'border' or 'filled', got {self.fill!r}")
        if self.subject_length <= 0 or self.subject_width <= 0:
            raise ValueError("risk subject_length/subject_width must be > 0 m")
        if self.lane_width <= 0 or self.lane_width / 2 + self.corridor_margin <= 0:
            raise ValueError(
                f"risk corridor half-width lane_width/2 + corridor_margin must be > 0 m, got "
                f"lane_width {self.lane_width}, corridor_margin {self.corridor_margin}"
            )


@dataclass(frozen=True)
class RiskResult:
    """One frame: distance (m, inf if none), target (index into the boxes given, -1 none),
    thw/ttc/wttc (s) and their risks in [0, 1]."""

    distance: float
    target: int
    thw: float
    ttc: float
    wttc: float
    risk_thw: float
    risk_ttc: float
    risk_wttc: float


def to_subject_frame(boxes: Boxes, pose: np.ndarray) -> Boxes:
    """Boxes (world) expressed in the frame of the subject at ``pose`` = (x, y, yaw) (m, rad)."""
    x, y, yaw = (float(p) for p in pose)
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, s], [-s, c]])
    return Boxes(
        (boxes.center - [x, y]) @ rot.T,
        boxes.size,
        boxes.yaw - yaw,
        boxes.cls,
        z0=boxes.z0,
        velocity=boxes.velocity @ rot.T,
        ids=boxes.ids,
    )


def path_to_subject_frame(path: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """World path points (K, 2) expressed in the frame of the subject at ``pose`` (m, rad)."""
    path = np.asarray(path, float)
    if path.ndim != 2 or path.shape[1] != 2 or len(path) < 2:
        raise ValueError(f"corridor path must be (K >= 2, 2) metres, got {path.shape}")
    x, y, yaw = (float(p) for p in pose)
    c, s = np.cos(yaw), np.sin(yaw)
    return (path - [x, y]) @ np.array([[c, -s], [s, c]])


def rasterise(rel: Boxes, grid: GridSpec, fill: str = "border") -> np.ndarray:
    """Label map (rows, cols) int32: 0 free, k + 1 = cells of box k (subject-frame boxes)."""
    lab = np.zeros(grid.shape, np.int32)
    if len(rel) == 0:
        return lab
    cr = rel.corners()  # (N, 4, 2)
    r, c = grid.xy_to_rc(cr[..., 0], cr[..., 1])
    pts = np.round(np.stack([c, r], -1) * (1 << _SHIFT))
    pts = np.clip(pts, -(1 << 24), 1 << 24).astype(np.int32)
    for k in range(len(rel)):  # loop over vehicles, not cells
        if fill == "border":
            cv2.polylines(
                lab, [pts[k]], True, k + 1, thickness=1, lineType=cv2.LINE_8, shift=_SHIFT
            )
        else:
            cv2.fillPoly(lab, [pts[k]], k + 1, lineType=cv2.LINE_8, shift=_SHIFT)
    return lab


def straight_path(length: float, step: float = 0.5) -> np.ndarray:
    """A straight path (K, 2) along +x from the reference point (m): the corridor without a lane."""
    xs = np.arange(0.0, length + step / 2, step)
    return np.stack([xs, np.zeros_like(xs)], 1)


def project_on_path(xy: np.ndarray, path: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project points ``xy`` (M, 2) onto the polyline ``path`` (K >= 2, 2) (m).

    Returns the lateral distance to the polyline (M,), the arc length of the projection from
    ``path[0]`` (M,) and the unit tangent there (M, 2); vectorised over points and segments.
    """
    a, b = path[:-1], path[1:]
    ab = b - a
    seg = np.hypot(ab[:, 0], ab[:, 1])
    keep = seg > 1e-9
    a, ab, seg = a[keep], ab[keep], seg[keep]
    if len(seg) == 0:
        raise ValueError("corridor path needs at least two distinct points")
    cum = np.r_[0.0, np.cumsum(seg)[:-1]]
    apx = xy[:, 0, None] - a[:, 0]  # (M, S): x and y apart, no (M, S, 2) temporaries
    apy = xy[:, 1, None] - a[:, 1]
    t = np.clip((apx * ab[:, 0] + apy * ab[:, 1]) / (seg * seg), 0.0, 1.0)
    apx -= t * ab[:, 0]  # now the offset from the projection
    apy -= t * ab[:, 1]
    d2 = apx**2 + apy**2
    j = np.argmin(d2, axis=1)
    m = np.arange(len(xy))
    tangent = ab[j] / seg[j, None]
    return np.sqrt(d2[m, j]), cum[j] + t[m, j] * seg[j], tangent


def region_mask(grid: GridSpec, cfg: RiskConfig, path: np.ndarray | None = None) -> np.ndarray:
    """Bool (rows, cols): cells in the region the metric searches (see module docstring);
    ``path`` (K, 2, subject frame, m) only for ``corridor`` (default: straight ahead)."""
    x, y = grid.cell_centers()
    ahead = x > cfg.subject_length / 2.0
    if cfg.region == "paper":
        return ahead
    if cfg.region == "corridor":
        if path is None:
            path = straight_path(grid.length)
        lat, s, _ = project_on_path(np.stack([x.ravel(), y.ravel()], 1), np.asarray(path, float))
        inside = (lat <= cfg.lane_width / 2 + cfg.corridor_margin) & (s > cfg.subject_length / 2)
        return inside.reshape(x.shape)
    bearing = np.arctan2(y, x - cfg.mount_x)
    return ahead & (x > cfg.mount_x) & (np.abs(bearing) <= np.radians(cfg.hfov_deg) / 2.0)


def bumper_distance(grid: GridSpec, cfg: RiskConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per cell: free distance (m) from the front bumper segment and the unit direction (ex, ey)."""
    x, y = grid.cell_centers()
    dx = x - cfg.subject_length / 2.0
    ay = np.abs(y) - cfg.subject_width / 2.0
    dy = np.where(ay > 0, np.sign(y) * ay, 0.0)
    n = np.hypot(dx, dy)
    nn = np.maximum(n, 1e-9)
    return n, dx / nn, dy / nn


class RiskCalculator:
    """Risk metric on a grid for many frames with the same grid and config (caches the region)."""

    def __init__(self, grid: GridSpec, cfg: RiskConfig) -> None:
        self.grid = grid
        self.cfg = cfg
        self.region = region_mask(grid, cfg) if cfg.region != "corridor" else None
        self.dist, self.ex, self.ey = bumper_distance(grid, cfg)
        self.cx, self.cy = grid.cell_centers()

    def obstacles(self, boxes: Boxes) -> np.ndarray:
        """Indices of boxes that count as obstacles (vehicles; pedestrians if configured)."""
        classes = list(VEHICLE_CLASSES) + ([3] if self.cfg.include_pedestrians else [])
        return np.flatnonzero(np.isin(boxes.cls, classes))

    def __call__(
        self,
        pose: np.ndarray,
        speed: float,
        others: Boxes,
        path: np.ndarray | None = None,
        lane_width: float | None = None,
    ) -> RiskResult:
        """Risk of the subject at world ``pose`` (x, y, yaw) with ``speed`` (m/s >= 0) among
        ``others`` (world boxes with world velocities; the subject itself must not be in it).

        ``corridor`` region only: ``path`` (K, 2) = the subject's path ahead in *world*
        coordinates starting at its reference point (default: straight ahead) and ``lane_width``
        (m; default ``cfg.lane_width``)."""
        if not np.isfinite(speed) or speed < 0:
            raise ValueError(f"subject speed must be finite and >= 0 m/s, got {speed}")
        idx = self.obstacles(others)
        rel = to_subject_frame(others.subset(idx), pose)
        # cull boxes far outside the grid before drawing
        half = np.hypot(self.grid.length, self.grid.width) / 2 + 10.0
        near = np.hypot(rel.center[:, 0], rel.center[:, 1]) < half
        idx, rel = idx[near], rel.subset(near)
        lab = rasterise(rel, self.grid, self.cfg.fill)
        if self.cfg.region == "corridor":
            sel, d, ex_c, ey_c = self._corridor(lab, pose, path, lane_width)
        else:
            sel = (lab > 0) & self.region
            d = self.dist[sel]
            ex_c, ey_c = self.ex[sel], self.ey[sel]
        if not sel.any():
            return RiskResult(np.inf, -1, np.inf, np.inf, np.inf, 0.0, 0.0, 0.0)
        k = lab[sel] - 1
        # per-vehicle nearest cell
        order = np.lexsort((d, k))
        k, d = k[order], d[order]
        first = np.r_[True, k[1:] != k[:-1]]
        kv, dv = k[first], d[first]
        ex, ey = ex_c[order][first], ey_c[order][first]
        vel = rel.velocity[kv]
        closing = speed - (vel[:, 0] * ex + vel[:, 1] * ey)
        with np.errstate(divide="ignore", invalid="ignore"):
            ttc = np.where(closing > 1e-9, dv / np.where(closing > 1e-9, closing, 1.0), np.inf)
            ttc = np.where((dv == 0) & (closing > 1e-9), 0.0, ttc)
            wsp = speed + np.hypot(vel[:, 0], vel[:, 1])
            wttc = np.where(wsp > 1e-9, dv / np.where(wsp > 1e-9, wsp, 1.0), np.inf)
        j = int(np.argmin(dv))
        dmin = float(dv[j])
        thw = dmin / speed if speed > 0 else np.inf
        t_ttc, t_wttc = float(np.min(ttc)), float(np.min(wttc))
        return RiskResult(
            dmin,
            int(idx[kv[j]]),
            thw,
            t_ttc,
            t_wttc,
            float(risk_from_time(thw)),
            float(risk_from_time(t_ttc)),
            float(risk_from_time(t_wttc)),
        )

    def _corridor(
        self, lab: np.ndarray, pose: np.ndarray, path: np.ndarray | None, lane_width: float | None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Occupied cells in the corridor (bool mask), their free distance along the path (m)
        and the path's unit tangent at their projection (subject frame), in mask order."""
        rel_path = (
            straight_path(self.grid.length) if path is None else path_to_subject_frame(path, pose)
        )
        half = (self.cfg.lane_width if lane_width is None else float(lane_width)) / 2
        half += self.cfg.corridor_margin
        occ = lab > 0
        flat = np.flatnonzero(occ)
        xs, ys = self.cx.ravel()[flat], self.cy.ravel()[flat]
        if len(flat) == 0:
            return occ, np.zeros(0), np.zeros(0), np.zeros(0)
        lat, arc, tangent = project_on_path(np.stack([xs, ys], 1), rel_path)
        inside = (lat <= half) & (arc > self.cfg.subject_length / 2)
        sel = np.zeros(lab.size, bool)
        sel[flat[inside]] = True
        # mask order (row-major) = flat order, so the per-cell arrays line up with lab[sel]
        return (
            sel.reshape(lab.shape),
            arc[inside] - self.cfg.subject_length / 2,
            tangent[inside, 0],
            tangent[inside, 1],
        )


def swept_cells(rel: Boxes, grid: GridSpec, horizon: float = 3.0, dt: float = 0.5) -> np.ndarray:
    """Bool (rows, cols): border cells the boxes (subject frame) occupy over the next ``horizon`` s
    under constant velocity (the paper's Fig. 3 'blue' cells; for figures)."""
    out = np.zeros(grid.shape, bool)
    for t in np.arange(dt, horizon + 1e-9, dt):
        moved = Boxes(
            rel.center + t * rel.velocity, rel.size, rel.yaw, rel.cls, velocity=rel.velocity
        )
        out |= rasterise(moved, grid, "border") > 0
    return out


def occupancy_distance(
    occupied: np.ndarray,
    grid: GridSpec,
    cfg: RiskConfig,
    path: np.ndarray | None = None,
    lane_width: float | None = None,
    self_margin: float = 0.5,
) -> float:
    """Free distance (m) along the corridor to the nearest occupied cell of a *grid map*.

    The map-based twin of :meth:`RiskCalculator.__call__` (region ``corridor``): ``occupied`` is a
    bool ``(rows, cols)`` map in the subject's sensor frame (subject at the grid centre, row 0
    front; e.g. ``m_O >= 0.5`` of an evidential map); ``path`` (K, 2) the subject's path ahead in
    that frame (default straight ahead), ``lane_width`` (m; default ``cfg.lane_width``). Cells of
    the subject's own footprint grown by ``self_margin`` (m) are ignored (other vehicles' maps
    show the subject itself). Returns inf when no occupied cell is in the corridor."""
    if cfg.region != "corridor":
        raise ValueError(f"occupancy_distance needs the corridor region, got {cfg.region!r}")
    occupied = np.asarray(occupied, dtype=bool)
    if occupied.shape != grid.shape:
        raise ValueError(f"occupied map is {occupied.shape}, the grid is {grid.shape}")
    r, c = np.nonzero(occupied)
    if len(r) == 0:
        return float("inf")
    x, y = grid.rc_to_xy(r, c)
    own = (np.abs(x) <= cfg.subject_length / 2 + self_margin) & (
        np.abs(y) <= cfg.subject_width / 2 + self_margin
    )
    x, y = x[~own], y[~own]
    if len(x) == 0:
        return float("inf")
    rel_path = straight_path(grid.length) if path is None else np.asarray(path, float)
    lat, arc, _ = project_on_path(np.stack([x, y], 1), rel_path)
    half = (cfg.lane_width if lane_width is None else float(lane_width)) / 2 + cfg.corridor_margin
    inside = (lat <= half) & (arc > cfg.subject_length / 2)
    if not inside.any():
        return float("inf")
    return float(np.min(arc[inside]) - cfg.subject_length / 2)


def headway(distance: np.ndarray | float, speed: np.ndarray | float) -> np.ndarray:
    """Time headway (s) = distance (m) / speed (m/s); inf where the speed is 0 or nothing is ahead."""
    d = np.asarray(distance, dtype=np.float64)
    v = np.asarray(speed, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.where((v > 0) & np.isfinite(d), d / np.where(v > 0, v, 1.0), np.inf)
    return out
