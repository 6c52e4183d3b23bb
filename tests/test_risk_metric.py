"""Grid-map risk metric: hand cases (THW, TTC, worst-case TTC, regions, clipping)."""

from __future__ import annotations

import numpy as np
import pytest

from traffictwin.grid import GridSpec
from traffictwin.risk.metric import (
    RiskCalculator,
    RiskConfig,
    path_to_subject_frame,
    project_on_path,
    rasterise,
    region_mask,
    risk_from_time,
    risk_threshold,
    risk_to_thw,
    thw_to_risk,
    to_subject_frame,
)
from traffictwin.sim.scene import Boxes, Cls

G = GridSpec()
L, W = 4.5, 1.8


def car(x, y=0.0, vx=0.0, vy=0.0, yaw=0.0, cls=Cls.CAR, length=4.5):
    return Boxes([[x, y]], [[length, 1.8, 1.5]], [yaw], [cls], velocity=[[vx, vy]])


def calc(region="paper", grid=G, **kw):
    return RiskCalculator(grid, RiskConfig(subject_length=L, subject_width=W, region=region, **kw))


def ahead(gap, **kw):
    """A car whose rear is ``gap`` m ahead of the subject's front bumper."""
    return car(L / 2 + gap + 2.25, **kw)


@pytest.mark.parametrize("region", ["corridor", "paper", "camera_fov"])
def test_vehicle_20m_ahead_at_10mps(region):
    r = calc(region)((0.0, 0.0, 0.0), 10.0, ahead(20.0))
    assert r.distance == pytest.approx(20.0, abs=G.cell / 2)
    assert r.thw == pytest.approx(2.0, abs=G.cell / 2 / 10)
    assert r.risk_thw == pytest.approx(0.025, abs=1e-3)
    assert r.target == 0


def test_risk_from_time_hand_values():
    assert risk_from_time(2.0) == pytest.approx(0.025)
    assert risk_from_time(0.238) == pytest.approx(0.21, abs=1e-3)  # the paper's Fig. 4 example
    assert risk_from_time(np.inf) == 0.0
    assert risk_from_time(0.0) == 1.0
    assert risk_from_time(0.01) == 1.0  # 1/THW = 100 clipped at 20
    assert risk_from_time(1.5) == pytest.approx(1 / 30)
    np.testing.assert_allclose(risk_from_time(np.array([0.05, 0.1, 1.0])), [1.0, 0.5, 0.05])


def test_standing_subject_has_zero_risk():
    r = calc()((0.0, 0.0, 0.0), 0.0, ahead(3.0))
    assert r.thw == np.inf and r.risk_thw == 0.0 and np.isfinite(r.distance)


def test_nothing_ahead_has_zero_risk():
    c = calc()
    r = c((0.0, 0.0, 0.0), 15.0, Boxes.empty())
    assert (r.thw, r.risk_thw, r.risk_ttc, r.risk_wttc, r.target) == (np.inf, 0.0, 0.0, 0.0, -1)
    r = c((0.0, 0.0, 0.0), 15.0, car(-15.0))  # behind
    assert r.risk_thw == 0.0 and r.target == -1


def test_vehicle_beside_follows_the_region_rule():
    beside_behind = car(0.0, 3.5)  # entirely behind the front bumper line
    assert calc("paper")((0, 0, 0), 10.0, beside_behind).risk_thw == 0.0
    # beside, its front 3.5 m beyond our bumper: ahead for the paper's pessimistic region,
    # outside the 60 deg camera view
    beside_ahead = car(3.5, 4.0)
    rp = calc("paper")((0, 0, 0), 10.0, beside_ahead)
    rf = calc("camera_fov")((0, 0, 0), 10.0, beside_ahead)
    assert rp.risk_thw > 0 and rp.distance == pytest.approx(4.0 - 0.9 - 0.9, abs=G.cell)
    assert rf.risk_thw == 0.0


def test_clip_at_20():
    r = calc()((0, 0, 0), 20.0, ahead(0.5))
    assert r.thw < 0.05 and r.risk_thw == 1.0


