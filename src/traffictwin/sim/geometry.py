"""2D polyline helpers for the simulator (vectorised; metres, radians).

A polyline is an ``(M, 2)`` array of points; its direction is the order of the points.
"""

from __future__ import annotations

import numpy as np


def cumulative_length(points: np.ndarray) -> np.ndarray:
    """Arc length (m) at every vertex of a polyline, shape ``(M,)``, starting at 0."""
    points = np.asarray(points, dtype=np.float64)
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(seg)])


def resample(points: np.ndarray, step: float) -> np.ndarray:
    """Resample a polyline at (about) ``step`` metres between consecutive points (keeps both ends)."""
    cum = cumulative_length(points)
    n = max(2, int(np.ceil(cum[-1] / step)) + 1)
    s = np.linspace(0.0, cum[-1], n)
    return np.stack([np.interp(s, cum, points[:, 0]), np.interp(s, cum, points[:, 1])], axis=1)


def interpolate(
    points: np.ndarray, cum: np.ndarray, s: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Position ``(K, 2)`` and heading ``(K,)`` (rad) at arc lengths ``s`` (m, clipped to the polyline)."""
    s = np.clip(np.asarray(s, dtype=np.float64), 0.0, cum[-1])
    idx = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(cum) - 2)
    seg = points[idx + 1] - points[idx]
    seg_len = np.maximum(cum[idx + 1] - cum[idx], 1e-12)
    f = ((s - cum[idx]) / seg_len)[:, None]
    xy = points[idx] + f * seg
    yaw = np.arctan2(seg[:, 1], seg[:, 0])
    return xy, yaw


def normals(points: np.ndarray) -> np.ndarray:
    """Unit left normals ``(M, 2)`` at the vertices (average of the adjacent segments' normals)."""
    d = np.diff(points, axis=0)
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    t = np.concatenate([d[:1], d[:-1] + d[1:], d[-1:]], axis=0)
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
    return np.stack([-t[:, 1], t[:, 0]], axis=1)


def offset(points: np.ndarray, d: float) -> np.ndarray:
    """Polyline shifted by ``d`` metres to its left (negative: right)."""
    return points + d * normals(points)


def hermite(
    p0: np.ndarray, yaw0: float, p1: np.ndarray, yaw1: float, step: float = 1.0
) -> np.ndarray:
    """Cubic Hermite curve from ``p0`` (heading ``yaw0``) to ``p1`` (heading ``yaw1``), about ``step`` m apart."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    dist = float(np.linalg.norm(p1 - p0))
    n = max(3, int(np.ceil(dist * 1.3 / step)) + 1)
    t = np.linspace(0.0, 1.0, n)[:, None]
    m0 = dist * np.array([np.cos(yaw0), np.sin(yaw0)])
    m1 = dist * np.array([np.cos(yaw1), np.sin(yaw1)])
    h00, h10 = 2 * t**3 - 3 * t**2 + 1, t**3 - 2 * t**2 + t
    h01, h11 = -2 * t**3 + 3 * t**2, t**3 - t**2
    return h00 * p0 + h10 * m0 + h01 * p1 + h11 * m1


def arc(center: np.ndarray, radius: float, a0: float, a1: float, step: float = 1.0) -> np.ndarray:
    """Circular arc from angle ``a0`` to ``a1`` (rad; ``a1 > a0`` is counter-clockwise)."""
    n = max(2, int(np.ceil(abs(a1 - a0) * radius / step)) + 1)
    a = np.linspace(a0, a1, n)
    return np.stack([center[0] + radius * np.cos(a), center[1] + radius * np.sin(a)], axis=1)


def segments(points: np.ndarray) -> np.ndarray:
    """Segments ``(M-1, 2, 2)`` of a polyline."""
    return np.stack([points[:-1], points[1:]], axis=1)


def distance_to_segments(q: np.ndarray, segs: np.ndarray, chunk: int = 4096) -> np.ndarray:
    """Distance (m) from every point ``q (K, 2)`` to the nearest of ``segs (S, 2, 2)``; chunked over points."""
    q = np.asarray(q, dtype=np.float64).reshape(-1, 2)
    out = np.full(len(q), np.inf)
    if len(segs) == 0:
        return out
    a, b = segs[:, 0], segs[:, 1]
    ab = b - a
    ab2 = np.maximum((ab**2).sum(1), 1e-12)
    for i in range(0, len(q), chunk):
        p = q[i : i + chunk, None, :]
        t = np.clip(((p - a) * ab).sum(-1) / ab2, 0.0, 1.0)
        d = p - (a + t[..., None] * ab)
        out[i : i + chunk] = np.sqrt((d**2).sum(-1)).min(1)
    return out
