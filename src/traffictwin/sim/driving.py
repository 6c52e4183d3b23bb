"""Driving sequences of a stereo-equipped subject vehicle through the shared world (paper 003, 3.2).

One *sequence* = one scenario: a world (:func:`traffictwin.sim.world.build_world`) and its
traffic (:func:`traffictwin.sim.traffic.sample_scenario`), plus a subject vehicle that drives
along one lane route with an Intelligent-Driver-Model (IDM) speed controller and the vehicles
this module inserts on its lane to produce a *situation*:

========================  ==============================================================
``free``                  no vehicle on the subject's entry lane; cruising 8-25 m/s
``follow_far``            lead vehicle, desired time gap 1.4-3.5 s
``follow_close``          lead vehicle, desired time gap 0.5-1.5 s
``approach_slow``         subject (12-25 m/s) closes in on a slower lead (3-10 m/s)
``approach_stopped``      stopped vehicle ahead (queue / red light); subject brakes to a stop
``stop_and_go``           both at standstill, the lead drives off, the subject follows
``cut_in``                a vehicle from the neighbouring lane merges in front of the subject
``pedestrian``            a pedestrian steps into the lane 0.8-3.5 s ahead; the subject brakes late
========================  ==============================================================

Intersections, oncoming traffic, parked cars and pedestrians on the sidewalks come from the
shared world and its scenario (templates are drawn per sequence). The situation of sequence
``i`` is drawn from the configured weights by :func:`draw_situation`, from ``(seed, i)`` alone,
so that splits can be stratified by situation before anything is simulated; the roadside
parking density (the probability that a parking slot is taken) is drawn per sequence from
``parked_prob``. Every frame carries the subject's path ahead (its lane's centreline) and lane
width: the driving corridor of the risk label (:mod:`traffictwin.risk.metric`).

Everything is deterministic for ``(seed, index)``. Units: m, s, m/s, rad.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from traffictwin.sim.scene import Boxes, Cls
from traffictwin.sim.traffic import SUBJECT_SIZE, sample_scenario
from traffictwin.sim.world import TEMPLATES, World, build_world

SITUATIONS = (
    "free",
    "follow_far",
    "follow_close",
    "approach_slow",
    "approach_stopped",
    "stop_and_go",
    "cut_in",
    "pedestrian",
)
FAULTS = ("none", "delay", "vertical")
INSERTED_ID0 = 900_000  # ids of vehicles this module inserts
PATH_AHEAD = 60.0  # m of the subject's lane recorded per frame (the corridor; >= the grid's reach)
PATH_STEP = 0.5  # m between path points


def draw_situation(seed: int, index: int, weights: tuple[tuple[str, float], ...]) -> str:
    """The situation of sequence ``index`` (deterministic for ``(seed, index)``), drawn with the
    relative ``weights`` ((name, weight >= 0), ...; names from :data:`SITUATIONS`)."""
    names = [n for n, _ in weights]
    w = np.array([float(x) for _, x in weights])
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), int(index), 3004]))
    return str(names[int(rng.choice(len(names), p=w / w.sum()))])


# the lowest top speed (m/s) the situations can be drawn with: 'approach_slow' draws the subject's
# speed in [12, max_speed], 'follow_*' a lead in [6, max_speed - 2], others in [8, max_speed]
MIN_TOP_SPEED = 12.0


@dataclass(frozen=True)
class DrivingConfig:
    """fps: frame rate (Hz); frames: frames per sequence; warmup: simulated seconds before the
    first frame; sim_dt: integration step (s); max_speed (m/s); situations: relative weights
    ((name, weight), ...) of the situations (:data:`SITUATIONS`); parked_prob: range of the
    per-sequence probability that a parking slot is taken; templates: world templates to draw
    from (empty = all);
    fault_delay/fault_vertical: share of frames with a delayed right image / vertical
    misalignment; delay: right-image delay (s); vertical_px: misalignment range (px)."""

    fps: float = 4.0
    frames: int = 20
    warmup: float = 3.0
    sim_dt: float = 0.05
    max_speed: float = 25.0
    situations: tuple[tuple[str, float], ...] = tuple((n, 1.0) for n in SITUATIONS)
    parked_prob: tuple[float, float] = (0.0, 0.9)
    templates: tuple[str, ...] = ()
    fault_delay: float = 0.03
    fault_vertical: float = 0.03
    delay: float = 0.088
    vertical_px: tuple[float, float] = (4.0, 12.0)

    def __post_init__(self) -> None:
        if self.fps <= 0 or self.frames < 1 or self.sim_dt <= 0 or self.warmup < 0:
            raise ValueError("driving: fps and sim_dt must be > 0, frames >= 1, warmup >= 0")
        if not self.max_speed >= MIN_TOP_SPEED:
            raise ValueError(
                f"driving: max_speed must be >= {MIN_TOP_SPEED} m/s (the situations draw speeds "
                f"up to it from at least 12 m/s), got {self.max_speed}"
            )
        unknown = [n for n, _ in self.situations if n not in SITUATIONS]
        if unknown:
            raise ValueError(
                f"driving: unknown situations {unknown}; expected some of {list(SITUATIONS)}"
            )
        w = [float(x) for _, x in self.situations]
        if not w or min(w) < 0 or sum(w) <= 0:
            raise ValueError(
                f"driving: situation weights must be >= 0 with a positive sum, got {w}"
            )
        lo, hi = self.parked_prob
        if not 0 <= lo <= hi <= 1:
            raise ValueError(f"driving: parked_prob must be [low, high] in [0, 1], got {[lo, hi]}")
        if (
            self.fault_delay < 0
            or self.fault_vertical < 0
            or self.fault_delay + self.fault_vertical > 1
        ):
            raise ValueError("driving: fault_delay and fault_vertical must be >= 0 and sum to <= 1")
        bad = [t for t in self.templates if t not in TEMPLATES]
        if bad:
            raise ValueError(
                f"driving: unknown templates {bad}; expected some of {list(TEMPLATES)}"
            )


@dataclass
class Frame:
    """One recorded instant: time (s), subject pose (x, y, yaw) and speed (m/s), the scene
    (static + agents, world frame) for the left image, the scene/pose for the right image
    (differs for a ``delay`` fault), the vertical offset of the right image (px), the fault,
    and the subject's path ahead (K, 2; world, m, from its reference point along its lane) and
    lane width (m)."""

    t: float
    pose: np.ndarray
    speed: float
    boxes: Boxes
    pose_right: np.ndarray
    boxes_right: Boxes
    right_cy_offset: float
    fault: str
    path: np.ndarray
    lane_width: float


@dataclass
class Sequence:
    """A driven sequence: its world, situation name, template, and frames."""

    index: int
    world: World
    situation: str
    frames: list[Frame] = field(default_factory=list)


# ------------------------------------------------------------------------------------------------
class _Track:
    """An inserted agent: arc length on the subject's lane + lateral offset over the time grid."""

    def __init__(
        self, ident: int, cls: int, size: np.ndarray, s: np.ndarray, lat: np.ndarray
    ) -> None:
        self.ident, self.cls, self.size, self.s, self.lat = ident, cls, size, s, lat