def test_nearest_vehicle_wins_and_pose_transform():
    others = Boxes.concat([ahead(30.0), ahead(10.0)])
    r = calc()((0, 0, 0), 10.0, others)
    assert r.target == 1 and r.thw == pytest.approx(1.0, abs=0.02)
    # the same scene rotated and translated into the world
    yaw = 0.7
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s], [s, c]])
    moved = Boxes(others.center @ R.T + [100.0, -50.0], others.size, others.yaw + yaw, others.cls)
    r2 = calc()((100.0, -50.0, yaw), 10.0, moved)
    assert r2.target == 1 and r2.distance == pytest.approx(r.distance, abs=G.cell)


def test_ttc_and_worst_case_ttc():
    c = calc()
    # lead at the same speed: THW finite, TTC infinite
    r = c((0, 0, 0), 10.0, ahead(20.0, vx=10.0))
    assert r.thw == pytest.approx(2.0, abs=0.02) and r.ttc == np.inf and r.risk_ttc == 0.0
    # lead at 5 m/s: closing at 5 m/s -> TTC 4 s; worst case: 20 / (10 + 5)
    r = c((0, 0, 0), 10.0, ahead(20.0, vx=5.0))
    assert r.ttc == pytest.approx(4.0, abs=0.04)
    assert r.wttc == pytest.approx(20.0 / 15.0, abs=0.02)
    # oncoming at 10 m/s, subject standing: THW inf, TTC 2 s
    r = c((0, 0, 0), 0.0, ahead(20.0, vx=-10.0))
    assert r.thw == np.inf and r.ttc == pytest.approx(2.0, abs=0.02)
    assert r.wttc <= r.ttc


def test_pedestrians_only_when_configured():
    ped = car(L / 2 + 5.0, cls=Cls.PEDESTRIAN, length=0.5)
    assert calc()((0, 0, 0), 10.0, ped).risk_thw == 0.0
    assert calc(include_pedestrians=True)((0, 0, 0), 10.0, ped).risk_thw > 0


def test_border_and_filled_give_the_same_distance():
    scene = Boxes.concat([ahead(12.0), car(20.0, -6.0, yaw=0.4)])
    a = calc(fill="border")((0, 0, 0), 8.0, scene)
    b = calc(fill="filled")((0, 0, 0), 8.0, scene)
    assert a.distance == pytest.approx(b.distance)
    lab = rasterise(to_subject_frame(scene, np.zeros(3)), G, "border")
    full = rasterise(to_subject_frame(scene, np.zeros(3)), G, "filled")
    assert 0 < (lab > 0).sum() < (full > 0).sum()


def test_works_on_the_ci_grid():
    g = GridSpec(128, 96, 0.64)
    r = calc(grid=g)((0, 0, 0), 10.0, ahead(20.0))
    assert r.thw == pytest.approx(2.0, abs=g.cell / 2 / 10)
    m = region_mask(g, RiskConfig(region="camera_fov"))
    assert m.shape == g.shape and m[:, g.cols // 2].sum() > 0 and not m[-1].any()


def test_bad_input_raises():
    with pytest.raises(ValueError, match="region"):
        RiskConfig(region="everywhere")
    with pytest.raises(ValueError, match="speed"):
        calc()((0, 0, 0), -1.0, Boxes.empty())


def test_thresholds_and_conversions() -> None:
    assert risk_threshold(1.5) == pytest.approx(1 / 30)
    assert risk_threshold(1.0) == pytest.approx(1 / 20)
    assert risk_threshold(0.01) == 1.0  # clipped at 1/THW = 20
    r = thw_to_risk(np.array([np.inf, 0.05, 0.0, 1.5, 0.02, 10.0]))
    assert np.allclose(r, [0, 1, 1, 1 / 30, 1, 1 / 200])
    assert np.allclose(
        risk_to_thw(np.array([0.0, 1 / 30, 1.0, 1 / 400]), cap=10), [10, 1.5, 0.05, 10]
    )
    # the paper's example: risk 0.21 <-> a crash in 0.238 s
    assert risk_to_thw(np.array([0.21]))[0] == pytest.approx(0.238, abs=1e-3)


# ---- corridor region -----------------------------------------------------------------------


def test_project_on_path_hand_values():
    path = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])  # 10 m east, then 10 m north
    lat, arc, tangent = project_on_path(np.array([[5.0, 1.0], [11.0, 4.0], [-2.0, 0.0]]), path)
    np.testing.assert_allclose(lat, [1.0, 1.0, 2.0])
    np.testing.assert_allclose(arc, [5.0, 14.0, 0.0])
    np.testing.assert_allclose(tangent, [[1, 0], [0, 1], [1, 0]])


