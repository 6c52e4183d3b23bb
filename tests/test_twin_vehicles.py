"""Risk for every vehicle: each vehicle's view of the twin, its path and truth."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from traffictwin.grid import GridSpec
from traffictwin.sim.cooperative import CooperativeConfig, cooperator_role
from traffictwin.sim.lidar import LidarSpec
from traffictwin.twin.data import TwinDataParams, sequence_arrays
from traffictwin.twin.evaluation import (
    EGO,
    TwinEvalSettings,
    TwinPass,
    evaluate_sequence,
    evaluate_sequence_tables,
    evaluate_sequences_tables,
    map_thw,
)
from traffictwin.twin.fuse import TwinOptions, build_twin
from traffictwin.twin.predict import PredictSettings
from traffictwin.twin.summary import vehicle_summaries
from traffictwin.twin.vehicle_view import vehicle_view

GRID = GridSpec(rows=64, cols=48, cell=0.5)
P = TwinDataParams(
    grid=GRID,
    lidar=LidarSpec(azimuth_res_deg=0.8, max_range=50.0),
    scenario=CooperativeConfig(critical_thw=1.5, frames=6, vehicles=3),
    predict=PredictSettings(warn_s=1.5),
)


def _point_map(x: float, y: float) -> np.ndarray:
    """A map (2, H, W) of GRID: all unknown but one occupied cell at (x, y) m of its frame."""
    m = np.zeros((2, *GRID.shape), np.float32)
    r = int(GRID.rows / 2 - x / GRID.cell - 0.5)
    c = int(GRID.cols / 2 - y / GRID.cell - 0.5)
    m[1, r, c] = 1.0
    return m


def _occupied_xy(m: np.ndarray) -> np.ndarray:
    r, c = np.nonzero(m[1] > 0.5)
    return np.stack(
        [(GRID.rows / 2 - r - 0.5) * GRID.cell, (GRID.cols / 2 - c - 0.5) * GRID.cell], 1
    )


def test_a_vehicle_sees_the_ego_s_object_where_it_is_in_its_own_frame() -> None:
    # the ego sees an object 6 m ahead; vehicle 1 stands 4 m ahead of the ego, same heading:
    # in vehicle 1's view the object is 2 m ahead of it
    maps = np.stack([_point_map(6.0, 0.0), np.zeros((2, *GRID.shape), np.float32)])
    poses = np.array([[0.0, 0.0, 0.0], [4.0, 0.0, 0.0]])
    view = vehicle_view(maps, poses, np.array([True, True]), 1, GRID)
    xy = _occupied_xy(view)
    assert len(xy) >= 1 and np.allclose(xy.mean(0), [2.0, 0.0], atol=GRID.cell)
    # turned by 90 degrees to the left: the object is 2 m to its right (y = -2)
    poses[1] = [4.0, 0.0, np.pi / 2]
    xy = _occupied_xy(vehicle_view(maps, poses, np.array([True, True]), 1, GRID))
    assert np.allclose(xy.mean(0), [0.0, -2.0], atol=GRID.cell)
    # left out of the twin: only its own map
    own = vehicle_view(maps, poses, np.array([True, False]), 1, GRID)
    np.testing.assert_array_equal(own, maps[1])
    with pytest.raises(ValueError, match="vehicle 2"):
        vehicle_view(maps, poses, np.array([True, True]), 2, GRID)


def test_the_reference_s_view_is_the_twin_itself() -> None:
    rng = np.random.default_rng(0)
    a = rng.dirichlet([1.0, 1.0, 1.0], size=(3, *GRID.shape))
    maps = np.moveaxis(a[..., :2], -1, 1).astype(np.float32)
    poses = np.array([[0, 0, 0], [2.0, -1.0, 0.1], [-3.0, 0.5, -0.2]])
    step = build_twin(maps, poses, GRID, TwinOptions("naive"))
    view = vehicle_view(maps, step.poses, step.used, 0, GRID)
    np.testing.assert_allclose(view, step.masses, atol=2e-5)


def test_every_vehicle_has_its_path_and_truth_in_the_data() -> None:
    a = sequence_arrays(5, 0, P)
    T, N = a["maps"].shape[:2]
    assert a["vehicle_path"].shape == (T, N, a["path"].shape[1], 2)
    np.testing.assert_array_equal(a["vehicle_path"][:, 0], a["path"])
    np.testing.assert_array_equal(a["vehicle_thw_true"][:, 0], a["thw_true"])
    np.testing.assert_array_equal(a["vehicle_lane_width"][:, 0], a["lane_width"])
    # every vehicle's path starts at its own reference point, heading along +x
    assert np.allclose(a["vehicle_path"][:, :, 0], 0.0, atol=1e-6)
    assert np.all(a["vehicle_path"][:, :, 1, 0] > 0)
    assert cooperator_role(1) == "oncoming" and cooperator_role(2) == "follower"
    with pytest.raises(ValueError, match="numbered from 1"):
        cooperator_role(0)


def test_evaluate_sequence_tables_reads_every_vehicle_s_risk() -> None:
    a = sequence_arrays(5, 0, P)
    T, N = a["maps"].shape[:2]
    s = TwinEvalSettings(critical_thw=1.5, predict=PredictSettings(warn_s=1.5), n_boot=50)
    run = TwinPass(GRID, (0.5, 1.0), ["naive"], {}, s)
    tables = evaluate_sequence_tables(a, run, vehicles=True)
    pd.testing.assert_frame_equal(  # the ego's table unchanged (but the wall times)
        tables.frames.drop(columns="step_ms"), evaluate_sequence(a, run).drop(columns="step_ms")
    )
    v = tables.vehicles
    assert len(v) == T * (N - 1) * 2 and set(v["method"]) == {EGO, "naive"}
    assert set(v["vehicle"]) == set(range(1, N))
    own = v[v["method"] == EGO].set_index(["frame", "vehicle"])
    for t, k in [(0, 1), (T - 1, 2)]:
        path, lw = a["vehicle_path"][t, k], float(a["vehicle_lane_width"][t, k])
        thw = map_thw(a["maps"][t, k], float(a["speeds"][t, k]), path, lw, GRID, s)
        assert own.loc[(t, k), "thw"] == pytest.approx(thw)
        assert own.loc[(t, k), "thw_true"] == pytest.approx(a["vehicle_thw_true"][t, k])
    assert (v["critical"] == (v["thw_true"] < s.critical_thw)).all()
    assert (v["flagged"] == (v["thw"] < s.warn_thw)).all()
    assert evaluate_sequence_tables(a, run).vehicles.empty  # not asked for


def _without_wall_times(tables: list) -> list[pd.DataFrame]:
    return [t.frames.drop(columns="step_ms") for t in tables] + [t.vehicles for t in tables]


def test_sequences_in_worker_processes_give_the_same_tables() -> None:
    """Two worker processes return every sequence's tables, in the sequences' order, equal to
    one process's (but the wall times)."""
    seqs = [sequence_arrays(5, i, P) for i in range(3)]
    s = TwinEvalSettings(critical_thw=1.5, predict=PredictSettings(warn_s=1.5), n_boot=50)
    one = TwinPass(GRID, (0.5, 1.0), ["naive"], {}, s, workers=1)
    two = TwinPass(GRID, (0.5, 1.0), ["naive"], {}, s, workers=2)
    serial = evaluate_sequences_tables(seqs, one, [None] * 3, vehicles=True)
    pooled = evaluate_sequences_tables(seqs, two, [None] * 3, vehicles=True)
    assert [int(t.frames["sequence"].iloc[0]) for t in pooled] == [
        int(a["sequence"].reshape(-1)[0]) for a in seqs
    ]
    for a, b in zip(_without_wall_times(serial), _without_wall_times(pooled)):
        pd.testing.assert_frame_equal(a, b)
    with pytest.raises(ValueError, match="2 registrations for 3 sequences"):
        evaluate_sequences_tables(seqs, two, [None] * 2)


