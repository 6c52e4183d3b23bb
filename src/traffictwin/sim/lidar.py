"""A Velodyne VLP-32C-like roof lidar: 32 channels, 360 deg, ray cast against the world.

Elevations: the VLP-32C's non-uniform table (datasheet, -25 deg ... +15 deg, dense around the
horizon), or ``uniform=True`` for 32 evenly spaced channels over the same interval. Azimuth
resolution, maximum range, Gaussian range noise (sigma, m) and per-ray dropout (probability)
are configurable. The scan is cast in azimuth sectors; every sector only tests the boxes whose
angular footprint overlaps it (plus the ground plane), and all 32 channels of a column share
one footprint slab test (:func:`_cast_columns`); results equal the generic
:func:`~traffictwin.sim.raycast.cast_rays` (tested).

Frames: the sensor pose ``(x, y, yaw)`` is the lidar's ground projection in the world (m, rad);
the lidar sits ``height`` m above the ground. Returned points are in the *sensor frame*
(x forward, y left, z up from the ground under the sensor).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from traffictwin.scan import HIT_GROUND, HIT_NOTHING, Scan
from traffictwin.sim.scene import Boxes

#: VLP-32C elevation angles (deg), sorted ascending (Velodyne VLP-32C user manual, table 9-2)
VLP32C_ELEVATIONS_DEG: tuple[float, ...] = (
    -25.0,
    -15.639,
    -11.31,
    -8.843,
    -7.254,
    -6.148,
    -5.333,
    -4.667,
    -4.0,
    -3.667,
    -3.333,
    -3.0,
    -2.667,
    -2.333,
    -2.0,
    -1.667,
    -1.333,
    -1.0,
    -0.667,
    -0.333,
    0.0,
    0.333,
    0.667,
    1.0,
    1.333,
    1.667,
    2.333,
    3.333,
    4.667,
    7.0,
    10.333,
    15.0,
)


@dataclass(frozen=True)
class LidarSpec:
    """Lidar parameters: ``azimuth_res_deg`` (deg), ``max_range``/``min_range`` (m),
    ``range_noise`` (sigma, m), ``dropout`` (probability a ray returns nothing),
    ``height`` (m above ground), ``uniform`` (evenly spaced elevations instead of the table)."""

    azimuth_res_deg: float = 0.2
    max_range: float = 100.0
    min_range: float = 1.0
    range_noise: float = 0.02
    dropout: float = 0.0
    height: float = 1.9
    uniform: bool = False
    sectors: int = 72

    def __post_init__(self) -> None:
        if not 0 < self.azimuth_res_deg <= 10:
            raise ValueError(
                f"LidarSpec.azimuth_res_deg must be in (0, 10] deg, got {self.azimuth_res_deg}"
            )
        if abs(360.0 / self.azimuth_res_deg - round(360.0 / self.azimuth_res_deg)) > 1e-6:
            raise ValueError(
                f"LidarSpec.azimuth_res_deg must divide 360 deg, got {self.azimuth_res_deg}"
            )
        if not self.max_range > self.min_range >= 0:
            raise ValueError(
                f"LidarSpec: need max_range > min_range >= 0 m, got {self.max_range}, {self.min_range}"
            )
        if self.range_noise < 0 or not 0 <= self.dropout < 1:
            raise ValueError(
                f"LidarSpec: range_noise >= 0 m and dropout in [0, 1) required, got {self.range_noise}, {self.dropout}"
            )
        if self.height <= 0:
            raise ValueError(f"LidarSpec.height must be > 0 m, got {self.height}")

    @property
    def elevations(self) -> np.ndarray:
        """Channel elevations (rad), ascending, shape (32,)."""
        if self.uniform:
            return np.deg2rad(np.linspace(-25.0, 15.0, 32))
        return np.deg2rad(np.array(VLP32C_ELEVATIONS_DEG))

    @property
    def n_azimuth(self) -> int:
        return int(round(360.0 / self.azimuth_res_deg))

    @property
    def azimuths(self) -> np.ndarray:
        """Column azimuths (rad) in the sensor frame, 0 = forward, counter-clockwise, in [-pi, pi)."""
        return -np.pi + (np.arange(self.n_azimuth) + 0.5) * (2 * np.pi / self.n_azimuth)


def _cast_columns(
    pose: np.ndarray,
    world_az: np.ndarray,
    el: np.ndarray,
    height: float,
    boxes: Boxes,
    max_range: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Rays of all channels ``el (E,)`` in the columns ``world_az (A,)`` (world azimuths, rad)
    from ``(pose x, y, height)`` against ``boxes``: distance (A, E) along the ray (inf: no hit)
    and box index (A, E). All rays of a column share one vertical plane, so the footprint slab
    test (x, y in the box frame) is done once per column and box, in horizontal distance ``d``;
    the z slab of channel ``e`` is then ``d`` in ``[(z0 - h) / tan e, (z1 - h) / tan e]``.
    Equivalent to :func:`~traffictwin.sim.raycast.cast_rays` for these rays."""
    c, s = np.cos(boxes.yaw), np.sin(boxes.yaw)
    ox, oy = pose[0] - boxes.center[:, 0], pose[1] - boxes.center[:, 1]
    lx, ly = c * ox + s * oy, -s * ox + c * oy  # (B,) sensor in box frames
    ua, va = np.cos(world_az)[:, None], np.sin(world_az)[:, None]
    dx, dy = c[None] * ua + s[None] * va, -s[None] * ua + c[None] * va  # (A, B)
    hl, hw = boxes.size[:, 0] / 2, boxes.size[:, 1] / 2
    t_in = np.full(dx.shape, -np.inf)
    t_out = np.full(dx.shape, np.inf)
    for o, dd, half in ((lx, dx, hl), (ly, dy, hw)):
        small = np.abs(dd) < 1e-12
        inv = 1.0 / np.where(small, 1e-12, dd)
        t1, t2 = (-half - o)[None] * inv, (half - o)[None] * inv
        out_par = small & (np.abs(o) > half)[None]
        t1 = np.where(small, np.where(out_par, np.inf, -np.inf), t1)
        t2 = np.where(small, np.inf, t2)
        np.maximum(t_in, np.minimum(t1, t2), out=t_in)
        np.minimum(t_out, np.maximum(t1, t2), out=t_out)
    # z slab per channel, in horizontal distance: (E, B)
    tan_e = np.tan(el)[:, None]
    z0, z1 = (boxes.z0 - height)[None], (boxes.z0 + boxes.size[:, 2] - height)[None]
    flat = np.abs(tan_e) < 1e-12
    with np.errstate(divide="ignore", invalid="ignore"):
        a, b = z0 / np.where(flat, 1.0, tan_e), z1 / np.where(flat, 1.0, tan_e)
    z_in = np.where(flat, np.where((z0 < 0) & (z1 > 0), -np.inf, np.inf), np.minimum(a, b))
    z_out = np.where(flat, np.inf, np.maximum(a, b))
    near = np.maximum(t_in[:, None, :], z_in[None])  # (A, E, B)
    far = np.minimum(t_out[:, None, :], z_out[None])
    cos_e = np.cos(el)[None, :, None]
    ok = (near <= far) & (near > 1e-4 * cos_e)
    t = np.where(ok, near / cos_e, np.inf)
    j = np.argmin(t, axis=2)
    best = np.take_along_axis(t, j[..., None], axis=2)[..., 0]
    best = np.where(best < max_range, best, np.inf)
    return best, np.where(np.isfinite(best), j, -1)


