"""The emerging-car scenario of the cooperative twin: a car pulls out of a driveway behind a parked
truck and a hedge (traffictwin.sim.emerging_car), drawn beside the pedestrian-behind-a-van one."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from traffictwin.sim.cooperative import (
    HAZARD_ID,
    VAN_ID,
    CooperativeConfig,
    ego_sees_hazard,
    generate_cooperative_sequence,
    sequence_hazard,
    sequence_kind,
    vehicle_sees_hazard,
)
from traffictwin.sim.emerging_car import (
    CLEAR_HALF_LENGTH,
    clear_driveway,
    straight_lanes,
)
from traffictwin.sim.lidar import LidarSpec
from traffictwin.sim.scene import Boxes, Cls
from traffictwin.sim.world import build_world

LIDAR = LidarSpec(azimuth_res_deg=0.4, max_range=60.0)
CFG = CooperativeConfig(
    critical_thw=1.5,
    frames=22,
    fps=5.0,
    lead_in=(3.0, 3.4),
    hidden_s=1.0,
    pedestrian_share=0.0,
    emerging_car_share=1.0,
)


def _lane_pose_near(path: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """The pose (x, y, yaw) of the path point nearest ``xy``, heading along the path."""
    i = int(np.argmin(np.linalg.norm(path - xy, axis=1)))
    i = min(i, len(path) - 2)
    d = path[i + 1] - path[i]
    return np.array([*path[i], np.arctan2(d[1], d[0])])


def _local(pose: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """``xy (..., 2)`` in the frame of ``pose`` (x ahead, y left), m."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    d = np.asarray(xy) - pose[:2]
    return np.stack([d[..., 0] * c + d[..., 1] * s, -d[..., 0] * s + d[..., 1] * c], -1)


def test_straight_lanes_keep_their_heading_and_the_kerb() -> None:
    world = build_world("cross4", 5)
    lanes = straight_lanes(world)
    assert lanes  # every cross4 has straight kerb-side lanes, one per arm
    for i in lanes:
        c = world.lanes[i].centerline
        d0, d1 = c[1] - c[0], c[-1] - c[-2]
        turn = np.arctan2(np.cross(d0, d1), np.dot(d0, d1))
        assert abs(turn) < np.deg2rad(20)
    # a t_junction has straight lanes only along its bar: fewer than the cross4's
    assert 0 < len(straight_lanes(build_world("t_junction", 5))) <= len(lanes)


def test_hazards_follow_the_shares_within_each_kind() -> None:
    cfg = replace(CFG, pedestrian_share=0.3, emerging_car_share=0.5)
    hazards = [sequence_hazard(i, cfg) for i in range(200)]
    for kind in ("occluded", "open"):
        mine = [h for i, h in enumerate(hazards) if sequence_kind(i, 0.5) == kind]
        assert len(mine) == 100
        # the low-discrepancy split: every share within one sequence of its expected count
        assert abs(mine.count("pedestrian") - 30) <= 1
        assert abs(mine.count("emerging_car") - 50) <= 1
        assert abs(mine.count("stopped_car") - 20) <= 1
    # fixed by the index: the same hazard whatever the seed or the draws
    assert sequence_hazard(7, cfg) == sequence_hazard(7, cfg)
    half = replace(CFG, pedestrian_share=0.5, emerging_car_share=0.5)
    assert [sequence_hazard(i, half) for i in range(6)] == [
        "pedestrian",
        "pedestrian",
        "emerging_car",
        "emerging_car",
        "pedestrian",
        "pedestrian",
    ]
    with pytest.raises(ValueError, match="pedestrian_share \\+ emerging_car_share"):
        CooperativeConfig(critical_thw=1.5, pedestrian_share=0.6, emerging_car_share=0.5)
    with pytest.raises(ValueError, match="emerge_tau"):
        CooperativeConfig(critical_thw=1.5, emerge_tau=(1.0, 0.5))


