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
from traffictwin.sim.traffic import SUBJECT_SIZE, Scenario, sample_scenario
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


@dataclass
class _Course:
    """Where and when the subject drives: its world, scenario traffic, lane (index, length L m,
    width lw m), start arc length s0 (m), simulation time grid (s) and scenario start time (s)."""

    world: World
    scen: Scenario
    lane: int
    L: float
    lw: float
    s0: float
    times: np.ndarray
    t_start: float


@dataclass
class _Plan:
    """The situation's parameters: IDM desired time gap T (s), standstill gap s0 (m),
    comfortable deceleration b (m/s^2), desired and initial speed (m/s), and the inserted lead,
    cut-in vehicle or pedestrian (None when the situation has none)."""

    T: float
    s0: float
    b: float
    v_des: float
    v_init: float
    lead: dict | None = None
    cut: dict | None = None
    ped: dict | None = None


def _draw_course(
    seed: int, index: int, cfg: DrivingConfig, rng: np.random.Generator
) -> tuple[_Course, str]:
    """The world, its traffic, the subject's lane and start, and the situation of the sequence."""
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
    return _Course(world, scen, lane, L, lw, s_sub0, times, t_start), situation


def _lead_plan(
    situation: str, plan: _Plan, rng: np.random.Generator, cfg: DrivingConfig, times: np.ndarray
) -> None:
    """Fill ``plan`` for a situation with an inserted lead vehicle (speed profile ``v``, m/s)."""
    n = len(times)
    if situation == "follow_far":
        plan.T = float(rng.uniform(1.3, 3.0))
        v_l = float(rng.uniform(6.0, cfg.max_speed - 2))
        plan.v_des, plan.v_init = v_l + 3.0, v_l
        plan.lead = dict(gap=2.0 + plan.T * v_l * float(rng.uniform(0.9, 1.2)), v=np.full(n, v_l))
    elif situation == "follow_close":
        plan.T = float(rng.uniform(0.4, 1.2))
        plan.s0 = float(rng.uniform(1.0, 2.0))
        v_l = float(rng.uniform(5.0, cfg.max_speed - 2))
        plan.v_des, plan.v_init = v_l + 3.0, v_l
        plan.lead = dict(gap=2.0 + plan.T * v_l * float(rng.uniform(0.8, 1.1)), v=np.full(n, v_l))
    elif situation == "approach_slow":
        v_l = float(rng.uniform(3.0, 10.0))
        plan.v_des = plan.v_init = float(rng.uniform(12.0, cfg.max_speed))
        plan.T = float(rng.uniform(0.4, 1.0))
        plan.b = float(rng.uniform(3.0, 6.0))
        plan.lead = dict(gap=float(rng.uniform(25.0, 70.0)), v=np.full(n, v_l))
    elif situation == "approach_stopped":
        plan.v_des = plan.v_init = float(rng.uniform(8.0, 20.0))
        plan.T = float(rng.uniform(0.4, 1.0))
        plan.b = float(rng.uniform(3.0, 6.0))  # late braking
        plan.lead = dict(gap=float(rng.uniform(20.0, 60.0)), v=np.zeros(n))
    elif situation == "stop_and_go":
        plan.v_init, plan.v_des = 0.0, float(rng.uniform(8.0, 16.0))
        plan.T = float(rng.uniform(0.4, 1.0))
        plan.s0 = float(rng.uniform(1.0, 2.0))
        t_go = cfg.warmup + float(rng.uniform(0.0, 2.5))
        acc = float(rng.uniform(1.0, 2.5))
        plan.lead = dict(
            gap=float(rng.uniform(2.0, 4.0)), v=np.clip((times - t_go) * acc, 0.0, plan.v_des)
        )


def _draw_plan(
    situation: str, rng: np.random.Generator, cfg: DrivingConfig, times: np.ndarray, lw: float
) -> _Plan:
    """The situation's IDM parameters, speeds and inserted agents (see the module docstring)."""
    T = float(rng.uniform(1.0, 1.8))
    v_des = float(rng.uniform(8.0, cfg.max_speed))
    v_init = v_des * float(rng.uniform(0.6, 1.0))
    plan = _Plan(T=T, s0=2.0, b=3.0, v_des=v_des, v_init=v_init)
    if situation == "cut_in":
        plan.v_des = plan.v_init = float(rng.uniform(8.0, cfg.max_speed))
        plan.T = float(rng.uniform(1.2, 1.8))
        side = float(rng.choice([-1.0, 1.0]))
        t_c = cfg.warmup + float(rng.uniform(0.0, cfg.frames / cfg.fps * 0.5))
        plan.cut = dict(
            gap=float(rng.uniform(2.0, 12.0)),
            v=plan.v_init * float(rng.uniform(0.75, 1.15)),
            side=side * lw,
            t_c=t_c,
            dur=float(rng.uniform(1.5, 3.0)),
        )
    elif situation == "pedestrian":
        plan.v_des = plan.v_init = float(rng.uniform(6.0, 14.0))
        plan.T = float(rng.uniform(0.5, 1.0))
        # the driver reacts late, once the pedestrian is in the lane
        plan.b = float(rng.uniform(4.0, 7.0))
        # the pedestrian steps into the lane at t_enter, when the (still unbraked) subject is
        # tau seconds away from it
        t_enter = cfg.warmup + float(rng.uniform(-0.5, 0.8)) * cfg.frames / cfg.fps
        tau = float(rng.uniform(0.8, 3.5))
        plan.ped = dict(
            dist=plan.v_init * (max(t_enter, 0.0) + tau) + SUBJECT_SIZE[0] / 2,
            t_enter=t_enter,
            v=float(rng.uniform(1.0, 1.8)),
            side=float(rng.choice([-1.0, 1.0])),
        )
    else:
        _lead_plan(situation, plan, rng, cfg, times)
    plan.v_des = min(plan.v_des, cfg.max_speed)
    return plan