def _candidates(spec: LidarSpec, pose: np.ndarray, boxes: Boxes) -> np.ndarray:
    """Indices of the boxes whose footprint circle reaches within ``max_range`` of the sensor."""
    if not len(boxes):
        return np.zeros(0, dtype=np.int64)
    rad = 0.5 * np.hypot(boxes.size[:, 0], boxes.size[:, 1])
    rel = boxes.center - pose[:2]
    dc = np.hypot(rel[:, 0], rel[:, 1])
    return np.flatnonzero(dc - rad <= spec.max_range)


def _sector_overlap(sub: Boxes, pose: np.ndarray, n_sec: int) -> np.ndarray:
    """(n_sec, len(sub)) mask: box j's angular footprint, seen from the sensor, overlaps sector k
    (sector k covers sensor azimuths ``[-pi + k w, -pi + (k+1) w)``, w = 2 pi / n_sec rad);
    a box around the sensor overlaps every sector."""
    rel = sub.center - pose[:2]
    center_ang = np.arctan2(rel[:, 1], rel[:, 0]) - pose[2]
    corners = sub.corners() - pose[:2]
    ang = np.arctan2(corners[..., 1], corners[..., 0]) - pose[2]
    dev = np.abs((ang - center_ang[:, None] + np.pi) % (2 * np.pi) - np.pi).max(1)
    close = np.hypot(rel[:, 0], rel[:, 1]) <= 0.5 * np.hypot(sub.size[:, 0], sub.size[:, 1]) + 0.5
    half_span = np.where(close, np.pi, dev + 1e-3)
    sec_w = 2 * np.pi / n_sec
    sec_mid = -np.pi + (np.arange(n_sec) + 0.5) * sec_w
    diff = np.abs((center_ang[None, :] - sec_mid[:, None] + np.pi) % (2 * np.pi) - np.pi)
    return diff <= half_span[None, :] + sec_w / 2


