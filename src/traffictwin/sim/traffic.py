"""Scenarios: random traffic in a :class:`~traffictwin.sim.world.World`, two subject vehicles that meet.

:func:`sample_scenario` draws, from a seed:

* moving vehicles (cars, trucks, motorcycles) in platoons on every entry lane. All vehicles of
  one entry lane share one speed, so platoons keep their gaps; every platoon picks one exit
  (route) of its entry. A vehicle exists while ``0 <= s <= route length`` (it enters/leaves at
  the template's border, ~200 m from the centre);
* parked cars in the parking strips (not within ``junction_radius + 10 m`` of the centre);
* pedestrians walking along the sidewalks, back and forth (they turn at the ends);
* two subject vehicles (ids 0 and 1, cars) that meet near the centre: at every one of the
  ``n_encounters`` encounter times (spaced ``encounter_spacing`` s around ``t_meet``) both
  exist and their distance lies within ``meet_distance``. Their exact world poses come from
  :meth:`Scenario.subject_pose`.

``Scenario.agents_at(t)`` returns every agent present at time ``t`` (s) as oriented boxes with
class labels, world-frame velocities (m/s) and stable ids: subjects 0, 1; moving vehicles from 2;
then parked cars; then pedestrians. Static occluders are in ``world.static`` (ids >= 1e6).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from traffictwin.sim import geometry as geo
from traffictwin.sim.scene import Boxes, Cls
from traffictwin.sim.world import World

# length, width, height ranges (m)
DIMS = {
    Cls.CAR: ((3.8, 5.0), (1.70, 1.95), (1.40, 1.70)),
    Cls.TRUCK: ((7.0, 12.0), (2.40, 2.55), (3.00, 3.80)),
    Cls.MOTORCYCLE: ((2.0, 2.3), (0.70, 0.90), (1.30, 1.50)),
    Cls.PEDESTRIAN: ((0.45, 0.65), (0.50, 0.70), (1.55, 1.95)),
}
SUBJECT_SIZE = (4.8, 1.9, 1.5)  # the research vehicle (m)

DEFAULT_DENSITY = dict(
    platoon_gap=(25.0, 120.0),  # m between platoons (divided by the scenario's density factor)
    platoon_size=(1, 5),  # vehicles per platoon (inclusive)
    truck_frac=0.12,
    moto_frac=0.08,
    parked_prob=0.55,  # probability that a parking slot is taken
    pedestrians_per_km=40.0,  # per sidewalk km
    density_scale=(0.5, 1.5),  # per-scenario factor on all densities
)


def _dims(rng: np.random.Generator, cls: np.ndarray) -> np.ndarray:
    out = np.zeros((len(cls), 3))
    for c, rngs in DIMS.items():
        m = cls == c
        for k in range(3):
            out[m, k] = rng.uniform(*rngs[k], size=int(m.sum()))
    return out


class _LaneTable:
    """All lanes concatenated for vectorised interpolation of many agents on many lanes."""

    def __init__(self, polylines: list[np.ndarray]) -> None:
        self.lengths = np.array([geo.cumulative_length(p)[-1] for p in polylines])
        starts, pts, gcum, off = [], [], [], 0.0
        n = 0
        self.offsets = np.zeros(len(polylines))
        for i, p in enumerate(polylines):
            cum = geo.cumulative_length(p)
            starts.append(n)
            pts.append(p)
            gcum.append(cum + off)
            self.offsets[i] = off
            off += cum[-1] + 10.0
            n += len(p)
        self.starts = np.array(starts)
        self.ends = self.starts + np.array([len(p) for p in polylines])  # exclusive
        self.pts = np.concatenate(pts) if pts else np.zeros((0, 2))
        self.gcum = np.concatenate(gcum) if gcum else np.zeros(0)

    def pose(self, lane: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """xy (K, 2) and heading (K,) at arc length ``s`` (clipped) on ``lane`` (indices)."""
        s = np.clip(s, 0.0, self.lengths[lane])
        g = self.offsets[lane] + s
        idx = np.searchsorted(self.gcum, g, side="right") - 1
        idx = np.clip(idx, self.starts[lane], self.ends[lane] - 2)
        seg = self.pts[idx + 1] - self.pts[idx]
        seg_len = np.maximum(self.gcum[idx + 1] - self.gcum[idx], 1e-12)
        f = ((g - self.gcum[idx]) / seg_len)[:, None]
        return self.pts[idx] + f * seg, np.arctan2(seg[:, 1], seg[:, 0])


@dataclass
class Scenario:
    """Traffic in ``world`` (see module docstring). Arrays per agent group; times in s."""

    world: World
    seed: int
    # moving vehicles (subjects first: index 0 and 1)
    veh_lane: np.ndarray
    veh_s0: np.ndarray  # arc length at t = 0 (m)
    veh_speed: np.ndarray  # m/s
    veh_size: np.ndarray
    veh_cls: np.ndarray
    veh_ids: np.ndarray
    parked: Boxes
    # pedestrians on sidewalks
    ped_walk: np.ndarray
    ped_s0: np.ndarray
    ped_speed: np.ndarray  # signed m/s along the sidewalk polyline
    ped_size: np.ndarray
    ped_ids: np.ndarray
    t_meet: float
    encounter_times: np.ndarray

    def __post_init__(self) -> None:
        self._lanes = _LaneTable([ln.centerline for ln in self.world.lanes])
        self._walks = _LaneTable(self.world.sidewalks) if self.world.sidewalks else None

    @property
    def subject_ids(self) -> tuple[int, int]:
        return (int(self.veh_ids[0]), int(self.veh_ids[1]))

    def _vehicles(self, t: float) -> Boxes:
        s = self.veh_s0 + self.veh_speed * t
        present = (s >= 0) & (s <= self._lanes.lengths[self.veh_lane])
        lane, s = self.veh_lane[present], s[present]
        xy, yaw = self._lanes.pose(lane, s)
        v = self.veh_speed[present][:, None] * np.stack([np.cos(yaw), np.sin(yaw)], 1)
        return Boxes(
            xy,
            self.veh_size[present],
            yaw,
            self.veh_cls[present],
            velocity=v,
            ids=self.veh_ids[present],
        )

    def _pedestrians(self, t: float) -> Boxes:
        if self._walks is None or len(self.ped_ids) == 0:
            return Boxes.empty()
        L = self._walks.lengths[self.ped_walk]
        u = np.mod(self.ped_s0 + self.ped_speed * t, 2 * L)
        back = u > L
        s = np.where(back, 2 * L - u, u)
        xy, yaw = self._walks.pose(self.ped_walk, s)
        sign = np.where(back, -1.0, 1.0) * np.sign(self.ped_speed)
        yaw = np.where(sign < 0, yaw + np.pi, yaw)
        v = np.abs(self.ped_speed)[:, None] * np.stack([np.cos(yaw), np.sin(yaw)], 1)
        n = len(self.ped_ids)
        return Boxes(
            xy, self.ped_size, yaw, np.full(n, Cls.PEDESTRIAN), velocity=v, ids=self.ped_ids
        )

    def agents_at(self, t: float, exclude_ids: tuple[int, ...] | list[int] = ()) -> Boxes:
        """Every agent present at time ``t`` (s): subjects, moving vehicles, parked cars, pedestrians."""
        b = Boxes.concat([self._vehicles(float(t)), self.parked, self._pedestrians(float(t))])
        if len(exclude_ids):
            b = b.subset(~np.isin(b.ids, np.asarray(exclude_ids)))
        return b

    def subject_pose(self, k: int, t: float) -> np.ndarray:
        """Exact world pose (x, y, yaw) (m, rad) of subject ``k`` (0 or 1) at time ``t`` (s)."""
        if k not in (0, 1):
            raise ValueError(f"subject index must be 0 or 1, got {k}")
        s = self.veh_s0[k] + self.veh_speed[k] * t
        lane = self.veh_lane[k : k + 1]
        if not 0 <= s <= self._lanes.lengths[lane[0]]:
            raise ValueError(f"subject {k} is not on its route at t={t} s (arc length {s:.1f} m)")
        xy, yaw = self._lanes.pose(lane, np.array([s]))
        return np.array([xy[0, 0], xy[0, 1], yaw[0]])

    def subject_size(self, k: int) -> np.ndarray:
        """Length, width, height (m) of subject ``k``."""
        return self.veh_size[k].copy()


def _platoons(
    rng, world: World, lane_speed: dict[int, float], horizon: float, dens: dict, scale: float
):
    """Moving vehicles in platoons on every entry; returns (lane, s0, speed, cls)."""
    lanes_by_entry: dict[int, list[int]] = {}
    for i, ln in enumerate(world.lanes):
        lanes_by_entry.setdefault(ln.entry, []).append(i)
    out_lane, out_s, out_v, out_cls = [], [], [], []
    for entry in sorted(lanes_by_entry):
        routes = lanes_by_entry[entry]
        v = lane_speed[entry]
        s_max = max(world.lanes[r].length for r in routes)
        s_min = -v * horizon
        head = s_max - float(rng.uniform(0, dens["platoon_gap"][1] / scale))
        while head > s_min:
            n = int(rng.integers(dens["platoon_size"][0], dens["platoon_size"][1] + 1))
            route = routes[int(rng.integers(len(routes)))]
            r = rng.random(n)
            cls = np.where(
                r < dens["truck_frac"],
                Cls.TRUCK,
                np.where(r < dens["truck_frac"] + dens["moto_frac"], Cls.MOTORCYCLE, Cls.CAR),
            )
            s = head
            for c in cls:
                out_lane.append(route)
                out_s.append(s)
                out_v.append(v)
                out_cls.append(int(c))
                length = 12.0 if c == Cls.TRUCK else 5.0
                s -= length + 2.0 + float(rng.uniform(0.8, 2.0)) * v  # 0.8..2 s time headway
            head = s - float(rng.uniform(*dens["platoon_gap"])) / scale
    return (
        np.array(out_lane, dtype=np.int64),
        np.array(out_s),
        np.array(out_v),
        np.array(out_cls, dtype=np.int64),
    )


def _choose_subjects(
    rng, world: World, lane_speed, times: np.ndarray, meet_distance, near_center: float
):
    """Lane, arc length at t=0 and speed of both subjects such that they meet at every time in ``times``."""
    table = _LaneTable([ln.centerline for ln in world.lanes])
    cand_lane, cand_s = [], []
    for i, ln in enumerate(world.lanes):
        s = np.arange(2.0, ln.length - 2.0, 2.0)
        cand_lane.append(np.full(len(s), i))
        cand_s.append(s)
    lane = np.concatenate(cand_lane)
    s_ref = np.concatenate(cand_s)  # arc length at t_ref = times[0]
    speed = np.array([lane_speed[world.lanes[i].entry] for i in lane])
    L = table.lengths[lane]
    # positions of every candidate at every encounter time
    pos = []
    valid = np.ones(len(lane), dtype=bool)
    for t in times:
        s = s_ref + speed * (t - times[0])
        valid &= (s >= 0) & (s <= L)
        xy, _ = table.pose(lane, s)
        pos.append(xy)
    pos = np.stack(pos, 1)  # (C, T, 2)
    first = valid & (np.linalg.norm(pos - world.center, axis=2).max(1) <= near_center)
    if not first.any():
        first = valid
    order = rng.permutation(np.flatnonzero(first))
    entries = np.array([world.lanes[i].entry for i in lane])
    for a in order[:200]:
        d = np.linalg.norm(pos - pos[a][None], axis=2)  # (C, T)
        ok = valid & (d.min(1) >= meet_distance[0]) & (d.max(1) <= meet_distance[1])
        ok &= ~((entries == entries[a]) & (np.abs(s_ref - s_ref[a]) < 12.0))
        if ok.any():
            b = int(rng.choice(np.flatnonzero(ok)))
            return [
                (int(lane[a]), float(s_ref[a]), float(speed[a])),
                (int(lane[b]), float(s_ref[b]), float(speed[b])),
            ]
    raise RuntimeError(
        f"no pair of subject positions meets within {meet_distance} m in template {world.template}"
    )


def _check_density(density: dict[str, float], n_encounters: int) -> dict:
    """:data:`DEFAULT_DENSITY` with the overrides; ValueError for unknown keys or no encounter."""
    unknown = set(density) - set(DEFAULT_DENSITY)
    if unknown:
        raise ValueError(
            f"sample_scenario: unknown density parameter(s) {sorted(unknown)}; expected {sorted(DEFAULT_DENSITY)}"
        )
    if n_encounters < 1:
        raise ValueError(f"sample_scenario: n_encounters must be >= 1, got {n_encounters}")
    return {**DEFAULT_DENSITY, **density}


def _lane_speeds(rng: np.random.Generator, world: World) -> dict[int, float]:
    """One speed (m/s) per entry: 65-100 % of the lowest speed limit of its lanes."""
    entries = sorted({ln.entry for ln in world.lanes})
    lane_speed = {}
    for e in entries:
        limit = min(ln.speed_limit for ln in world.lanes if ln.entry == e)
        lane_speed[e] = float(rng.uniform(0.65, 1.0) * limit)
    return lane_speed


@dataclass(frozen=True)
class _Subjects:
    """Both subjects' lanes (2,), arc lengths at t = 0 (2,; m) and speeds (2,; m/s)."""

    lane: np.ndarray
    s0: np.ndarray
    speed: np.ndarray

    def xy(self, table: _LaneTable, k: int, t: float) -> np.ndarray:
        """World xy (1, 2) of subject ``k`` at time ``t`` (s)."""
        return table.pose(self.lane[k : k + 1], self.s0[k : k + 1] + self.speed[k] * t)[0]