def _idm(
    v: float,
    v0: float,
    gap: float,
    dv: float,
    T: float,
    a: float = 2.0,
    b: float = 3.0,
    s0: float = 2.0,
) -> float:
    """IDM acceleration (m/s^2) at speed v with desired speed v0, bumper gap (m), approach rate dv."""
    s_star = s0 + max(0.0, v * T + v * dv / (2.0 * np.sqrt(a * b)))
    free = 1.0 - (v / max(v0, 0.1)) ** 4
    inter = (s_star / max(gap, 0.1)) ** 2 if np.isfinite(gap) else 0.0
    return float(np.clip(a * (free - inter), -9.0, a))


def _pose_on(world: World, lane: int, s: np.ndarray, lat: np.ndarray | float = 0.0) -> np.ndarray:
    """Poses (K, 3) at arc lengths s on ``lane`` shifted ``lat`` m to the left."""
    p = world.lanes[lane].pose_at(np.atleast_1d(s))
    lat = np.broadcast_to(np.asarray(lat, float), (len(p),))
    p[:, 0] -= np.sin(p[:, 2]) * lat
    p[:, 1] += np.cos(p[:, 2]) * lat
    return p


def _rel(pose: np.ndarray, xy: np.ndarray) -> np.ndarray:
    c, s = np.cos(pose[2]), np.sin(pose[2])
    d = xy - pose[:2]
    return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], 1)


