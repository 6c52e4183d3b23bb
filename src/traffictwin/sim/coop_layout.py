"""What a cooperative scenario draw fixes before the frames are built: the layout.

Every scenario of :mod:`traffictwin.sim.cooperative` (the hazard beside a parked van after a right
turn, the car from a side street behind a truck, :mod:`traffictwin.sim.side_street`) draws a
world, the ego's lane and speed profile, an occluder box and the hazard's track; the frames
(vehicles, boxes, path) are then assembled the same way for all of them. Units: m, s, m/s, rad.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from traffictwin.sim.world import World

__all__ = ["HazardTrack", "ScenarioLayout", "ego_profile", "lateral"]


@dataclass(frozen=True)
class HazardTrack:
    """The hazard's box over the frames: world poses ``(T, 3)`` (x m, y m, yaw rad of the box),
    world velocities ``(T, 2)`` (m/s), size ``(3,)`` (length, width, height m) and class
    (:class:`~traffictwin.sim.scene.Cls`)."""

    poses: np.ndarray
    velocity: np.ndarray
    size: np.ndarray
    cls: int


@dataclass(frozen=True)
class ScenarioLayout:
    """A drawn scenario: the world, the ego's lane (index into ``world.lanes``), the occluder's
    world pose ``(3,)`` and size ``(3,)``, the hazard's track, the ego's arc length ``s_ego (T,)``
    (m) and speed ``v_ego (T,)`` (m/s) along its lane, ``s_stop`` (m): the arc length where the
    ego's bumper meets the hazard's near side (the critical onset's reference), and
    ``hazard_point (2,)``: the world point level with the hazard, where the oncoming vehicles are
    placed from."""

    world: World
    ego_lane: int
    van_pose: np.ndarray
    van_size: np.ndarray
    hazard: HazardTrack
    s_ego: np.ndarray
    v_ego: np.ndarray
    s_stop: float
    hazard_point: np.ndarray


def lateral(pose: np.ndarray, lat: float) -> np.ndarray:
    """``pose`` (x, y, yaw) shifted ``lat`` m to its left."""
    return np.array([pose[0] - np.sin(pose[2]) * lat, pose[1] + np.cos(pose[2]) * lat, pose[2]])


def ego_profile(
    t: np.ndarray, s0: float, v: float, s_hazard: float, d_react: float, decel: float
) -> tuple[np.ndarray, np.ndarray]:
    """Ego arc length (m) and speed (m/s) at times ``t``: constant ``v`` until the bumper is
    ``d_react`` m before ``s_hazard`` (arc length of the hazard's near side minus the ego's half
    length), then braking at ``decel`` to a stop (no earlier than 0.5 m before the hazard)."""
    s_brake = s_hazard - d_react
    t_brake = max(0.0, (s_brake - s0) / v)
    stop_dist = min(v * v / (2 * decel), max(d_react - 0.5, 0.1))
    a = v * v / (2 * stop_dist)
    tb = np.clip(t - t_brake, 0.0, v / a)
    s = np.where(t < t_brake, s0 + v * t, s0 + v * t_brake + v * tb - 0.5 * a * tb * tb)
    speed = np.where(t < t_brake, v, np.maximum(v - a * tb, 0.0))
    return s, speed
