"""The ``emerging_car`` scenario: a car pulls out of a driveway behind a parked truck.

The ego drives straight through the junction into the *exit arm*. A truck (the scenario's
occluder, the same box as the van of the right-turn scenario) is parked a few metres into the
exit arm: at the ego's kerb (``occluded``: between the ego and the driveway) or at the far kerb
(``open``: it hides nothing). Just beyond the truck's far end a car waits in a driveway, nose to
the road behind the parking strip, and pulls out perpendicular to the road at a constant speed;
its nose enters the ego's lane when the unbraked ego is ``emerge_tau`` seconds away, and it stops
with its nose at the lane's far edge, blocking it. The ego drives straight, so the truck's shadow
covers the driveway until late (a turning ego looks across the corner past the truck); the
oncoming vehicles see the driveway from ahead. Static boxes (buildings, walls, trees) in front of
the driveway are cleared so the car has a way out; in ``occluded`` sequences a hedge along the verge behind the
truck, up to the driveway, hides the waiting car's body from the ego's side (the truck alone
would let a distant ego see it past the truck's back, across the sidewalk). Units: m, s, m/s, rad.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from traffictwin.sim.coop_layout import HazardTrack, ScenarioLayout, ego_profile, lateral
from traffictwin.sim.scene import Boxes, Cls
from traffictwin.sim.traffic import SUBJECT_SIZE
from traffictwin.sim.world import World

__all__ = ["straight_lanes", "draw_emerging_car", "clear_driveway"]

PARKING_GAP = 0.25  # m between the ego's lane edge and a parked box
DRIVEWAY_SETBACK = 0.3  # m between the truck's kerb side and the waiting car's nose
CLEAR_HALF_LENGTH = 5.0  # m along the road cleared of static boxes either side of the driveway
CLEAR_DEPTH = 20.0  # m beside the road cleared behind the driveway
HEDGE_WIDTH = 0.6  # m, the hedge behind the truck (occluded sequences)
HEDGE_LEAD = 2.0  # m the hedge starts before the truck's near end


def straight_lanes(world: World) -> list[int]:
    """Indices of the kerb-side lanes that cross the junction straight (heading change < 20 deg)."""
    out = []
    for i, lane in enumerate(world.lanes):
        c = lane.centerline
        d0, d1 = c[1] - c[0], c[-1] - c[-2]
        turn = (np.arctan2(d1[1], d1[0]) - np.arctan2(d0[1], d0[0]) + np.pi) % (2 * np.pi) - np.pi
        h = np.arctan2(d0[1], d0[0])
        offset = abs(c[0, 0] * np.sin(h) - c[0, 1] * np.cos(h))
        if abs(turn) < np.deg2rad(20) and offset < 0.75 * lane.width:
            out.append(i)
    return out


def _exit_mouth(world: World, lane_index: int) -> float:
    """Arc length (m) where the lane leaves the junction: the first point past its closest
    approach to the centre that is ``world.junction_radius`` from it."""
    lane = world.lanes[lane_index]
    r = np.linalg.norm(lane.centerline - world.center, axis=1)
    past = np.arange(len(r)) >= int(np.argmin(r))
    return float(lane.cum[int(np.flatnonzero(past & (r >= world.junction_radius))[0])])


def clear_driveway(world: World, pose: np.ndarray, extra: Boxes | None = None) -> World:
    """``world`` without the static boxes whose centre lies within ``CLEAR_HALF_LENGTH`` m
    along the road of ``pose`` (a lane pose at the driveway) and up to ``CLEAR_DEPTH`` m to its
    right, plus the static boxes ``extra`` (new ids after the world's)."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    rel = world.static.center - pose[:2]
    along = rel[:, 0] * c + rel[:, 1] * s
    right = rel[:, 0] * s - rel[:, 1] * c
    block = (np.abs(along) < CLEAR_HALF_LENGTH) & (right > 0) & (right < CLEAR_DEPTH)
    static = world.static.subset(~block)
    if extra is not None and len(extra):
        extra.ids = int(world.static.ids.max(initial=0)) + 1 + np.arange(len(extra))
        static = Boxes.concat([static, extra])
    return replace(world, static=static)


def _hedge(lane_pose_at, s0: float, s1: float, lat: float, height: float) -> Boxes:
    """A hedge (vegetation box) beside the lane from arc length ``s0`` to ``s1`` (m), its inner
    side ``lat`` m left of the lane centre (negative: right), ``HEDGE_WIDTH`` m wide."""
    pose = lateral(lane_pose_at(np.array([(s0 + s1) / 2]))[0], lat - HEDGE_WIDTH / 2)
    return Boxes(pose[None, :2], [[s1 - s0, HEDGE_WIDTH, height]], [pose[2]], [int(Cls.VEGETATION)])


def draw_emerging_car(
    rng: np.random.Generator,
    world: World,
    ego_lane: int,
    kind: str,
    cfg: Any,
    times: np.ndarray,
) -> ScenarioLayout:
    """The layout of an ``emerging_car`` sequence on ``world`` with the ego on the straight lane
    ``ego_lane`` (see the module docstring); ``cfg`` the
    :class:`~traffictwin.sim.cooperative.CooperativeConfig` (its ranges)."""
    lane = world.lanes[ego_lane]
    lw = float(lane.width)
    van_len = float(rng.uniform(*cfg.van_length))
    van_size = np.array([van_len, float(rng.uniform(2.0, 2.3)), float(rng.uniform(2.6, 3.2))])
    van_near = _exit_mouth(world, ego_lane) + float(rng.uniform(*cfg.hazard_after_turn))
    kerb = -(lw / 2 + PARKING_GAP + van_size[1] / 2)
    van_lat = kerb if kind == "occluded" else lw * 1.5 + PARKING_GAP + van_size[1] / 2
    van_pose = lateral(lane.pose_at(np.array([van_near + van_len / 2]))[0], van_lat)
    v_ego = float(rng.uniform(*cfg.ego_speed))
    d_react = float(rng.uniform(*cfg.reaction_distance))
    decel = float(rng.uniform(*cfg.deceleration))
    car_size = np.array([float(rng.uniform(3.9, 4.8)), float(rng.uniform(1.7, 1.9)), 1.5])
    hazard_near = van_near + van_len + float(rng.uniform(0.5, 2.5))  # its side facing the ego
    s_h = hazard_near + car_size[1] / 2
    half = SUBJECT_SIZE[0] / 2
    lead_in = float(rng.uniform(*cfg.lead_in))
    s0 = hazard_near - half - v_ego * (cfg.critical_thw + lead_in)  # onset after lead_in s
    s_ego, v_prof = ego_profile(times, s0, v_ego, hazard_near - half, d_react, decel)
    tau = float(rng.uniform(*cfg.emerge_tau))
    speed = float(rng.uniform(*cfg.emerge_speed))
    # lateral position of the car's centre (m, left of the ego's lane centre) over time
    nose0 = -(lw / 2 + PARKING_GAP + van_size[1] + DRIVEWAY_SETBACK)
    t_enter = (hazard_near - half - s0) / v_ego - tau  # its nose reaches the lane's edge
    t_start = t_enter - (nose0 + lw / 2) / -speed
    centre = nose0 - car_size[0] / 2 + speed * np.maximum(times - t_start, 0.0)
    centre = np.minimum(centre, lw / 2 - car_size[0] / 2)
    hp = lane.pose_at(np.array([s_h]))[0]
    poses = np.stack([lateral(hp, float(c)) for c in centre])
    poses[:, 2] += np.pi / 2  # facing the road
    moving = np.r_[centre[1:] != centre[:-1], False]
    across = speed * np.array([-np.sin(hp[2]), np.cos(hp[2])])
    track = HazardTrack(poses, np.where(moving[:, None], across[None], 0.0), car_size, int(Cls.CAR))
    hedge = None
    if kind == "occluded":  # along the verge behind the truck, up to the driveway
        hedge_lat = -(lw / 2 + PARKING_GAP + van_size[1] + 0.1)
        s_hedge = van_near - HEDGE_LEAD
        hedge = _hedge(
            lane.pose_at, s_hedge, hazard_near - 0.3, hedge_lat, float(rng.uniform(2.0, 2.5))
        )
    return ScenarioLayout(
        clear_driveway(world, hp, hedge),
        ego_lane,
        van_pose,
        van_size,
        track,
        s_ego,
        v_prof,
        hazard_near - half,
        hp[:2],
    )
