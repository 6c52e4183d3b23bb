"""Road templates: static worlds of about 400 m with lanes, sidewalks and occluders.

A world is built from a template name and a seed (:func:`build_world`). Every template is
either a *junction* (straight arms of 200 m radiating from a centre at the origin, lanes that
run from every arm to every other arm through a cubic-Hermite connector, or around a ring
for the roundabout) or a *single road* (straight, curve, S-curve) with lanes in both
directions. Traffic drives on the right. Static occluders (buildings, walls, vegetation,
poles) are oriented boxes (:class:`~traffictwin.sim.scene.Boxes`) placed beside the
roads and rejected where they would intrude on a road or its sidewalks.

Units: metres, radians, m/s. World frame: x east, y north, z up; the junction centre (or
the middle of the road) is near the origin.

Simplification (documented): there is no interaction model between lanes — vehicles on
crossing or merging lanes can overlap inside a junction. Vehicles of the same entry lane
share one speed, so they never overlap on that lane (:mod:`traffictwin.sim.traffic`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from traffictwin.sim import geometry as geo
from traffictwin.sim.scene import Boxes, Cls

TEMPLATES: tuple[str, ...] = (
    "cross4",  # 4-way intersection
    "t_junction",  # T intersection
    "y_junction",  # Y junction (acute branches)
    "skewed_cross",  # 4-way with a skew angle of 50..70 deg
    "five_way",  # 5 arms
    "roundabout",  # single-lane ring, 4 arms
    "straight",  # straight two-lane road with parking
    "boulevard",  # straight road, 2 lanes per direction
    "curve",  # straight - arc - straight
    "s_curve",  # straight - left arc - right arc - straight
)

ARM_LENGTH = 200.0  # m, junction arms (total extent ~ 400 m)
URBAN_SPEED = 13.9  # m/s (50 km/h)
TURN_SPEED = 8.3  # m/s (30 km/h) for turns and the roundabout
STATIC_ID0 = 1_000_000  # ids of static boxes start here (agents use small ids)


@dataclass
class Lane:
    """A route a vehicle can follow: ``centerline (M, 2)`` (m; direction of travel = point order).

    ``width`` lane width (m); ``speed_limit`` (m/s); ``entry``: lanes that share their first
    part (the same incoming lane of a junction) share this id.
    """

    centerline: np.ndarray
    width: float
    speed_limit: float
    entry: int = 0
    cum: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.centerline = np.asarray(self.centerline, dtype=np.float64)
        self.cum = geo.cumulative_length(self.centerline)

    @property
    def length(self) -> float:
        """Length of the route (m)."""
        return float(self.cum[-1])

    def pose_at(self, s: np.ndarray) -> np.ndarray:
        """Poses ``(K, 3)`` (x, y, yaw) at arc lengths ``s`` (m; clipped to the lane)."""
        xy, yaw = geo.interpolate(self.centerline, self.cum, np.atleast_1d(s))
        return np.concatenate([xy, yaw[:, None]], axis=1)


@dataclass
class Road:
    """A road section: ``centerline (M, 2)``, drivable ``half_width`` (m, lanes + parking strip),
    ``sidewalk`` width (m) on both sides, lanes per direction, lane width (m), parking strip."""

    centerline: np.ndarray
    half_width: float
    sidewalk: float
    lanes_per_dir: int
    lane_width: float
    parking: bool
    closed: bool = False


@dataclass
class World:
    """A static world: occluders, lanes, sidewalks, parking strips (see module docstring)."""

    template: str
    seed: int
    static: Boxes
    lanes: list[Lane]
    sidewalks: list[np.ndarray]
    roads: list[Road]
    parking: list[tuple[np.ndarray, float]]  # (polyline, yaw offset 0 or pi) for parked cars
    center: np.ndarray
    junction_radius: float = 0.0

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) of all road centerlines (m)."""
        pts = np.concatenate([r.centerline for r in self.roads])
        return (
            float(pts[:, 0].min()),
            float(pts[:, 1].min()),
            float(pts[:, 0].max()),
            float(pts[:, 1].max()),
        )

    def surface_at(self, xy: np.ndarray) -> np.ndarray:
        """Surface type at world points ``xy (..., 2)``: 0 off-road, 1 road, 2 sidewalk (int8)."""
        xy = np.asarray(xy, dtype=np.float64)
        flat = xy.reshape(-1, 2)
        out = np.zeros(len(flat), dtype=np.int8)
        for road in self.roads:
            d = geo.distance_to_segments(flat, geo.segments(road.centerline))
            out = np.where((out == 0) & (d < road.half_width + road.sidewalk), 2, out)
            out = np.where(d < road.half_width, 1, out)
        return out.reshape(xy.shape[:-1])