def _dropped_ids(course: _Course, situation: str, plan: _Plan) -> tuple[int, ...]:
    """Scenario vehicles on the subject's entry lane: removed for 'free' and when a lead or
    cut-in vehicle is inserted (none otherwise)."""
    world, scen = course.world, course.scen
    entry = world.lanes[course.lane].entry
    drop_ids: set[int] = set()
    if situation == "free" or plan.lead is not None or plan.cut is not None:
        for k in range(len(scen.veh_ids)):
            if world.lanes[int(scen.veh_lane[k])].entry == entry:
                drop_ids.add(int(scen.veh_ids[k]))
    return tuple(drop_ids)


def _inserted_tracks(
    course: _Course, plan: _Plan, rng: np.random.Generator, cfg: DrivingConfig
) -> list[_Track]:
    """The inserted lead (car or truck), cut-in car and crossing pedestrian on the time grid."""
    times, s_sub0, lw = course.times, course.s0, course.lw
    n = len(times)
    tracks: list[_Track] = []
    if plan.lead is not None:
        sl = np.zeros(n)
        sl[0] = s_sub0 + SUBJECT_SIZE[0] + plan.lead["gap"]
        sl[1:] = sl[0] + np.cumsum(plan.lead["v"][:-1]) * cfg.sim_dt
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
    cut, ped = plan.cut, plan.ped
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
    return tracks


def _nearest_ahead(
    course: _Course,
    tracks: list[_Track],
    drop_ids: tuple[int, ...],
    i: int,
    s_i: float,
    v_i: float,
    dt: float,
) -> tuple[float, float]:
    """Bumper gap (m, inf if none) and approach rate (m/s) to the nearest agent in the subject's
    corridor at grid step ``i`` (subject at arc length ``s_i`` m with speed ``v_i`` m/s)."""
    lw = course.lw
    pose = _pose_on(course.world, course.lane, s_i)[0]
    gap, dv = np.inf, 0.0
    for tr in tracks:
        if (
            abs(tr.lat[i]) < (lw + tr.size[1]) / 2 - 0.3
            or tr.cls == Cls.PEDESTRIAN
            and abs(tr.lat[i]) < lw / 2 + 0.5
        ):
            g = tr.s[i] - s_i - (SUBJECT_SIZE[0] + tr.size[0]) / 2
            if g > -1.0 and g < gap:
                vt = (tr.s[i + 1] - tr.s[i]) / dt
                gap, dv = g, v_i - vt
    ag = course.scen.agents_at(course.t_start + course.times[i], exclude_ids=drop_ids)
    if len(ag):
        rel = _rel(pose, ag.center)
        vrel = ag.velocity @ np.array([np.cos(pose[2]), np.sin(pose[2])])
        inc = (rel[:, 0] > 0) & (np.abs(rel[:, 1]) < (SUBJECT_SIZE[1] + ag.size[:, 1]) / 2 + 0.2)
        if inc.any():
            g = rel[inc, 0] - (SUBJECT_SIZE[0] + ag.size[inc, 0]) / 2
            j = int(np.argmin(g))
            if g[j] < gap:
                gap, dv = float(g[j]), float(v_i - vrel[inc][j])
    return gap, dv


