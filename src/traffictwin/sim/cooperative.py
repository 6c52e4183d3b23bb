"""Cooperative sequences: N lidar-equipped vehicles at a junction over time, with a hazard.

One *sequence* (deterministic for ``(seed, index)``) happens at a junction of the shared world
(:func:`traffictwin.sim.world.build_world`, templates :data:`JUNCTIONS`). Vehicle 0, the *ego*,
turns right into the *target arm*, where a van is parked and a *hazard* waits in the ego's lane
beside it, a few metres after the turn:

* ``stopped_car``: a car stopped in the ego's lane beside the van (double-parked / waiting);
* ``pedestrian``: a person standing at the van's side in the lane (the delivery driver), who
  walks across the lane when the unbraked ego is ``step_in_tau`` seconds away.

The *kind* of the sequence decides what the ego can see:

* ``occluded``: the van is parked at the inner kerb, between the ego's line of sight (it comes
  round the corner) and the hazard. Drawn until the ego's own lidar has no return from the
  hazard at the critical onset (:func:`generate_cooperative_sequence`): the hazard "behind the
  parked van" is visible only to the others;
* ``open``: the van is parked on the far kerb, where it hides nothing; drawn the same way
  otherwise, never selected.

The other vehicles cooperate: ``oncoming`` ones drive on the target arm towards the junction
(they see the hazard head-on), ``follower`` ones drive behind the ego in its lane; roles
alternate (1: oncoming, 2: follower, 3: oncoming, ...). Their speed is constant; the ego turns
at a constant speed and brakes only once the hazard is within its reaction distance — a driver
who reacts late, so that sequences contain critical frames (time headway < ``critical_thw``).

Every frame carries all vehicles' exact world poses and speeds, every box in the world (static +
agents, world frame, with velocities), and the ego's path ahead (its lane's centreline) and lane
width: the corridor of the risk label (:mod:`traffictwin.risk.metric`). Units: m, s, m/s, rad.
Simplification (documented): vehicles do not interact, except the ego with the hazard.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from traffictwin.sim.coop_layout import HazardTrack, ScenarioLayout, ego_profile, lateral
from traffictwin.sim.emerging_car import draw_emerging_car, straight_lanes
from traffictwin.sim.lidar import LidarSpec, scan
from traffictwin.sim.scene import Boxes, Cls
from traffictwin.sim.traffic import SUBJECT_SIZE
from traffictwin.sim.world import Lane, World, build_world

KINDS = ("occluded", "open")
HAZARDS = ("stopped_car", "pedestrian", "emerging_car")
JUNCTIONS = ("cross4", "t_junction")
ROLES = ("ego", "oncoming", "follower")
AGENT_ID0 = 800_000  # ids of the cooperating vehicles (ego = AGENT_ID0)
VAN_ID = AGENT_ID0 + 100
HAZARD_ID = AGENT_ID0 + 101
PATH_AHEAD = 60.0  # m of the ego's lane recorded per frame
PATH_STEP = 0.5  # m between path points
PATH_POINTS = int(round(PATH_AHEAD / PATH_STEP)) + 1


@dataclass(frozen=True)
class CooperativeConfig:
    """fps (Hz) and frames per sequence; vehicles N >= 2 (ego + N - 1 cooperating); the share of
    ``occluded`` sequences (the rest are ``open``, alternating by index) and of ``pedestrian``
    hazards; ranges (low, high) drawn per sequence: ego turning speed (m/s), reaction distance
    (m, bumper to hazard along the path, when the ego starts braking), braking deceleration
    (m/s^2), time from the sequence start to the critical onset at constant speed (s), van
    length (m), gap between the van's far end and the stopped car's rear (m), pedestrian
    step-in time (s before the unbraked ego reaches it) and walking speed (m/s), cooperating
    vehicles' speed (m/s) and spacing (m); van length (m) and the distance of its near end after
    the end of the turn (m); junction templates to draw from; ``hidden_s`` (s): in ``occluded``
    sequences the hazard must stay hidden from the ego over the ``hidden_s`` seconds up to the
    critical onset and be seen by another vehicle in that window (0: hidden at the onset only);
    ``critical_thw`` (s): the time headway below which a frame is critical (the critical onset: the
    first such frame; ``twin.critical_thw``, the risk label's threshold)."""

    fps: float = 10.0
    frames: int = 30
    vehicles: int = 3
    occluded_share: float = 0.5
    pedestrian_share: float = 0.5
    emerging_car_share: float = 0.0
    ego_speed: tuple[float, float] = (5.5, 8.5)
    reaction_distance: tuple[float, float] = (3.0, 7.0)
    deceleration: tuple[float, float] = (4.0, 7.0)
    lead_in: tuple[float, float] = (0.6, 1.4)
    van_length: tuple[float, float] = (6.0, 7.5)
    hazard_after_turn: tuple[float, float] = (0.0, 2.0)
    step_in_tau: tuple[float, float] = (0.8, 1.6)
    walk_speed: tuple[float, float] = (1.2, 1.8)
    emerge_speed: tuple[float, float] = (2.0, 3.5)
    emerge_tau: tuple[float, float] = (0.6, 1.2)
    other_speed: tuple[float, float] = (3.0, 7.0)
    spacing: tuple[float, float] = (9.0, 16.0)
    templates: tuple[str, ...] = JUNCTIONS
    max_attempts: int = 40
    hidden_s: float = 0.0
    critical_thw: float = field(kw_only=True)

    def __post_init__(self) -> None:
        if self.fps <= 0 or self.frames < 2:
            raise ValueError(
                f"cooperative: fps must be > 0 Hz and frames >= 2, got {self.fps}, {self.frames}"
            )
        if self.vehicles < 2:
            raise ValueError(
                f"cooperative: vehicles must be >= 2 (ego + others), got {self.vehicles}"
            )
        for name in ("occluded_share", "pedestrian_share", "emerging_car_share"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(
                    f"cooperative: {name} must be in [0, 1], got {getattr(self, name)}"
                )
        for name in (
            "ego_speed",
            "reaction_distance",
            "deceleration",
            "lead_in",
            "van_length",
            "step_in_tau",
            "walk_speed",
            "emerge_speed",
            "emerge_tau",
            "other_speed",
            "spacing",
        ):
            lo, hi = getattr(self, name)
            if not 0 < lo <= hi:
                raise ValueError(
                    f"cooperative: {name} must be (low, high) with 0 < low <= high, got {[lo, hi]}"
                )
        if self.pedestrian_share + self.emerging_car_share > 1.0:
            raise ValueError(
                "cooperative: pedestrian_share + emerging_car_share must be <= 1 (the rest are "
                f"stopped cars), got {self.pedestrian_share} + {self.emerging_car_share}"
            )
        if self.hidden_s < 0 or self.hidden_s >= self.frames / self.fps:
            raise ValueError(
                f"cooperative: hidden_s must be >= 0 s and shorter than the sequence "
                f"({self.frames / self.fps:g} s), got {self.hidden_s}"
            )
        bad = [t for t in self.templates if t not in JUNCTIONS]
        if bad or not self.templates:
            raise ValueError(
                f"cooperative: templates {bad or '(empty list)'} unknown; expected some of {list(JUNCTIONS)}"
            )


@dataclass
class CoopFrame:
    """One instant: time (s), exact world poses ``(N, 3)`` and speeds ``(N,)`` of the vehicles
    (row 0 = ego), all boxes in the world (static + agents, world frame, world velocities), the
    ego's path ahead ``(PATH_POINTS, 2)`` (world, m) and its lane width (m); every vehicle's path
    ahead ``vehicle_paths (N, PATH_POINTS, 2)`` (world, m; row 0 = ``path``) and lane widths
    ``vehicle_lane_widths (N,)`` m."""

    t: float
    poses: np.ndarray
    speeds: np.ndarray
    boxes: Boxes
    path: np.ndarray
    lane_width: float
    vehicle_paths: np.ndarray | None = None
    vehicle_lane_widths: np.ndarray | None = None


@dataclass
class CoopSequence:
    """A cooperative sequence: index, world, kind (:data:`KINDS`), hazard (:data:`HAZARDS`), the
    role of each vehicle (:data:`ROLES`), their box ids, and the frames."""

    index: int
    world: World
    kind: str
    hazard: str
    roles: tuple[str, ...]
    vehicle_ids: np.ndarray
    frames: list[CoopFrame] = field(default_factory=list)
    onset_frame: int = -1
    hidden_at_onset: bool = False
    attempts: int = 1
    hidden_window: bool = False


def sequence_kind(index: int, occluded_share: float) -> str:
    """Kind of sequence ``index``: ``occluded`` for a share ``occluded_share`` of the indices,
    spread evenly (index-based, so a split by index stays balanced)."""
    return (
        "occluded"
        if np.floor((index + 1) * occluded_share) > np.floor(index * occluded_share)
        else "open"
    )


def _heading_change(lane_xy: np.ndarray) -> float:
    d0, d1 = lane_xy[1] - lane_xy[0], lane_xy[-1] - lane_xy[-2]
    return float(
        (np.arctan2(d1[1], d1[0]) - np.arctan2(d0[1], d0[0]) + np.pi) % (2 * np.pi) - np.pi
    )


def _offset_from_axis(lane_xy: np.ndarray) -> float:
    """Lateral distance (m) of a junction lane's first point from its arm's axis (through the origin)."""
    d = lane_xy[1] - lane_xy[0]
    h = np.arctan2(d[1], d[0])
    p = lane_xy[0]
    return float(abs(p[0] * np.sin(h) - p[1] * np.cos(h)))


def right_turn_lanes(world: World) -> list[int]:
    """Indices of the lanes that turn right (60-120 deg clockwise) from the kerb-side lane."""
    out = []
    for i, lane in enumerate(world.lanes):
        turn = _heading_change(lane.centerline)
        if -2.1 < turn < -1.05 and _offset_from_axis(lane.centerline) < 0.75 * lane.width:
            out.append(i)
    return out


def _turn_span(lane_xy: np.ndarray, cum: np.ndarray) -> tuple[float, float]:
    """Arc lengths (m) where the lane starts and ends turning (heading off by > 2 deg)."""
    d = np.diff(lane_xy, axis=0)
    yaw = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    turning = np.flatnonzero(
        (np.abs(yaw - yaw[0]) > np.deg2rad(2)) & (np.abs(yaw - yaw[-1]) > np.deg2rad(2))
    )
    if len(turning) == 0:
        raise ValueError("cooperative: the ego's lane does not turn")
    return float(cum[turning[0]]), float(cum[turning[-1] + 1])


def _reverse_lane(world: World, ego_lane: int) -> int:
    """The lane that drives the ego's route backwards (from the target arm into the ego's arm)."""
    ego = world.lanes[ego_lane].centerline
    best, best_d = -1, np.inf
    for i, lane in enumerate(world.lanes):
        if i == ego_lane:
            continue
        c = lane.centerline
        d = np.linalg.norm(c[0] - ego[-1]) + np.linalg.norm(c[-1] - ego[0])
        if d < best_d:
            best, best_d = i, d
    return best


def generate_cooperative_sequence(
    seed: int, index: int, cfg: CooperativeConfig, lidar: LidarSpec | None = None
) -> CoopSequence:
    """Simulate cooperative sequence ``index`` of the dataset with ``seed`` (deterministic).

    ``occluded`` sequences are what their name says: with ``lidar`` given, draws are repeated
    (up to ``cfg.max_attempts``, from the same generator) until the ego's own lidar has no return
    from the hazard at the *critical onset* (the first frame whose time headway to the hazard,
    along the path at the ego's speed, is below ``cfg.critical_thw``) and, with ``cfg.hidden_s >
    0``, at no frame of the ``hidden_s`` seconds before it, while another vehicle's lidar returns
    from it at some frame of that window (noiseless scans); the sequence records whether that
    held (``hidden_at_onset``, ``hidden_window``) and the attempts it took. ``open`` sequences are
    never selected."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), int(index), 5005]))
    kind = sequence_kind(index, cfg.occluded_share)
    hazard = sequence_hazard(index, cfg)
    seq = None
    for attempt in range(1, cfg.max_attempts + 1):
        seq = _draw_sequence(rng, index, kind, hazard, cfg)
        seq.attempts = attempt
        if kind == "open" or lidar is None:
            return seq
        seq.hidden_at_onset = not ego_sees_hazard(seq, lidar, seq.onset_frame)
        if seq.hidden_at_onset and cfg.hidden_s <= 0:
            return seq
        if seq.hidden_at_onset:
            seq.hidden_window = hidden_before_onset(seq, lidar, cfg.hidden_s, cfg.fps)
            if seq.hidden_window:
                return seq
    assert seq is not None
    return seq


def ego_sees_hazard(seq: CoopSequence, lidar: LidarSpec, frame: int) -> bool:
    """Whether any ray of the ego's lidar (no noise, no dropout) returns from the hazard at ``frame``."""
    return vehicle_sees_hazard(seq, lidar, frame, 0)


def vehicle_sees_hazard(seq: CoopSequence, lidar: LidarSpec, frame: int, k: int) -> bool:
    """Whether any ray of vehicle ``k``'s lidar (no noise, no dropout) returns from the hazard at ``frame``."""
    f = seq.frames[frame]
    others = f.boxes.subset(f.boxes.ids != seq.vehicle_ids[k])
    s = scan(lidar, f.poses[k], others, None)
    return bool(np.any(s.hit == int(np.flatnonzero(others.ids == HAZARD_ID)[0])))


def hidden_before_onset(seq: CoopSequence, lidar: LidarSpec, hidden_s: float, fps: float) -> bool:
    """Whether the hazard is hidden from the ego at every frame of the ``hidden_s`` seconds up to
    the critical onset (the window must lie inside the sequence) and seen by another vehicle at
    some frame of that window (noiseless scans)."""
    first = seq.onset_frame - int(round(hidden_s * fps))
    if first < 0:
        return False
    window = range(seq.onset_frame, first - 1, -1)
    if any(ego_sees_hazard(seq, lidar, f) for f in window):
        return False
    return any(
        vehicle_sees_hazard(seq, lidar, f, k) for f in window for k in range(1, len(seq.roles))
    )


GOLDEN = (np.sqrt(5.0) - 1.0) / 2.0  # low-discrepancy step of the hazard assignment


def sequence_hazard(index: int, cfg: CooperativeConfig) -> str:
    """Hazard (:data:`HAZARDS`) of sequence ``index``: fixed by the index, not redrawn with the
    scenario, so the shares hold among the sequences kept (an occluded draw that fails to hide
    its hazard is redrawn with the same hazard). The ``r``-th sequence of its kind gets the
    position ``r * GOLDEN mod 1`` (a low-discrepancy sequence: every prefix of a kind is split
    as evenly as it can be): ``pedestrian`` below ``cfg.pedestrian_share``, ``emerging_car``
    below that plus ``cfg.emerging_car_share``, ``stopped_car`` above."""
    kind = sequence_kind(index, cfg.occluded_share)
    rank = sum(sequence_kind(j, cfg.occluded_share) == kind for j in range(index))
    u = (rank * GOLDEN) % 1.0
    if u < cfg.pedestrian_share:
        return "pedestrian"
    if u < cfg.pedestrian_share + cfg.emerging_car_share:
        return "emerging_car"
    return "stopped_car"


def _draw_sequence(
    rng: np.random.Generator, index: int, kind: str, hazard: str, cfg: CooperativeConfig
) -> CoopSequence:
    """One draw of a sequence of ``kind`` and ``hazard`` (see :func:`generate_cooperative_sequence`)."""
    times = np.arange(cfg.frames) / cfg.fps
    if hazard == "emerging_car":
        world, lanes = draw_world(rng, index, cfg.templates, straight_lanes)
        ego_lane = int(lanes[int(rng.integers(len(lanes)))])
        layout = draw_emerging_car(rng, world, ego_lane, kind, cfg, times)
    else:
        layout = _van_layout(rng, index, kind, hazard, cfg, times)
    roles, tracks = _cooperators(rng, layout, cfg, times)
    return _assemble(index, kind, hazard, layout, roles, tracks, times, cfg.critical_thw)


def draw_world(
    rng: np.random.Generator, index: int, templates: tuple[str, ...], routes
) -> tuple[World, list]:
    """A junction world from ``templates`` with at least one route ``routes(world)`` (a list;
    nearly always the first draw works) and that list."""
    for _ in range(20):
        template = str(templates[int(rng.integers(len(templates)))])
        world = build_world(template, int(rng.integers(0, 2**31 - 1)))
        found = routes(world)
        if found:
            return world, found
    raise RuntimeError(  # pragma: no cover - every junction template has the routes
        f"cooperative sequence {index}: no junction with a suitable route in {list(templates)}"
    )


def _van_layout(
    rng: np.random.Generator,
    index: int,
    kind: str,
    hazard: str,
    cfg: CooperativeConfig,
    times: np.ndarray,
) -> ScenarioLayout:
    """The ego turns right; a van at the target arm's inner kerb (occluded) or its far kerb
    (open), the hazard (stopped car or pedestrian) beside it in the ego's lane."""
    world, lanes = draw_world(rng, index, cfg.templates, right_turn_lanes)
    ego_lane = int(lanes[int(rng.integers(len(lanes)))])
    lane = world.lanes[ego_lane]
    lw = float(lane.width)
    _, turn_end = _turn_span(lane.centerline, lane.cum)

    van_len = float(rng.uniform(*cfg.van_length))
    van_size = np.array([van_len, float(rng.uniform(2.0, 2.3)), float(rng.uniform(2.6, 3.2))])
    van_near = turn_end + float(rng.uniform(*cfg.hazard_after_turn))
    van_lat = -(lw / 2 + 0.25 + van_size[1] / 2)  # inner (right-hand) kerb, beside the ego's lane
    if kind == "open":
        van_lat = lw * 1.5 + 0.25 + van_size[1] / 2  # far kerb, beyond the oncoming lane
    van_pose = lateral(lane.pose_at(np.array([van_near + van_len / 2]))[0], van_lat)
    v_ego = float(rng.uniform(*cfg.ego_speed))
    d_react = float(rng.uniform(*cfg.reaction_distance))
    decel = float(rng.uniform(*cfg.deceleration))
    half = SUBJECT_SIZE[0] / 2
    if hazard == "stopped_car":
        car_size = np.array([float(rng.uniform(3.9, 4.8)), float(rng.uniform(1.7, 1.9)), 1.5])
        hazard_near = van_near + float(rng.uniform(0.5, 2.5))  # arc length of its rear
        s_h = hazard_near + car_size[0] / 2
    else:
        ped_size = np.array([0.55, 0.6, float(rng.uniform(1.6, 1.9))])
        s_h = van_near + float(rng.uniform(1.5, van_len - 1.0))
        hazard_near = s_h - ped_size[0] / 2
    # the sequence starts lead_in seconds (at constant speed) before the ego's bumper is 1.5 s away
    lead_in = float(rng.uniform(*cfg.lead_in))
    s0 = hazard_near - half - v_ego * (cfg.critical_thw + lead_in)  # onset after lead_in s
    s_ego, v_prof = ego_profile(times, s0, v_ego, hazard_near - half, d_react, decel)
    hp = lane.pose_at(np.array([s_h]))[0]
    if hazard == "stopped_car":
        track = HazardTrack(
            np.tile(hp, (len(times), 1)), np.zeros((len(times), 2)), car_size, int(Cls.CAR)
        )
    else:  # out of the van's shadow into the lane, when the unbraked ego is tau s away
        tau = float(rng.uniform(*cfg.step_in_tau))
        walk = float(rng.uniform(*cfg.walk_speed))
        t_enter = (hazard_near - half - s0) / v_ego - tau
        start = -(lw / 2 - 0.1)  # in the lane beside the van (hidden behind it when occluded)
        ped_lat = np.minimum(start + walk * np.maximum(times - t_enter, 0.0), lw * 1.5)
        poses = np.stack([lateral(hp, float(lat)) for lat in ped_lat])
        moving = np.r_[ped_lat[1:] != ped_lat[:-1], False]
        across = walk * np.array([-np.sin(hp[2]), np.cos(hp[2])])
        velocity = np.where(moving[:, None], across[None], 0.0)
        poses[:, 2] += np.pi / 2
        track = HazardTrack(poses, velocity, ped_size, int(Cls.PEDESTRIAN))
    return ScenarioLayout(
        world, ego_lane, van_pose, van_size, track, s_ego, v_prof, hazard_near - half, hp[:2]
    )


def cooperator_role(k: int) -> str:
    """The role of vehicle ``k >= 1`` (:data:`ROLES`): odd ones oncoming, even ones following."""
    if k < 1:
        raise ValueError(f"vehicle {k}: cooperators are numbered from 1 (0 is the ego)")
    return "oncoming" if k % 2 == 1 else "follower"


def _cooperators(
    rng: np.random.Generator, layout: ScenarioLayout, cfg: CooperativeConfig, times: np.ndarray
) -> tuple[list[str], list[tuple[int, np.ndarray, np.ndarray]]]:
    """Roles (ego first) and tracks ``(lane index, s(t) m, speed(t) m/s)`` of the cooperating
    vehicles: ``oncoming`` ones on the ego's route driven backwards, placed from the point level
    with the hazard, ``follower`` ones behind the ego in its lane."""
    world, ego_lane = layout.world, layout.ego_lane
    rev = _reverse_lane(world, ego_lane)
    rev_lane = world.lanes[rev]
    d_rev = np.linalg.norm(rev_lane.centerline - layout.hazard_point, axis=1)
    s_rev_h = float(rev_lane.cum[int(np.argmin(d_rev))])
    roles = ["ego"]
    tracks = []
    for k in range(1, cfg.vehicles):
        role = cooperator_role(k)
        rank = (k - 1) // 2  # 0 for the first of each role
        gap = float(rng.uniform(*cfg.spacing))
        if role == "oncoming":
            v = float(rng.uniform(*cfg.other_speed))
            s_start = s_rev_h - (8.0 + gap) * (rank + 1) - 4.0
            tracks.append((rev, s_start + v * times, np.full(len(times), v)))
        else:
            tracks.append((ego_lane, layout.s_ego - gap * (rank + 1) - 1.0, layout.v_ego.copy()))
        roles.append(role)
    return roles, tracks


def _assemble(
    index: int,
    kind: str,
    hazard: str,
    layout: ScenarioLayout,
    roles: list[str],
    tracks: list[tuple[int, np.ndarray, np.ndarray]],
    times: np.ndarray,
    critical_thw: float,
) -> CoopSequence:
    """The frames of a drawn scenario: vehicle poses and speeds, every box, every vehicle's path;
    the critical onset is the first frame with THW below ``critical_thw`` (s)."""
    world, lane = layout.world, layout.world.lanes[layout.ego_lane]
    n = len(roles)
    ids = AGENT_ID0 + np.arange(n)
    seq = CoopSequence(index, world, kind, hazard, tuple(roles), ids)
    v_prof, s_ego, track = layout.v_ego, layout.s_ego, layout.hazard
    with np.errstate(divide="ignore"):
        thw = np.where(v_prof > 0, (layout.s_stop - s_ego) / np.maximum(v_prof, 1e-9), np.inf)
    critical = np.flatnonzero(thw < critical_thw)
    seq.onset_frame = int(critical[0]) if len(critical) else 0
    size_v = np.array(SUBJECT_SIZE)
    van = Boxes(
        layout.van_pose[None, :2],
        layout.van_size[None],
        [layout.van_pose[2]],
        [int(Cls.TRUCK)],
        ids=[VAN_ID],
    )
    for f, t in enumerate(times):
        poses = np.zeros((n, 3))
        speeds = np.zeros(n)
        poses[0] = lane.pose_at(np.array([s_ego[f]]))[0]
        speeds[0] = v_prof[f]
        for k, (li, s, v) in enumerate(tracks, start=1):
            poses[k] = world.lanes[li].pose_at(np.array([s[f]]))[0]
            speeds[k] = v[f]
        vels = speeds[:, None] * np.stack([np.cos(poses[:, 2]), np.sin(poses[:, 2])], 1)
        vehicles = Boxes(
            poses[:, :2],
            np.tile(size_v, (n, 1)),
            poses[:, 2],
            np.full(n, int(Cls.CAR)),
            velocity=vels,
            ids=ids,
        )
        hazard_box = Boxes(
            track.poses[f, None, :2],
            track.size[None],
            [track.poses[f, 2]],
            [track.cls],
            velocity=track.velocity[f, None],
            ids=[HAZARD_ID],
        )
        on_lane = [(layout.ego_lane, s_ego[f])] + [(li, s[f]) for li, s, _ in tracks]
        paths = np.stack([_path_ahead(world.lanes[li], float(at)) for li, at in on_lane])
        seq.frames.append(
            CoopFrame(
                float(t),
                poses,
                speeds,
                Boxes.concat([world.static, van, vehicles, hazard_box]),
                paths[0],
                float(lane.width),
                paths,
                np.array([world.lanes[li].width for li, _ in on_lane], dtype=np.float64),
            )
        )
    return seq


def _path_ahead(lane: Lane, at: float) -> np.ndarray:
    """``PATH_POINTS`` world points (m) of ``lane``'s centreline from arc length ``at`` on, every
    ``PATH_STEP`` m (held at the lane's end)."""
    arc = np.minimum(at + np.arange(PATH_POINTS) * PATH_STEP, lane.length)
    return lane.pose_at(arc)[:, :2]