# ---------------------------------------------------------------------------------------------
def _rng(template: str, seed: int) -> np.random.Generator:
    return np.random.default_rng(
        np.random.SeedSequence([int(seed), TEMPLATES.index(template), 7001])
    )


def _check_template(template: str) -> None:
    if template not in TEMPLATES:
        raise ValueError(f"unknown road template '{template}'; expected one of {list(TEMPLATES)}")


def _road_params(rng: np.random.Generator, lanes_per_dir: int | None = None) -> dict:
    lw = float(rng.uniform(3.2, 3.7))
    n = int(lanes_per_dir if lanes_per_dir is not None else rng.choice([1, 1, 2]))
    parking = bool(rng.random() < 0.7)
    hw = n * lw + (2.3 if parking else 0.5)
    return dict(
        lane_width=lw,
        lanes_per_dir=n,
        parking=parking,
        half_width=hw,
        sidewalk=float(rng.uniform(2.0, 4.0)),
    )


def _junction(template: str, rng: np.random.Generator) -> tuple[list[float], bool]:
    """Arm angles (rad) and whether the junction is a roundabout."""
    j = lambda d: np.deg2rad(rng.uniform(-d, d))  # noqa: E731 - small jitter
    base = float(rng.uniform(0, 2 * np.pi))
    if template == "cross4":
        a = [0, np.pi / 2 + j(4), np.pi + j(4), 3 * np.pi / 2 + j(4)]
    elif template == "t_junction":
        a = [0, np.pi / 2 + j(6), np.pi]
    elif template == "y_junction":
        half = np.deg2rad(rng.uniform(22, 35))
        a = [np.pi, half, -half]
    elif template == "skewed_cross":
        sk = np.deg2rad(rng.uniform(50, 70))
        a = [0, sk, np.pi, np.pi + sk]
    elif template == "five_way":
        a = [k * 2 * np.pi / 5 + j(5) for k in range(5)]
    elif template == "roundabout":
        a = [0, np.pi / 2 + j(8), np.pi + j(8), 3 * np.pi / 2 + j(8)]
    else:  # pragma: no cover - guarded by callers
        raise ValueError(template)
    return sorted(float((base + x) % (2 * np.pi)) for x in a), template == "roundabout"


