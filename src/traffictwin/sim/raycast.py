"""Vectorised ray casting against oriented boxes and the ground plane (shared by lidar and camera).

Rays are cast in float32 in chunks of ``chunk`` ray-box pairs to bound memory. Every box is
intersected in its own frame (rotation about z, footprint centre at the origin, bottom at
``z0``) with the slab test; a ray whose origin lies inside a box ignores that box (the sensor's
own vehicle, an agent overlapping the sensor). The ground is the plane ``z = 0``.
"""

from __future__ import annotations

import numpy as np

# the hit codes live with the scan data (traffictwin.scan); re-exported here
from traffictwin.scan import HIT_GROUND as HIT_GROUND
from traffictwin.scan import HIT_NOTHING as HIT_NOTHING
from traffictwin.sim.scene import Boxes

_EPS = 1e-4


def _check(
    origins: np.ndarray, dirs: np.ndarray, max_range: float
) -> tuple[np.ndarray, np.ndarray]:
    origins = np.asarray(origins, dtype=np.float64)
    dirs = np.asarray(dirs, dtype=np.float64)
    if origins.ndim != 2 or origins.shape[1] != 3:
        raise ValueError(f"cast_rays: origins must have shape (R, 3), got {origins.shape}")
    if dirs.shape != origins.shape:
        raise ValueError(
            f"cast_rays: dirs must have the shape of origins {origins.shape}, got {dirs.shape}"
        )
    if not np.isfinite(max_range) or max_range <= 0:
        raise ValueError(
            f"cast_rays: max_range must be a positive finite distance (m), got {max_range}"
        )
    return origins, dirs


def cast_rays(
    origins: np.ndarray, dirs: np.ndarray, boxes: Boxes, max_range: float, chunk: int = 1 << 21
) -> tuple[np.ndarray, np.ndarray]:
    """First intersection of every ray with ``boxes`` and the ground plane ``z = 0``.

    ``origins (R, 3)`` (m, world), ``dirs (R, 3)`` unit vectors, ``max_range`` (m).
    Returns ``dist (R,)`` float64 (m along the ray; ``max_range`` where nothing is hit) and
    ``hit (R,)`` int64: the box index, ``-1`` (:data:`HIT_GROUND`) or ``-2`` (:data:`HIT_NOTHING`).
    """
    origins, dirs = _check(origins, dirs, max_range)
    R = len(origins)
    dist = np.full(R, float(max_range))
    hit = np.full(R, HIT_NOTHING, dtype=np.int64)
    if R == 0:
        return dist, hit
    # ground plane
    with np.errstate(divide="ignore", invalid="ignore"):
        tg = np.where(dirs[:, 2] < -1e-9, -origins[:, 2] / dirs[:, 2], np.inf)
    g = (tg > 0) & (tg < dist)
    dist[g] = tg[g]
    hit[g] = HIT_GROUND
    n = len(boxes)
    if n == 0:
        return dist, hit
    # cull boxes that no ray can reach: farther than max_range from the origins' bounding circle
    o_c = origins.mean(0)
    o_rad = float(np.sqrt(((origins[:, :2] - o_c[:2]) ** 2).sum(1).max()))
    b_rad = 0.5 * np.sqrt(boxes.size[:, 0] ** 2 + boxes.size[:, 1] ** 2)
    near = np.linalg.norm(boxes.center - o_c[:2], axis=1) <= max_range + o_rad + b_rad
    idx = np.flatnonzero(near)
    if len(idx) == 0:
        return dist, hit
    # box parameters (float64 for the translation, float32 for the per-pair math)
    c = np.cos(boxes.yaw[idx])
    s = np.sin(boxes.yaw[idx])
    half = (boxes.size[idx] / 2).astype(np.float32)
    half[:, 2] = boxes.size[idx, 2]  # z extent: [0, h] in the box frame
    step = max(1, chunk // len(idx))
    for a in range(0, R, step):
        o = origins[a : a + step]
        d = dirs[a : a + step]
        # to box frames: (r, n)
        ox = o[:, None, 0] - boxes.center[idx, 0][None]
        oy = o[:, None, 1] - boxes.center[idx, 1][None]
        lx = (c * ox + s * oy).astype(np.float32)
        ly = (-s * ox + c * oy).astype(np.float32)
        lz = (o[:, None, 2] - boxes.z0[idx][None]).astype(np.float32)
        dx = (c[None] * d[:, None, 0] + s[None] * d[:, None, 1]).astype(np.float32)
        dy = (-s[None] * d[:, None, 0] + c[None] * d[:, None, 1]).astype(np.float32)
        dz = np.broadcast_to(d[:, None, 2].astype(np.float32), dx.shape)
        tnear = np.full(lx.shape, -np.inf, dtype=np.float32)
        tfar = np.full(lx.shape, np.inf, dtype=np.float32)
        inside = np.ones(lx.shape, dtype=bool)
        for org, dd, lo, hi in (
            (lx, dx, -half[:, 0], half[:, 0]),
            (ly, dy, -half[:, 1], half[:, 1]),
            (lz, dz, np.zeros_like(half[:, 2]), half[:, 2]),
        ):
            lo, hi = lo[None], hi[None]
            inside &= (org > lo) & (org < hi)
            small = np.abs(dd) < 1e-9
            inv = 1.0 / np.where(small, np.float32(1e-9), dd)
            t1 = (lo - org) * inv
            t2 = (hi - org) * inv
            # a ray parallel to a slab misses unless its origin is inside that slab
            outside_par = small & ((org < lo) | (org > hi))
            # (outside: both +inf -> tnear = +inf, a miss; inside: the slab does not constrain t)
            t1 = np.where(small, np.where(outside_par, np.inf, -np.inf), t1)
            t2 = np.where(small, np.inf, t2)
            np.maximum(tnear, np.minimum(t1, t2), out=tnear)
            np.minimum(tfar, np.maximum(t1, t2), out=tfar)
        ok = (tnear <= tfar) & (tnear > _EPS) & ~inside
        tn = np.where(ok, tnear, np.inf)
        j = np.argmin(tn, axis=1)
        tbest = tn[np.arange(len(tn)), j].astype(np.float64)
        better = tbest < dist[a : a + step]
        dist[a : a + step][better] = tbest[better]
        hit[a : a + step][better] = idx[j[better]]
    return dist, hit
