"""The predictive hazard measure (traffictwin.twin.predict): hand-computed times to conflict."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from traffictwin.grid import GridSpec
from traffictwin.twin.predict import (
    MapReading,
    PredictSettings,
    box_points,
    cell_velocities,
    map_ttc,
    time_to_conflict,
)

P = PredictSettings(
    min_speed=1.0, max_speed=15.0, max_extent=6.0, step_s=0.1, horizon_s=2.0, warn_s=1.5
)
PATH = np.stack([np.linspace(0.0, 60.0, 61), np.zeros(61)], 1)  # straight ahead along +x
L = 4.0  # ego length: its front at x = 2 m


def test_static_blob_in_corridor_gives_thw():
    # an obstacle 12 m ahead of the front at 10 m/s: TTC = THW = 1.2 s
    ttc = time_to_conflict([[14.0, 0.0]], [[0.0, 0.0]], PATH, 3.5, 10.0, L, P)
    assert ttc == pytest.approx(1.2)


def test_static_blob_beside_corridor_no_conflict():
    ttc = time_to_conflict([[10.0, 4.0]], [[0.0, 0.0]], PATH, 3.5, 10.0, L, P)
    assert ttc == np.inf


def test_crossing_blob_enters_swept_corridor():
    # 6 m ahead of the front, 3.75 m to the left, walking right at 1.5 m/s: in the corridor
    # (|y| <= 1.75) after 2 / 1.5 = 1.333 s (first sample 1.4 s); the ego (5 m/s) reaches x = 8 at
    # 1.2 s, so the conflict is when the blob enters: 1.4 s. THW: none (not in the corridor now)
    ttc = time_to_conflict([[8.0, 3.75]], [[0.0, -1.5]], PATH, 3.5, 5.0, L, P)
    assert ttc == pytest.approx(1.4)
    assert time_to_conflict([[8.0, 3.75]], [[0.0, 0.0]], PATH, 3.5, 5.0, L, P) == np.inf


def test_blob_entering_ahead_of_the_ego_conflicts_when_reached():
    # 20 m ahead of the front, enters the corridor at 0.5 s; the ego (10 m/s) reaches it at 2.0 s
    ttc = time_to_conflict([[22.0, 2.25]], [[0.0, -1.0]], PATH, 3.5, 10.0, L, P)
    assert ttc == pytest.approx(2.0)
    # beyond the horizon: none
    far = time_to_conflict([[32.0, 2.25]], [[0.0, -1.0]], PATH, 3.5, 10.0, L, P)
    assert far == np.inf


def test_a_follower_is_no_forward_conflict_when_the_ego_turns():
    # the ego turns right: its path bends from +x to -y (quarter circle of radius 8 m); a vehicle
    # 9 m behind, beside the path's start, drives straight on (+x, 7 m/s) at the ego's speed:
    # extrapolated it would cross the bent corridor ahead of the ego (x = 8 m, y <= -8 m is the
    # path after the bend; the straight line y = -8 meets it at 2.4 s), but it follows the ego
    a = np.linspace(0.0, np.pi / 2, 40)
    bend = np.stack([8.0 * np.sin(a), -8.0 + 8.0 * np.cos(a)], 1)
    after = np.stack([np.full(40, 8.0), -8.0 - np.linspace(0.5, 40.0, 40)], 1)
    path = np.concatenate([bend, after])
    p = PredictSettings(step_s=0.1, horizon_s=3.0, warn_s=2.5)
    behind = time_to_conflict([[-9.0, -8.0]], [[7.0, 0.0]], path, 3.5, 7.0, L, p)
    assert behind == np.inf
    # the same straight-line motion from ahead of the ego's rear still conflicts
    ahead = time_to_conflict([[-1.0, -8.0]], [[7.0, 0.0]], path, 3.5, 7.0, L, p)
    assert np.isfinite(ahead)


def test_stopped_ego_and_empty_input():
    assert time_to_conflict([[5.0, 0.0]], [[0.0, 0.0]], PATH, 3.5, 0.0, L, P) == np.inf
    assert time_to_conflict(np.zeros((0, 2)), np.zeros((0, 2)), PATH, 3.5, 5.0, L, P) == np.inf


def test_settings_checked():
    with pytest.raises(ValueError, match="min_speed"):
        PredictSettings(min_speed=2.0, max_speed=1.0, warn_s=1.5)
    with pytest.raises(ValueError, match="step_s"):
        PredictSettings(step_s=0.0, warn_s=1.5)
    with pytest.raises(ValueError, match="max_extent"):
        PredictSettings(max_extent=0.0, warn_s=1.5)


def _blob(grid: GridSpec, x: float, y: float, half: float = 0.6) -> np.ndarray:
    xs, ys = grid.cell_centers() if hasattr(grid, "cell_centers") else _centres(grid)
    m = np.zeros((2, grid.rows, grid.cols), np.float32)
    m[1][(np.abs(xs - x) <= half) & (np.abs(ys - y) <= half)] = 0.9
    m[0][m[1] == 0] = 0.9
    return m


def _centres(grid: GridSpec) -> tuple[np.ndarray, np.ndarray]:
    r, c = np.meshgrid(np.arange(grid.rows), np.arange(grid.cols), indexing="ij")
    return grid.rc_to_xy(r, c)


@pytest.mark.parametrize(
    ("vx", "vy", "half"), [(0.0, -2.0, 0.6), (0.0, -4.0, 0.6), (1.5, 0.0, 0.3)]
)
def test_cell_velocities_of_a_moving_blob(vx, vy, half):
    # half = 0.3 m: a pedestrian-sized blob (2 x 2 cells) moving 1 cell per frame
    grid = GridSpec(rows=128, cols=96, cell=0.32)
    dt = 0.2
    pose = np.zeros(3)
    a = _blob(grid, 10.0, 4.0, half)
    b = _blob(grid, 10.0 + vx * dt, 4.0 + vy * dt, half)
    v = cell_velocities(a, b, pose, pose, dt, grid, 0.5, P)
    occ = b[1] >= 0.5
    est = v[occ].mean(0)
    # centroids move by whole cells: within one cell / dt = 1.6 m/s of the truth, direction right
    assert est[0] == pytest.approx(vx, abs=0.32 / dt + 1e-6)
    assert est[1] == pytest.approx(vy, abs=0.32 / dt + 1e-6)
    assert np.sign(est[0] + est[1]) == np.sign(vx + vy)
    assert np.all(v[~occ] == 0)


def test_long_components_are_static():
    grid = GridSpec(rows=128, cols=96, cell=0.32)
    a = _blob(grid, 10.0, 4.0, 4.0)  # 8 m long: longer than max_extent (6 m)
    b = _blob(grid, 10.0, 3.0, 4.0)
    v = cell_velocities(a, b, np.zeros(3), np.zeros(3), 0.2, grid, 0.5, P)
    assert np.abs(v).max() == 0.0


def test_cell_velocities_compensate_ego_motion():
    # a static blob seen from an ego that drove 2 m forward: no motion over the ground
    grid = GridSpec(rows=128, cols=96, cell=0.32)
    a, b = _blob(grid, 12.0, 3.0), _blob(grid, 10.0, 3.0)
    v = cell_velocities(a, b, np.zeros(3), np.array([2.0, 0.0, 0.0]), 0.2, grid, 0.5, P)
    assert np.abs(v).max() == 0.0  # below min_speed: static


def test_map_ttc_static_map_equals_thw_and_moving_blob_earlier():
    grid = GridSpec(rows=128, cols=96, cell=0.32)
    path = np.stack([np.linspace(0.0, 20.0, 41), np.zeros(41)], 1)
    m = _blob(grid, 10.0, 3.5)  # beside the corridor (lane 3.5 m)
    zero = np.zeros((grid.rows, grid.cols, 2), np.float32)
    args = (path, 3.5, 5.0, MapReading(grid, 0.5, 0.5, L, 1.8), P)
    assert map_ttc(m, zero, *args) == np.inf
    vel = zero.copy()
    vel[m[1] >= 0.5] = (0.0, -1.5)  # walking into the lane
    assert map_ttc(m, vel, *args) < 1.5


def test_box_points_in_ego_frame():
    corners = np.array([[[11.0, 1.0], [9.0, 1.0], [9.0, -1.0], [11.0, -1.0]]])
    xy, vel = box_points(corners, np.array([[0.0, 2.0]]), np.array([0.0, 0.0, np.pi / 2]))
    # ego facing +y: world +y is ego +x; world x = 10 is ego y = -10
    assert xy[:, 0].min() == pytest.approx(-1.0) and xy[:, 1].max() == pytest.approx(-9.0)
    np.testing.assert_allclose(vel, np.tile([2.0, 0.0], (len(vel), 1)), atol=1e-12)


# ------------------------------------------------------------------ paired with THW, in the summary
def _pred_table():
    """One open sequence with no episode (THW never warns; TTC warns at frame 2) and one occluded
    sequence whose episode starts at frame 5 (THW warns at the onset, TTC 0.3 s before), 10 Hz."""
    import pandas as pd

    from traffictwin.twin.evaluation import EGO

    rows = []
    for seq, kind in ((0, "open"), (1, "occluded")):
        for m in (EGO, "twin"):
            for i in range(10):
                crit = kind == "occluded" and i >= 5
                rows.append(
                    {
                        "sequence": seq,
                        "kind": kind,
                        "hazard": "pedestrian",
                        "vehicles": 3,
                        "method": m,
                        "frame": i,
                        "time": i / 10,
                        "thw": 1.0 if crit else 3.0,
                        "ttc": 1.0 if (crit or (kind == "occluded" and i >= 2)) else 3.0,
                        "thw_true": 1.0 if crit else 3.0,
                        "ttc_true": 1.0 if crit else np.inf,
                        "left_out": 0,
                    }
                )
            if m == "twin" and kind == "open":
                rows[-8]["ttc"] = 1.0  # frame 2 of the open sequence: a predictive false alarm
    f = pd.DataFrame(rows)
    f["critical"] = f["thw_true"] < 1.5
    f["flagged"] = f["thw"] < 1.5
    f["flagged_ttc"] = f["ttc"] < 1.5
    return f


def test_predictive_warnings_paired_with_thw_and_targets():
    from _acceptance import thresholds

    from traffictwin.twin.evaluation import TwinEvalSettings
    from traffictwin.twin.summary import summarise
    from traffictwin.twin.targets import targets

    TWIN = thresholds("twin")

    # h = 0.3 s: frames 0-6 of the 1 s open sequence are judged (7-9: window past its end)
    s = summarise(
        _pred_table(),
        ["twin"],
        10.0,
        TwinEvalSettings(
            critical_thw=1.5, predict=PredictSettings(warn_s=1.5), n_boot=200, horizon_s=0.3
        ),
    )
    occ = s["twin"]["occluded"]["predictive"]
    assert occ["lead_s_median"] == pytest.approx(0.3)  # TTC warns at 0.2 s, onset 0.5 s
    assert occ["lead_vs_thw_s_mean"] == pytest.approx(0.3)  # THW warns at the onset
    opn = s["twin"]["open"]["predictive"]
    assert opn["false_alarm_share"] == pytest.approx(1 / 7)
    assert opn["false_alarm_share_vs_thw"] == pytest.approx(1 / 7)
    assert occ["ttc_true_recall"] == pytest.approx(1.0)
    assert occ["ttc_true_false_alarm_rate"] == pytest.approx(3 / 5)
    t = targets({"D": {"methods": s}}, "twin", "D", TWIN)
    assert t["predictive_warns_earlier_than_thw"]["value"] == pytest.approx(0.3)
    assert t["predictive_no_more_false_alarms"]["value"] == pytest.approx(1 / 7)
    assert t["predictive_no_more_false_alarms"]["met"] is False  # one sequence: CI [1/7, 1/7]


def test_evaluate_sequence_reads_ttc_beside_thw():
    from traffictwin.sim.cooperative import CooperativeConfig
    from traffictwin.sim.lidar import LidarSpec
    from traffictwin.twin.data import TwinDataParams, sequence_arrays
    from traffictwin.twin.evaluation import EGO, TwinEvalSettings, TwinPass, evaluate_sequence

    grid = GridSpec(rows=64, cols=48, cell=0.5)
    p = TwinDataParams(
        grid=grid,
        lidar=LidarSpec(azimuth_res_deg=0.8, max_range=50.0),
        scenario=CooperativeConfig(critical_thw=1.5, frames=6, vehicles=3),
        predict=PredictSettings(warn_s=1.5),
    )
    a = sequence_arrays(5, 0, p)
    assert a["ttc_true"].shape == (6,)
    s = TwinEvalSettings(critical_thw=1.5, predict=PredictSettings(warn_s=1.5), n_boot=50)
    f = evaluate_sequence(a, TwinPass(grid, (0.5, 1.0), ["naive"], {}, s))
    assert {"ttc", "ttc_true", "flagged_ttc"} <= set(f.columns)
    # TTC <= THW wherever the THW is within the horizon (the same cells at tau = 0)
    within = f["thw"] <= s.predict.horizon_s
    assert (f.loc[within, "ttc"] <= f.loc[within, "thw"] + 1e-9).all()
    g = evaluate_sequence(a, TwinPass(grid, (0.5, 1.0), ["naive"], {}, s), include_ego=False)
    assert EGO not in set(g["method"]) and len(g) == len(f) // 2
    # a map warns a reaction time before the critical level; the label stays at the critical level
    r = evaluate_sequence(a, TwinPass(grid, (0.5, 1.0), ["naive"], {}, replace(s, reaction_s=1.0)))
    assert (r["flagged"] == (r["thw"] < s.critical_thw + 1.0)).all()
    assert (r["critical"] == (r["thw_true"] < s.critical_thw)).all()


def test_the_summary_holds_the_predictive_lead() -> None:
    from traffictwin.twin.evaluation import TwinEvalSettings
    from traffictwin.twin.summary import summarise

    s = summarise(
        _pred_table(),
        ["twin"],
        10.0,
        TwinEvalSettings(
            critical_thw=1.5, predict=PredictSettings(warn_s=1.5), n_boot=100, horizon_s=0.3
        ),
    )
    assert s["twin"]["occluded"]["predictive"]["lead_vs_thw_s_mean"] == pytest.approx(0.3)