def _build_junction(template: str, rng: np.random.Generator):
    angles, is_round = _junction(template, rng)
    n_arms = len(angles)
    rp = [_road_params(rng, 1 if is_round else None) for _ in range(n_arms)]
    gaps = np.diff(np.r_[angles, angles[0] + 2 * np.pi])
    hw_max = max(p["half_width"] + p["sidewalk"] for p in rp)
    r_stop = float(hw_max / np.tan(min(gaps) / 2) + 3.0)
    ring_r = 0.0
    if is_round:
        ring_r = float(rng.uniform(14.0, 20.0))
        r_stop = ring_r + 8.0
    roads: list[Road] = []
    arm_dirs = []
    for a, p in zip(angles, rp):
        u = np.array([np.cos(a), np.sin(a)])
        r0 = ring_r if is_round else 0.0
        cl = r0 * u + np.linspace(0, ARM_LENGTH - r0, int((ARM_LENGTH - r0) / 2) + 1)[:, None] * u
        roads.append(
            Road(
                cl,
                p["half_width"],
                p["sidewalk"],
                p["lanes_per_dir"],
                p["lane_width"],
                p["parking"],
            )
        )
        arm_dirs.append(u)
    if is_round:
        lw = rp[0]["lane_width"]
        ring = geo.arc(np.zeros(2), ring_r, 0.0, 2 * np.pi, step=1.0)
        roads.append(Road(ring, lw / 2 + 1.0, 0.0, 1, lw, False, closed=True))

    lanes: list[Lane] = []
    entry = 0
    for i, (ai, pi) in enumerate(zip(angles, rp)):
        ui = arm_dirs[i]
        n_in = np.array([-np.sin(ai), np.cos(ai)])  # right of the inbound heading
        for k in range(pi["lanes_per_dir"]):
            d = (k + 0.5) * pi["lane_width"]
            r = np.linspace(ARM_LENGTH, r_stop, int((ARM_LENGTH - r_stop) / 2) + 1)
            inbound = r[:, None] * ui + d * n_in
            for j, (aj, pj) in enumerate(zip(angles, rp)):
                if j == i:
                    continue
                uj = arm_dirs[j]
                n_out = np.array([np.sin(aj), -np.cos(aj)])
                kk = min(k, pj["lanes_per_dir"] - 1)
                dj = (kk + 0.5) * pj["lane_width"]
                r2 = np.linspace(r_stop, ARM_LENGTH, int((ARM_LENGTH - r_stop) / 2) + 1)
                outbound = r2[:, None] * uj + dj * n_out
                if is_round:
                    dl = 0.45
                    a_in, a_out = ai + dl, aj - dl
                    if a_out <= a_in + 0.2:
                        a_out += 2 * np.pi
                    p_in = ring_r * np.array([np.cos(a_in), np.sin(a_in)])
                    p_out = ring_r * np.array([np.cos(a_out), np.sin(a_out)])
                    c1 = geo.hermite(inbound[-1], ai + np.pi, p_in, a_in + np.pi / 2)
                    ring = geo.arc(np.zeros(2), ring_r, a_in, a_out)
                    c2 = geo.hermite(p_out, a_out + np.pi / 2, outbound[0], aj)
                    path = np.concatenate([inbound, c1[1:-1], ring, c2[1:-1], outbound])
                    limit = TURN_SPEED
                else:
                    conn = geo.hermite(inbound[-1], ai + np.pi, outbound[0], aj)
                    path = np.concatenate([inbound, conn[1:-1], outbound])
                    turn = abs((aj - (ai + np.pi) + np.pi) % (2 * np.pi) - np.pi)
                    limit = URBAN_SPEED if turn < np.deg2rad(35) else TURN_SPEED
                lanes.append(Lane(path, pi["lane_width"], limit, entry))
            entry += 1
    static_extra = []
    if is_round:
        # central island: an octagon of two boxes (vegetation), radius below the ring lane
        ri = ring_r - rp[0]["lane_width"] / 2 - 1.5
        side = 2 * ri / np.sqrt(2) * 0.98
        h = float(rng.uniform(1.0, 2.5))
        static_extra.append(
            Boxes(np.zeros((2, 2)), [[side, side, h]] * 2, [0.0, np.pi / 4], [Cls.VEGETATION] * 2)
        )
    return roads, lanes, r_stop, static_extra