def generate_sequence(seed: int, index: int, cfg: DrivingConfig) -> Sequence:
    """Simulate sequence ``index`` of the dataset with ``seed`` (deterministic for the pair)."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), int(index), 3003]))
    templates = cfg.templates or TEMPLATES
    template = str(templates[int(rng.integers(len(templates)))])
    world = build_world(template, int(rng.integers(0, 2**31 - 1)))
    parked = float(rng.uniform(*cfg.parked_prob))
    scen = sample_scenario(world, int(rng.integers(0, 2**31 - 1)), parked_prob=parked)
    situation = draw_situation(seed, index, cfg.situations)

    duration = cfg.warmup + cfg.frames / cfg.fps + 0.5
    n = int(np.ceil(duration / cfg.sim_dt)) + 1
    times = np.arange(n) * cfg.sim_dt
    t_start = float(rng.uniform(2.0, 14.0))  # scenario time of the sequence start
    lane = int(rng.integers(len(world.lanes)))
    L = world.lanes[lane].length
    lw = float(world.lanes[lane].width)
    ahead_needed = cfg.max_speed * duration + 60.0
    s_sub0 = float(rng.uniform(10.0, max(12.0, L - ahead_needed)))

    # situation parameters: subject desired speed v_des, initial speed v_init, desired gap T;
    # inserted lead: initial gap, speed profile
    T = float(rng.uniform(1.0, 1.8))
    s0, b = 2.0, 3.0  # IDM standstill gap (m) and comfortable deceleration (m/s^2)
    v_des = float(rng.uniform(8.0, cfg.max_speed))
    v_init = v_des * float(rng.uniform(0.6, 1.0))
    lead: dict | None = None
    cut: dict | None = None
    ped: dict | None = None
    if situation == "follow_far":
        T = float(rng.uniform(1.3, 3.0))
        v_l = float(rng.uniform(6.0, cfg.max_speed - 2))
        v_des, v_init = v_l + 3.0, v_l
        lead = dict(gap=2.0 + T * v_l * float(rng.uniform(0.9, 1.2)), v=np.full(n, v_l))
    elif situation == "follow_close":
        T = float(rng.uniform(0.4, 1.2))
        s0 = float(rng.uniform(1.0, 2.0))
        v_l = float(rng.uniform(5.0, cfg.max_speed - 2))
        v_des, v_init = v_l + 3.0, v_l
        lead = dict(gap=2.0 + T * v_l * float(rng.uniform(0.8, 1.1)), v=np.full(n, v_l))
    elif situation == "approach_slow":
        v_l = float(rng.uniform(3.0, 10.0))
        v_des = v_init = float(rng.uniform(12.0, cfg.max_speed))
        T = float(rng.uniform(0.4, 1.0))
        b = float(rng.uniform(3.0, 6.0))
        lead = dict(gap=float(rng.uniform(25.0, 70.0)), v=np.full(n, v_l))
    elif situation == "approach_stopped":
        v_des = v_init = float(rng.uniform(8.0, 20.0))
        T = float(rng.uniform(0.4, 1.0))
        b = float(rng.uniform(3.0, 6.0))  # late braking
        lead = dict(gap=float(rng.uniform(20.0, 60.0)), v=np.zeros(n))
    elif situation == "stop_and_go":
        v_init, v_des = 0.0, float(rng.uniform(8.0, 16.0))
        T = float(rng.uniform(0.4, 1.0))
        s0 = float(rng.uniform(1.0, 2.0))
        t_go = cfg.warmup + float(rng.uniform(0.0, 2.5))
        acc = float(rng.uniform(1.0, 2.5))
        lead = dict(gap=float(rng.uniform(2.0, 4.0)), v=np.clip((times - t_go) * acc, 0.0, v_des))
    elif situation == "cut_in":
        v_des = v_init = float(rng.uniform(8.0, cfg.max_speed))
        T = float(rng.uniform(1.2, 1.8))
        side = float(rng.choice([-1.0, 1.0]))
        t_c = cfg.warmup + float(rng.uniform(0.0, cfg.frames / cfg.fps * 0.5))
        cut = dict(
            gap=float(rng.uniform(2.0, 12.0)),
            v=v_init * float(rng.uniform(0.75, 1.15)),
            side=side * lw,
            t_c=t_c,
            dur=float(rng.uniform(1.5, 3.0)),
        )
    elif situation == "pedestrian":
        v_des = v_init = float(rng.uniform(6.0, 14.0))
        T = float(rng.uniform(0.5, 1.0))
        b = float(
            rng.uniform(4.0, 7.0)
        )  # the driver reacts late, once the pedestrian is in the lane
        # the pedestrian steps into the lane at t_enter, when the (still unbraked) subject is
        # tau seconds away from it
        t_enter = cfg.warmup + float(rng.uniform(-0.5, 0.8)) * cfg.frames / cfg.fps
        tau = float(rng.uniform(0.8, 3.5))
        ped = dict(
            dist=v_init * (max(t_enter, 0.0) + tau) + SUBJECT_SIZE[0] / 2,
            t_enter=t_enter,
            v=float(rng.uniform(1.0, 1.8)),
            side=float(rng.choice([-1.0, 1.0])),
        )
    v_des = min(v_des, cfg.max_speed)

    # scenario traffic on the subject's entry lane: removed for 'free' and when a lead is inserted
    entry = world.lanes[lane].entry
    drop_ids: set[int] = set()
    if situation == "free" or lead is not None or cut is not None:
        for k in range(len(scen.veh_ids)):
            if world.lanes[int(scen.veh_lane[k])].entry == entry:
                drop_ids.add(int(scen.veh_ids[k]))

    tracks: list[_Track] = []
    s_sub = np.zeros(n)
    v_sub = np.zeros(n)
    s_sub[0], v_sub[0] = s_sub0, v_init
    if lead is not None:
        sl = np.zeros(n)
        sl[0] = s_sub0 + SUBJECT_SIZE[0] + lead["gap"]
        sl[1:] = sl[0] + np.cumsum(lead["v"][:-1]) * cfg.sim_dt
        size = np.array(
            [
                float(rng.uniform(3.9, 4.9)),
                float(rng.uniform(1.7, 1.95)),
                float(rng.uniform(1.4, 1.7)),
            ]
        )
        cls = int(Cls.CAR)
        if rng.random() < 0.2:
            size, cls = (
                np.array([float(rng.uniform(7.0, 11.0)), 2.5, float(rng.uniform(3.0, 3.6))]),
                int(Cls.TRUCK),
            )
        tracks.append(_Track(INSERTED_ID0, cls, size, sl, np.zeros(n)))
    if cut is not None:
        sc = s_sub0 + SUBJECT_SIZE[0] + cut["gap"] + np.arange(n) * cfg.sim_dt * cut["v"]
        u = np.clip((times - cut["t_c"]) / cut["dur"], 0.0, 1.0)
        lat = cut["side"] * (1.0 - u * u * (3 - 2 * u))
        tracks.append(_Track(INSERTED_ID0 + 1, int(Cls.CAR), np.array([4.5, 1.8, 1.5]), sc, lat))
    if ped is not None:
        # crossing the lane at arc length s_sub0 + dist, from side to side
        s_p = np.full(n, s_sub0 + ped["dist"])
        lat = ped["side"] * np.clip(
            lw / 2 + 0.3 - (times - ped["t_enter"]) * ped["v"], -lw * 1.5, lw * 1.5
        )
        tracks.append(
            _Track(INSERTED_ID0 + 2, int(Cls.PEDESTRIAN), np.array([0.55, 0.6, 1.75]), s_p, lat)
        )

    # subject: IDM towards the nearest agent in its corridor (inserted tracks + scenario agents)
    for i in range(n - 1):
        t = t_start + times[i]
        pose = _pose_on(world, lane, s_sub[i])[0]
        gap, dv = np.inf, 0.0
        for tr in tracks:
            if (
                abs(tr.lat[i]) < (lw + tr.size[1]) / 2 - 0.3
                or tr.cls == Cls.PEDESTRIAN
                and abs(tr.lat[i]) < lw / 2 + 0.5
            ):
                g = tr.s[i] - s_sub[i] - (SUBJECT_SIZE[0] + tr.size[0]) / 2
                if g > -1.0 and g < gap:
                    vt = (tr.s[i + 1] - tr.s[i]) / cfg.sim_dt
                    gap, dv = g, v_sub[i] - vt
        ag = scen.agents_at(t, exclude_ids=tuple(drop_ids))
        if len(ag):
            rel = _rel(pose, ag.center)
            vrel = ag.velocity @ np.array([np.cos(pose[2]), np.sin(pose[2])])
            inc = (rel[:, 0] > 0) & (
                np.abs(rel[:, 1]) < (SUBJECT_SIZE[1] + ag.size[:, 1]) / 2 + 0.2
            )
            if inc.any():
                g = rel[inc, 0] - (SUBJECT_SIZE[0] + ag.size[inc, 0]) / 2
                j = int(np.argmin(g))
                if g[j] < gap:
                    gap, dv = float(g[j]), float(v_sub[i] - vrel[inc][j])
        a = _idm(v_sub[i], v_des, gap, dv, T, b=b, s0=s0)
        v_sub[i + 1] = max(0.0, v_sub[i] + a * cfg.sim_dt)
        s_sub[i + 1] = s_sub[i] + 0.5 * (v_sub[i] + v_sub[i + 1]) * cfg.sim_dt

    seq = Sequence(index, world, situation)
    frame_t = cfg.warmup + np.arange(cfg.frames) / cfg.fps
    r = rng.random(cfg.frames)
    faults = np.where(
        r < cfg.fault_delay,
        "delay",
        np.where(r < cfg.fault_delay + cfg.fault_vertical, "vertical", "none"),
    )
    vpx = rng.uniform(*cfg.vertical_px, cfg.frames) * rng.choice([-1.0, 1.0], cfg.frames)

    def path_ahead(tl: float) -> np.ndarray:
        s = float(np.interp(tl, times, s_sub))
        arc = np.arange(s, min(s + PATH_AHEAD, L) + PATH_STEP / 2, PATH_STEP)
        if len(arc) < 2:
            arc = np.array([s, s + PATH_STEP])
        return _pose_on(world, lane, arc)[:, :2]

    def state(tl: float) -> tuple[np.ndarray, float, Boxes]:
        s = float(np.interp(tl, times, s_sub))
        v = float(np.interp(tl, times, v_sub))
        pose = _pose_on(world, lane, s)[0]
        parts = [world.static, scen.agents_at(t_start + tl, exclude_ids=tuple(drop_ids))]
        for tr in tracks:
            ss, la = float(np.interp(tl, times, tr.s)), float(np.interp(tl, times, tr.lat))
            p = _pose_on(world, lane, ss, la)[0]
            ds = (float(np.interp(tl + 0.05, times, tr.s)) - ss) / 0.05
            dl = (float(np.interp(tl + 0.05, times, tr.lat)) - la) / 0.05
            if tr.cls == Cls.PEDESTRIAN:
                yaw = p[2] - np.pi / 2 * np.sign(la if la != 0 else 1.0)
                vel = np.array([-np.sin(p[2]) * dl, np.cos(p[2]) * dl])
            else:
                yaw = p[2] + np.arctan2(dl, max(ds, 0.1)) if ds > 0.1 else p[2]
                vel = ds * np.array([np.cos(p[2]), np.sin(p[2])]) + dl * np.array(
                    [-np.sin(p[2]), np.cos(p[2])]
                )
            parts.append(
                Boxes(
                    p[None, :2], tr.size[None], [yaw], [tr.cls], velocity=vel[None], ids=[tr.ident]
                )
            )
        boxes = Boxes.concat(parts)
        # never render/count an agent that overlaps the subject (no interaction model at junctions)
        rel = _rel(pose, boxes.center)
        hit = (np.abs(rel[:, 0]) < (SUBJECT_SIZE[0] + boxes.size[:, 0]) / 2 + 0.3) & (
            np.abs(rel[:, 1]) < (SUBJECT_SIZE[1] + boxes.size[:, 1]) / 2 + 0.3
        )
        hit &= boxes.ids < 1_000_000  # static boxes stay (the subject never enters them)
        return pose, v, boxes.subset(~hit)

    for k, tl in enumerate(frame_t):
        pose, v, boxes = state(float(tl))
        fault = str(faults[k])
        if fault == "delay":
            pose_r, _, boxes_r = state(float(tl) + cfg.delay)
        else:
            pose_r, boxes_r = pose, boxes
        seq.frames.append(
            Frame(
                float(t_start + tl),
                pose,
                v,
                boxes,
                pose_r,
                boxes_r,
                float(vpx[k]) if fault == "vertical" else 0.0,
                fault,
                path_ahead(float(tl)),
                lw,
            )
        )
    return seq