def test_a_sequence_worker_runs_torch_on_the_parent_s_thread_count() -> None:
    """Torch's float sums follow its intra-op thread count, so each worker process sets the
    parent's (0: torch not loaded in the parent, the worker's default is left)."""
    import signal

    import torch

    from traffictwin.twin.evaluation import _WORKER, _sequence_worker_init

    n, sigint = torch.get_num_threads(), signal.getsignal(signal.SIGINT)
    s = TwinEvalSettings(critical_thw=1.5, predict=PredictSettings(warn_s=1.5))
    run = TwinPass(GRID, (0.5, 1.0), ["naive"], {}, s)
    try:
        _sequence_worker_init(run, 3)
        assert torch.get_num_threads() == 3 and _WORKER["run"] is run
        _sequence_worker_init(run, 0)
        assert torch.get_num_threads() == 3
    finally:
        torch.set_num_threads(n)
        signal.signal(signal.SIGINT, sigint)  # the worker ignores Ctrl-C; this process must not
        _WORKER.clear()


def _vehicle_table() -> pd.DataFrame:
    """Vehicle 2 (a follower) in two sequences of 10 frames at 10 Hz: critical from frame 5;
    its own map warns from frame 5, the twin from frame 3 (0.2 s before the onset)."""
    rows = []
    for seq in (0, 1):
        for m, first in ((EGO, 5), ("twin", 3)):
            for i in range(10):
                rows.append(
                    {
                        "sequence": seq,
                        "kind": "open",
                        "hazard": "pedestrian",
                        "vehicles": 3,
                        "vehicle": 2,
                        "method": m,
                        "frame": i,
                        "time": i / 10,
                        "thw": 1.0 if i >= first else 3.0,
                        "thw_true": 1.0 if i >= 5 else 3.0,
                        "left_out": 0,
                    }
                )
    f = pd.DataFrame(rows)
    f["critical"] = f["thw_true"] < 1.5
    f["flagged"] = f["thw"] < 1.5
    return f