def test_path_to_subject_frame():
    pose = (10.0, 5.0, np.pi / 2)  # facing north
    rel = path_to_subject_frame(np.array([[10.0, 5.0], [10.0, 15.0]]), pose)
    np.testing.assert_allclose(rel, [[0, 0], [10, 0]], atol=1e-12)
    with pytest.raises(ValueError, match="corridor path"):
        path_to_subject_frame(np.zeros((1, 2)), pose)


def test_corridor_ignores_parked_car_and_next_lane_but_sees_the_lead():
    """Lane 3.5 m: a parked car at y = -3.2 m 4 m ahead and a car in the next lane (y = 3.5 m)
    10 m ahead count for the paper's region, not for the corridor; the lead 25 m ahead does."""
    others = Boxes.concat([ahead(4.0, y=-3.2), ahead(10.0, y=3.5), ahead(25.0)])
    paper = calc("paper")((0.0, 0.0, 0.0), 10.0, others)
    corr = calc("corridor", lane_width=3.5)((0.0, 0.0, 0.0), 10.0, others)
    # paper: straight line from the bumper corner (y = -0.9) to the car's corner (y = -2.3)
    assert paper.target == 0 and paper.distance == pytest.approx(np.hypot(4.0, 1.4), abs=G.cell)
    assert corr.target == 2 and corr.distance == pytest.approx(25.0, abs=G.cell / 2)
    assert corr.thw == pytest.approx(2.5, abs=0.02)


def test_corridor_margin_and_lane_width_from_the_frame():
    edge = ahead(10.0, y=2.5)  # nearest edge 2.5 - 0.9 = 1.6 m from the centreline
    c = calc("corridor")
    # (cells of 0.32 m: the border cell's centre is within 0.16 m of the edge)
    assert c((0.0, 0.0, 0.0), 10.0, edge, lane_width=2.6).target == -1  # half-width 1.3 m
    assert c((0.0, 0.0, 0.0), 10.0, edge, lane_width=3.8).target == 0  # half-width 1.9 m
    wide = calc("corridor", lane_width=2.6, corridor_margin=0.5)
    assert wide((0.0, 0.0, 0.0), 10.0, edge).target == 0
    with pytest.raises(ValueError, match="corridor half-width"):
        RiskConfig(region="corridor", lane_width=2.0, corridor_margin=-1.5)


def test_corridor_follows_a_curved_path_and_measures_along_it():
    """A left quarter circle of radius 20 m: a car on the arc 90 deg ahead (arc length 31.4 m)
    is in the corridor at distance 31.4 - L/2; a car straight ahead at x = 15 m (outside the
    bend) is not."""
    r = 20.0
    phi = np.linspace(0.0, np.pi / 2, 400)
    path_world = np.stack([r * np.sin(phi), r - r * np.cos(phi)], 1)
    on_arc = car(r * np.sin(np.pi / 4), r - r * np.cos(np.pi / 4), yaw=np.pi / 4)
    outside = ahead(10.0)
    c = calc("corridor", lane_width=3.5)
    got = c((0.0, 0.0, 0.0), 10.0, Boxes.concat([on_arc, outside]), path=path_world)
    assert got.target == 0
    # the nearest border cell is ~2.25 m (half the car) before the car's centre along the arc
    assert got.distance == pytest.approx(r * np.pi / 4 - L / 2 - 2.25, abs=0.5)
    straight = c((0.0, 0.0, 0.0), 10.0, Boxes.concat([on_arc, outside]))
    assert straight.target == 1


def test_corridor_ttc_uses_the_path_tangent():
    # a lead 20 m ahead driving away at 4 m/s while the subject does 10 m/s: closing 6 m/s
    r = calc("corridor")((0.0, 0.0, 0.0), 10.0, ahead(20.0, vx=4.0))
    assert r.ttc == pytest.approx(20.0 / 6.0, abs=0.05)


def test_corridor_region_mask_is_a_band_along_the_path():
    m = region_mask(G, RiskConfig(subject_length=L, region="corridor", lane_width=3.5))
    x, y = G.cell_centers()
    np.testing.assert_array_equal(m, (np.abs(y) <= 1.75) & (x > L / 2))