def _clear_of_subjects(
    table: _LaneTable,
    entry_of: np.ndarray,
    subj: _Subjects,
    times: np.ndarray,
    traffic: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
) -> np.ndarray:
    """Mask of the traffic (lane, s0, speed, size) that never overlaps a subject: not on a
    subject's entry lane close in arc length (same speed => forever), and never closer than
    8 m to a subject at an encounter time."""
    lane, s0, v, size = traffic
    keep = np.ones(len(lane), dtype=bool)
    for k in range(2):
        same = entry_of[lane] == entry_of[subj.lane[k]]
        keep &= ~(same & (np.abs(s0 - subj.s0[k]) < (size[:, 0] + SUBJECT_SIZE[0]) / 2 + 3.0))
        for t in times:
            s = s0 + v * t
            xy, _ = table.pose(lane, s)
            sxy = subj.xy(table, k, t)
            present = (s >= 0) & (s <= table.lengths[lane])
            keep &= ~(present & (np.linalg.norm(xy - sxy, axis=1) < 8.0))
    return keep


def _parked_cars(rng: np.random.Generator, world: World, dens: dict, scale: float) -> Boxes:
    """Cars in the parking strips, each slot taken with probability ``parked_prob * scale``, none
    within ``junction_radius + 10 m`` of the centre."""
    pc, psz, pyaw = [], [], []
    for poly, yaw_off in world.parking:
        cum = geo.cumulative_length(poly)
        s = float(rng.uniform(0, 4))
        while s < cum[-1] - 3:
            length = float(rng.uniform(*DIMS[Cls.CAR][0]))
            slot = length + float(rng.uniform(0.8, 2.5))
            if rng.random() < min(1.0, dens["parked_prob"] * scale):
                (xy,), (yaw,) = geo.interpolate(poly, cum, np.array([s + slot / 2]))
                if np.linalg.norm(xy - world.center) > world.junction_radius + 10.0:
                    pc.append(xy)
                    psz.append(
                        [length, rng.uniform(*DIMS[Cls.CAR][1]), rng.uniform(*DIMS[Cls.CAR][2])]
                    )
                    pyaw.append(yaw + yaw_off)
            s += slot
    return Boxes(
        np.array(pc).reshape(-1, 2),
        np.array(psz).reshape(-1, 3),
        np.array(pyaw),
        np.full(len(pc), Cls.CAR),
    )