def _drive_subject(
    course: _Course,
    plan: _Plan,
    tracks: list[_Track],
    drop_ids: tuple[int, ...],
    dt: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Arc length (m) and speed (m/s) of the subject over the time grid: IDM towards the nearest
    agent in its corridor (inserted tracks + scenario agents)."""
    n = len(course.times)
    s_sub = np.zeros(n)
    v_sub = np.zeros(n)
    s_sub[0], v_sub[0] = course.s0, plan.v_init
    for i in range(n - 1):
        gap, dv = _nearest_ahead(course, tracks, drop_ids, i, s_sub[i], v_sub[i], dt)
        a = _idm(v_sub[i], plan.v_des, gap, dv, plan.T, b=plan.b, s0=plan.s0)
        v_sub[i + 1] = max(0.0, v_sub[i] + a * dt)
        s_sub[i + 1] = s_sub[i] + 0.5 * (v_sub[i] + v_sub[i + 1]) * dt
    return s_sub, v_sub


@dataclass
class _Replay:
    """The simulated sequence, read at any time ``tl`` (s after its start) by interpolation."""

    course: _Course
    tracks: list[_Track]
    drop_ids: tuple[int, ...]
    s_sub: np.ndarray
    v_sub: np.ndarray

    def path_ahead(self, tl: float) -> np.ndarray:
        """The subject's lane centreline ahead (K, 2; world, m), :data:`PATH_AHEAD` m long."""
        c = self.course
        s = float(np.interp(tl, c.times, self.s_sub))
        arc = np.arange(s, min(s + PATH_AHEAD, c.L) + PATH_STEP / 2, PATH_STEP)
        if len(arc) < 2:
            arc = np.array([s, s + PATH_STEP])
        return _pose_on(c.world, c.lane, arc)[:, :2]

    def _track_box(self, tr: _Track, tl: float) -> Boxes:
        """Inserted agent ``tr`` at ``tl`` as a box, heading and velocity from its motion."""
        c = self.course
        times = c.times
        ss, la = float(np.interp(tl, times, tr.s)), float(np.interp(tl, times, tr.lat))
        p = _pose_on(c.world, c.lane, ss, la)[0]
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
        return Boxes(
            p[None, :2], tr.size[None], [yaw], [tr.cls], velocity=vel[None], ids=[tr.ident]
        )

    def state(self, tl: float) -> tuple[np.ndarray, float, Boxes]:
        """Subject pose (x, y, yaw) and speed (m/s) and every box (static + agents) at ``tl``."""
        c = self.course
        s = float(np.interp(tl, c.times, self.s_sub))
        v = float(np.interp(tl, c.times, self.v_sub))
        pose = _pose_on(c.world, c.lane, s)[0]
        parts = [c.world.static, c.scen.agents_at(c.t_start + tl, exclude_ids=self.drop_ids)]
        parts += [self._track_box(tr, tl) for tr in self.tracks]
        boxes = Boxes.concat(parts)
        # never render/count an agent that overlaps the subject (no interaction model at junctions)
        rel = _rel(pose, boxes.center)
        hit = (np.abs(rel[:, 0]) < (SUBJECT_SIZE[0] + boxes.size[:, 0]) / 2 + 0.3) & (
            np.abs(rel[:, 1]) < (SUBJECT_SIZE[1] + boxes.size[:, 1]) / 2 + 0.3
        )
        hit &= boxes.ids < 1_000_000  # static boxes stay (the subject never enters them)
        return pose, v, boxes.subset(~hit)


def _record_frames(replay: _Replay, rng: np.random.Generator, cfg: DrivingConfig) -> list[Frame]:
    """The ``cfg.frames`` recorded frames after the warm-up, with their drawn stereo faults."""
    frame_t = cfg.warmup + np.arange(cfg.frames) / cfg.fps
    r = rng.random(cfg.frames)
    faults = np.where(
        r < cfg.fault_delay,
        "delay",
        np.where(r < cfg.fault_delay + cfg.fault_vertical, "vertical", "none"),
    )
    vpx = rng.uniform(*cfg.vertical_px, cfg.frames) * rng.choice([-1.0, 1.0], cfg.frames)
    frames = []
    for k, tl in enumerate(frame_t):
        pose, v, boxes = replay.state(float(tl))
        fault = str(faults[k])
        if fault == "delay":
            pose_r, _, boxes_r = replay.state(float(tl) + cfg.delay)
        else:
            pose_r, boxes_r = pose, boxes
        frames.append(
            Frame(
                float(replay.course.t_start + tl),
                pose,
                v,
                boxes,
                pose_r,
                boxes_r,
                float(vpx[k]) if fault == "vertical" else 0.0,
                fault,
                replay.path_ahead(float(tl)),
                replay.course.lw,
            )
        )
    return frames


def generate_sequence(seed: int, index: int, cfg: DrivingConfig) -> Sequence:
    """Simulate sequence ``index`` of the dataset with ``seed`` (deterministic for the pair)."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), int(index), 3003]))
    course, situation = _draw_course(seed, index, cfg, rng)
    plan = _draw_plan(situation, rng, cfg, course.times, course.lw)
    drop_ids = _dropped_ids(course, situation, plan)
    tracks = _inserted_tracks(course, plan, rng, cfg)
    s_sub, v_sub = _drive_subject(course, plan, tracks, drop_ids, cfg.sim_dt)
    replay = _Replay(course, tracks, drop_ids, s_sub, v_sub)
    seq = Sequence(index, course.world, situation)
    seq.frames = _record_frames(replay, rng, cfg)
    return seq