def _single_road_centerline(template: str, rng: np.random.Generator) -> np.ndarray:
    L = 2 * ARM_LENGTH
    if template in ("straight", "boulevard"):
        cl = np.stack([np.linspace(-L / 2, L / 2, 201), np.zeros(201)], 1)
    elif template == "curve":
        R = float(rng.uniform(45.0, 110.0))
        ang = np.deg2rad(rng.uniform(80.0, 140.0))
        arc_len = R * ang
        s1 = (L - arc_len) / 2
        a = geo.arc(np.array([0.0, R]), R, -np.pi / 2, -np.pi / 2 + ang)
        p_end, yaw_end = a[-1], ang
        first = np.stack([np.linspace(-s1, 0, 50), np.zeros(50)], 1)
        last = p_end + np.linspace(0, s1, 50)[:, None] * np.array(
            [np.cos(yaw_end), np.sin(yaw_end)]
        )
        cl = np.concatenate([first[:-1], a, last[1:]])
    elif template == "s_curve":
        R = float(rng.uniform(60.0, 120.0))
        ang = np.deg2rad(rng.uniform(30.0, 60.0))
        first = np.stack([np.linspace(-120, 0, 61), np.zeros(61)], 1)
        a1 = geo.arc(np.array([0.0, R]), R, -np.pi / 2, -np.pi / 2 + ang)
        c2 = a1[-1] + R * np.array([np.sin(ang), -np.cos(ang)])  # centre of the right-hand arc
        a2 = geo.arc(c2, R, ang + np.pi / 2, np.pi / 2)  # clockwise back to heading 0
        rest = L - 120 - 2 * R * ang
        last = a2[-1] + np.linspace(0, max(rest, 20.0), 60)[:, None] * np.array([1.0, 0.0])
        cl = np.concatenate([first[:-1], a1, a2[1:], last[1:]])
    else:  # pragma: no cover
        raise ValueError(template)
    cl = geo.resample(cl, 2.0)
    cl -= cl[len(cl) // 2]  # middle of the road at the origin
    rot = float(rng.uniform(0, 2 * np.pi))
    c, s = np.cos(rot), np.sin(rot)
    return cl @ np.array([[c, s], [-s, c]])


def _build_single(template: str, rng: np.random.Generator):
    p = _road_params(rng, 2 if template == "boulevard" else 1)
    if template == "straight":
        p["parking"], p["half_width"] = True, p["lanes_per_dir"] * p["lane_width"] + 2.3
    cl = _single_road_centerline(template, rng)
    road = Road(
        cl, p["half_width"], p["sidewalk"], p["lanes_per_dir"], p["lane_width"], p["parking"]
    )
    lanes = []
    entry = 0
    for k in range(p["lanes_per_dir"]):
        d = (k + 0.5) * p["lane_width"]
        lanes.append(Lane(geo.offset(cl, -d), p["lane_width"], URBAN_SPEED, entry))
        lanes.append(Lane(geo.offset(cl, d)[::-1].copy(), p["lane_width"], URBAN_SPEED, entry + 1))
        entry += 2
    return [road], lanes, 0.0, []


def _roadside(roads: list[Road], r_clear: float, rng: np.random.Generator):
    """Occluder candidates beside every (open) road, sidewalks and parking strips."""
    centers, sizes, yaws, classes = [], [], [], []
    near_road = []  # True for objects allowed on the sidewalk (trees, poles)
    sidewalks, parking = [], []
    for road in roads:
        if road.closed:
            continue
        cl, cum = road.centerline, geo.cumulative_length(road.centerline)
        L = cum[-1]
        for side in (-1.0, 1.0):
            sw_off = road.half_width + road.sidewalk / 2
            walk = geo.offset(cl, side * sw_off)
            sidewalks.append(walk if side < 0 else walk[::-1].copy())
            if road.parking:
                pk = geo.offset(cl, side * (road.half_width - 1.15))
                parking.append((pk, 0.0 if side < 0 else np.pi))
            # buildings / walls / hedges along the frontage
            s = r_clear + road.sidewalk + float(rng.uniform(0, 6))
            while s < L - 5:
                front = float(rng.uniform(8.0, 30.0))
                kind = rng.choice(["building", "building", "building", "wall", "hedge", "none"])
                if kind != "none":
                    (xy,), (yaw,) = geo.interpolate(cl, cum, np.array([s + front / 2]))
                    n = np.array([-np.sin(yaw), np.cos(yaw)]) * side
                    setback = float(rng.uniform(0.5, 5.0))
                    if kind == "building":
                        depth, h, c = (
                            float(rng.uniform(8, 20)),
                            float(rng.uniform(5, 22)),
                            Cls.BUILDING,
                        )
                    elif kind == "wall":
                        depth, h, c = (
                            float(rng.uniform(0.25, 0.5)),
                            float(rng.uniform(1.2, 2.6)),
                            Cls.WALL,
                        )
                    else:
                        depth, h, c = (
                            float(rng.uniform(1.0, 2.5)),
                            float(rng.uniform(1.0, 2.2)),
                            Cls.VEGETATION,
                        )
                    off = road.half_width + road.sidewalk + setback + depth / 2
                    centers.append(xy + off * n)
                    sizes.append([front, depth, h])
                    yaws.append(yaw)
                    classes.append(c)
                    near_road.append(False)
                s += front + float(rng.uniform(0.5, 8.0))
            # trees and poles near the kerb
            s = r_clear + float(rng.uniform(0, 10))
            tree_p = float(rng.uniform(0.0, 0.8))
            while s < L - 2:
                r = rng.random()
                (xy,), (yaw,) = geo.interpolate(cl, cum, np.array([s]))
                n = np.array([-np.sin(yaw), np.cos(yaw)]) * side
                if r < tree_p:
                    w = float(rng.uniform(0.8, 1.6))
                    centers.append(xy + (road.half_width + 0.9) * n)
                    sizes.append([w, w, float(rng.uniform(3.0, 8.0))])
                    yaws.append(yaw)
                    classes.append(Cls.VEGETATION)
                    near_road.append(True)
                elif r < tree_p + 0.15:
                    centers.append(xy + (road.half_width + 0.4) * n)
                    sizes.append([0.25, 0.25, float(rng.uniform(4.0, 8.0))])
                    yaws.append(yaw)
                    classes.append(Cls.POLE)
                    near_road.append(True)
                s += float(rng.uniform(7.0, 16.0))
    boxes = Boxes(
        np.array(centers).reshape(-1, 2),
        np.array(sizes).reshape(-1, 3),
        np.array(yaws),
        np.array(classes),
    )
    return boxes, np.array(near_road, dtype=bool), sidewalks, parking


def _reject_intruders(boxes: Boxes, near_road: np.ndarray, roads: list[Road]) -> np.ndarray:
    """Keep-mask: a box must not reach into any road (sidewalk objects) or road + sidewalk (others)."""
    if len(boxes) == 0:
        return np.zeros(0, dtype=bool)
    u = np.linspace(-0.5, 0.5, 5)
    gu, gv = np.meshgrid(u, u, indexing="ij")
    local = np.stack([gu.ravel(), gv.ravel()], 1)  # 25 sample points over the footprint
    pl = local[None] * boxes.size[:, None, :2]
    c, s = np.cos(boxes.yaw)[:, None], np.sin(boxes.yaw)[:, None]
    pts = (
        np.stack([c * pl[..., 0] - s * pl[..., 1], s * pl[..., 0] + c * pl[..., 1]], -1)
        + boxes.center[:, None]
    )
    flat = pts.reshape(-1, 2)
    margin = np.full(len(flat), np.inf)
    margin_side = np.full(len(flat), np.inf)
    for road in roads:
        d = geo.distance_to_segments(flat, geo.segments(road.centerline))
        margin = np.minimum(margin, d - road.half_width - road.sidewalk)
        margin_side = np.minimum(margin_side, d - road.half_width)
    m = margin.reshape(len(boxes), -1).min(1)
    ms = margin_side.reshape(len(boxes), -1).min(1)
    return np.where(near_road, ms > 0.15, m > 0.3)


def build_world(template: str, seed: int) -> World:
    """Build the static world of road ``template`` (one of :data:`TEMPLATES`) with random
    variations drawn from ``seed`` (lane count and width, parking, sidewalk width, angles,
    radii, occluders). Deterministic for ``(template, seed)``."""
    _check_template(template)
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"build_world: seed must be a non-negative int, got {seed!r}")
    rng = _rng(template, int(seed))
    if template in ("straight", "boulevard", "curve", "s_curve"):
        roads, lanes, r_clear, extra = _build_single(template, rng)
    else:
        roads, lanes, r_clear, extra = _build_junction(template, rng)
    cand, near_road, sidewalks, parking = _roadside(roads, r_clear, rng)
    keep = _reject_intruders(cand, near_road, roads)
    static = Boxes.concat([cand.subset(keep), *extra])
    static.ids = STATIC_ID0 + np.arange(len(static))
    return World(
        template=template,
        seed=int(seed),
        static=static,
        lanes=lanes,
        sidewalks=sidewalks,
        roads=roads,
        parking=parking,
        center=np.zeros(2),
        junction_radius=r_clear,
    )