def _parked_clear_of_subjects(
    parked: Boxes, table: _LaneTable, subj: _Subjects, times: np.ndarray
) -> Boxes:
    """Parked cars overlapping a subject at an encounter time are dropped (subjects may use a
    lane next to the parking strip but never overlap it; this guards connectors near junctions)."""
    if not len(parked):
        return parked
    keep = np.ones(len(parked), dtype=bool)
    for k in range(2):
        for t in times:
            keep &= np.linalg.norm(parked.center - subj.xy(table, k, t), axis=1) > 6.0
    return parked.subset(keep)


def _walkers(
    rng: np.random.Generator, world: World, dens: dict, scale: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pedestrians on the sidewalks (Poisson count per km): walk index, arc length at t = 0 (m),
    signed speed (m/s) and size (m)."""
    walks = world.sidewalks
    wl = np.array([geo.cumulative_length(w)[-1] for w in walks]) if walks else np.zeros(0)
    n_ped = (
        int(rng.poisson(dens["pedestrians_per_km"] * scale * wl.sum() / 1000.0)) if len(wl) else 0
    )
    ped_walk = (
        rng.choice(len(wl), size=n_ped, p=wl / wl.sum()).astype(np.int64)
        if n_ped
        else np.zeros(0, np.int64)
    )
    ped_s0 = rng.uniform(0, 1, n_ped) * wl[ped_walk] if n_ped else np.zeros(0)
    ped_speed = rng.uniform(0.8, 1.7, n_ped) * rng.choice([-1.0, 1.0], n_ped)
    ped_size = _dims(rng, np.full(n_ped, Cls.PEDESTRIAN))
    return ped_walk, ped_s0, ped_speed, ped_size


def sample_scenario(
    world: World,
    seed: int,
    *,
    t_meet: float = 10.0,
    n_encounters: int = 4,
    encounter_spacing: float = 0.5,
    meet_distance: tuple[float, float] = (6.0, 40.0),
    horizon: float = 30.0,
    **density: float,
) -> Scenario:
    """Random traffic in ``world`` from ``seed`` (see module docstring).

    ``t_meet`` (s): centre of the encounter window; ``n_encounters`` times ``encounter_spacing``
    (s) apart around it; ``meet_distance`` (m): allowed subject distance at those times;
    ``horizon`` (s): vehicles are seeded so that traffic flows over ``[0, horizon]``.
    ``density``: overrides of :data:`DEFAULT_DENSITY` (unknown keys raise ``ValueError``).
    """
    dens = _check_density(density, n_encounters)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 7002]))
    scale = float(rng.uniform(*dens["density_scale"]))
    lane_speed = _lane_speeds(rng, world)
    times = t_meet + (np.arange(n_encounters) - (n_encounters - 1) / 2) * encounter_spacing
    near = max(50.0, world.junction_radius + 30.0)
    chosen = _choose_subjects(rng, world, lane_speed, times, meet_distance, near)

    lane, s0, v, cls = _platoons(rng, world, lane_speed, horizon, dens, scale)
    size = _dims(rng, cls)
    # subjects as vehicles 0 and 1 (s0 at t = 0)
    sv = np.array([x[2] for x in chosen])
    subj = _Subjects(
        np.array([x[0] for x in chosen]), np.array([x[1] for x in chosen]) - sv * times[0], sv
    )
    table = _LaneTable([ln.centerline for ln in world.lanes])
    entry_of = np.array([ln.entry for ln in world.lanes])
    keep = _clear_of_subjects(table, entry_of, subj, times, (lane, s0, v, size))
    lane, s0, v, cls, size = lane[keep], s0[keep], v[keep], cls[keep], size[keep]
    veh_lane = np.concatenate([subj.lane, lane]).astype(np.int64)
    veh_ids = np.arange(len(veh_lane), dtype=np.int64)
    next_id = len(veh_lane)

    parked = _parked_clear_of_subjects(_parked_cars(rng, world, dens, scale), table, subj, times)
    parked.ids = next_id + np.arange(len(parked))
    next_id += len(parked)

    ped_walk, ped_s0, ped_speed, ped_size = _walkers(rng, world, dens, scale)
    return Scenario(
        world=world,
        seed=int(seed),
        veh_lane=veh_lane,
        veh_s0=np.concatenate([subj.s0, s0]),
        veh_speed=np.concatenate([subj.speed, v]),
        veh_size=np.concatenate([np.array([SUBJECT_SIZE, SUBJECT_SIZE]), size]).reshape(-1, 3),
        veh_cls=np.concatenate([[Cls.CAR, Cls.CAR], cls]).astype(np.int64),
        veh_ids=veh_ids,
        parked=parked,
        ped_walk=ped_walk,
        ped_s0=ped_s0,
        ped_speed=ped_speed,
        ped_size=ped_size,
        ped_ids=next_id + np.arange(len(ped_walk), dtype=np.int64),
        t_meet=float(t_meet),
        encounter_times=times,
    )