def _ground(spec: LidarSpec, el: np.ndarray, n_az: int) -> tuple[np.ndarray, np.ndarray]:
    """Distance (n_az, E; m, ``max_range`` for no return) and hit code of the ground plane: the
    same for every column of a channel."""
    sin_e = np.sin(el)
    with np.errstate(divide="ignore"):
        t_ground = np.where(sin_e < -1e-9, -spec.height / sin_e, np.inf)
    g_hit = t_ground < spec.max_range
    dist = np.where(g_hit, t_ground, spec.max_range)[None].repeat(n_az, 0)
    hit = np.where(g_hit, HIT_GROUND, HIT_NOTHING)[None].repeat(n_az, 0).astype(np.int64)
    return dist, hit


def _add_noise(
    spec: LidarSpec, dist: np.ndarray, hit: np.ndarray, rng: np.random.Generator | None
) -> None:
    """Range noise (m) on returns and per-ray dropout, drawn from ``rng`` (in place), then every
    return outside ``[min_range, max_range]`` becomes no return."""
    if rng is not None:
        if spec.range_noise > 0:
            ret = hit != HIT_NOTHING
            dist[ret] = dist[ret] + rng.normal(0.0, spec.range_noise, int(ret.sum()))
        if spec.dropout > 0:
            drop = rng.random(len(dist)) < spec.dropout
            hit[drop] = HIT_NOTHING
            dist[drop] = spec.max_range
    short = (dist < spec.min_range) | (dist > spec.max_range)
    hit[short] = HIT_NOTHING
    dist[short] = spec.max_range


def scan(
    spec: LidarSpec, pose: np.ndarray, boxes: Boxes, rng: np.random.Generator | None = None
) -> Scan:
    """Cast one revolution of ``spec`` from sensor ``pose`` (x, y, yaw; m, rad) against ``boxes`` + ground.

    The caller excludes the sensor's own vehicle from ``boxes`` (a box around the origin is
    ignored anyway). ``rng`` draws range noise and dropout (none when ``None``).
    """
    pose = np.asarray(pose, dtype=np.float64).reshape(3)
    el = spec.elevations
    az = spec.azimuths
    n_az, n_el = len(az), len(el)
    A, E = np.meshgrid(az, el, indexing="ij")  # (n_az, n_el)

    cand = _candidates(spec, pose, boxes)
    sub = boxes.subset(cand) if len(cand) else Boxes.empty()
    n_sec = max(1, min(spec.sectors, n_az))
    sec_of_col = (np.arange(n_az) * n_sec) // n_az
    dist2, hit2 = _ground(spec, el, n_az)
    if len(sub):
        overlap = _sector_overlap(sub, pose, n_sec)
        bounds = np.searchsorted(sec_of_col, np.arange(n_sec + 1))
        for k in range(n_sec):
            cols = np.arange(bounds[k], bounds[k + 1])
            bsel = np.flatnonzero(overlap[k])
            if len(cols) == 0 or len(bsel) == 0:
                continue
            d, h = _cast_columns(
                pose, az[cols] + pose[2], el, spec.height, sub.subset(bsel), spec.max_range
            )
            better = d < dist2[cols]
            dist2[cols] = np.where(better, d, dist2[cols])
            hit2[cols] = np.where(better, cand[bsel][np.maximum(h, 0)], hit2[cols])
    dist = dist2.reshape(-1)
    hit = hit2.reshape(-1)
    _add_noise(spec, dist, hit, rng)
    return Scan(
        range=dist.reshape(n_az, n_el),
        hit=hit.reshape(n_az, n_el),
        azimuth=A,
        elevation=E,
        spec=spec,
    )