def test_vehicle_summaries_pair_the_twin_with_the_vehicle_s_own_map() -> None:
    out = vehicle_summaries(
        _vehicle_table(),
        ["twin"],
        10.0,
        TwinEvalSettings(
            critical_thw=1.5, predict=PredictSettings(warn_s=1.5), n_boot=50, horizon_s=0.5
        ),
    )
    assert list(out) == ["2"] and out["2"]["role"] == "follower"
    own, twin = out["2"]["methods"]["own"]["all"], out["2"]["methods"]["twin"]["all"]
    assert own["recall"] == 1.0 and twin["recall"] == 1.0
    assert own["lead_s_median"] == pytest.approx(0.0)
    assert twin["lead_s_median"] == pytest.approx(0.2)
    assert twin["lead_vs_ego_s_median"] == pytest.approx(0.2)  # over the vehicle's own map
    assert "by_hazard" not in twin
    assert (
        vehicle_summaries(
            _vehicle_table().iloc[:0],
            ["twin"],
            10.0,
            TwinEvalSettings(critical_thw=1.5, predict=PredictSettings(warn_s=1.5)),
        )
        == {}
    )


def test_every_vehicle_s_risk_is_summarised() -> None:
    v = vehicle_summaries(
        _vehicle_table(),
        ["twin"],
        10.0,
        TwinEvalSettings(critical_thw=1.5, predict=PredictSettings(warn_s=1.5), n_boot=50),
    )
    follower = v["2"]
    assert follower["role"] == "follower" and set(follower["methods"]) == {"own", "twin"}
    assert follower["methods"]["twin"]["all"]["critical_frames"] == 10
    assert follower["methods"]["twin"]["all"]["recall"] == 1.0