def test_clear_driveway_removes_only_what_blocks_the_way_out() -> None:
    world = build_world("straight", 1)
    pose = np.array([0.0, 0.0, 0.0])  # the driveway's lane pose: heading +x, right = -y
    boxes = Boxes(
        [[1.0, -6.0], [1.0, 6.0], [CLEAR_HALF_LENGTH + 2.0, -6.0], [-2.0, -25.0]],
        [[2.0, 2.0, 3.0]] * 4,
        [0.0] * 4,
        [int(Cls.BUILDING)] * 4,
        ids=[10, 11, 12, 13],
    )
    hedge = Boxes([[-6.0, -4.0]], [[6.0, 0.6, 2.2]], [0.0], [int(Cls.VEGETATION)])
    out = clear_driveway(replace(world, static=boxes), pose, hedge)
    # the box right of the driveway goes; left, beyond the cleared length or depth stay
    assert sorted(out.static.ids[:3].tolist()) == [11, 12, 13]
    assert out.static.ids[-1] == 14 and out.static.cls[-1] == int(Cls.VEGETATION)
    assert len(boxes) == 4  # the world's boxes are not modified in place


def test_occluded_emerging_car_is_hidden_from_the_ego_and_seen_by_another() -> None:
    seq = generate_cooperative_sequence(0, 1, CFG, LIDAR)  # index 1: occluded
    assert seq.kind == "occluded" and seq.hazard == "emerging_car"
    assert seq.hidden_at_onset and seq.hidden_window
    first = seq.onset_frame - int(round(CFG.hidden_s * CFG.fps))
    window = range(first, seq.onset_frame + 1)
    assert not any(ego_sees_hazard(seq, LIDAR, f) for f in window)
    assert any(vehicle_sees_hazard(seq, LIDAR, f, k) for f in window for k in (1, 2))
    # the ego drives straight; the truck is parked at its kerb (right) and the car ends in its lane
    boxes0, boxes_end = seq.frames[0].boxes, seq.frames[-1].boxes
    lane_pose = _lane_pose_near(seq.frames[0].path, boxes0.center[boxes0.ids == HAZARD_ID][0])
    van = _local(lane_pose, boxes0.center[boxes0.ids == VAN_ID][0])
    car0 = _local(lane_pose, boxes0.center[boxes0.ids == HAZARD_ID][0])
    car_end = _local(lane_pose, boxes_end.center[boxes_end.ids == HAZARD_ID][0])
    assert van[1] < -2.0  # right of the ego's lane
    assert car0[0] > van[0] and car0[1] < -5.0  # beyond the truck, waiting off the road
    assert car_end[0] == pytest.approx(car0[0], abs=0.02)  # it moves across the road only
    length = boxes0.size[boxes0.ids == HAZARD_ID][0, 0]
    lw = seq.frames[0].lane_width
    nose_end = car_end[1] + length / 2
    assert -lw / 2 < nose_end <= lw / 2 + 0.05  # in the ego's lane, never beyond its far edge
    # a hedge stands behind the truck
    assert int(Cls.VEGETATION) in set(seq.world.static.cls.tolist())


def test_open_emerging_car_has_no_occluder_between_ego_and_driveway() -> None:
    seq = generate_cooperative_sequence(0, 0, CFG, LIDAR)  # index 0: open
    assert seq.kind == "open" and seq.hazard == "emerging_car" and seq.attempts == 1
    boxes = seq.frames[0].boxes
    pose = _lane_pose_near(seq.frames[0].path, boxes.center[boxes.ids == HAZARD_ID][0])
    assert _local(pose, boxes.center[boxes.ids == VAN_ID][0])[1] > 2.0  # far (left) kerb
    # the ego sees the car in the driveway before it moves and at the onset
    assert ego_sees_hazard(seq, LIDAR, seq.onset_frame)
    speed = np.linalg.norm(seq.frames[0].boxes.velocity[boxes.ids == HAZARD_ID][0])
    assert speed == 0.0  # waiting at the start
