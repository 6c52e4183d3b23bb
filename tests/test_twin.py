"""The cooperative twin: simulator sequences, the twin's fusion, risk from a map, the evaluation, the stages."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from _acceptance import thresholds
from conftest import run_record

from traffictwin.evidential.dempster import dempster
from traffictwin.evidential.warp import warp_masses
from traffictwin.grid import GridSpec
from traffictwin.risk.metric import headway, occupancy_distance
from traffictwin.sim.cooperative import (
    HAZARD_ID,
    CooperativeConfig,
    ego_sees_hazard,
    generate_cooperative_sequence,
    sequence_kind,
)
from traffictwin.sim.lidar import LidarSpec
from traffictwin.twin.data import TwinDataParams, sequence_arrays, twin_risk_config
from traffictwin.twin.evaluation import EGO, TwinEvalSettings
from traffictwin.twin.fuse import Twin, TwinInputError, TwinOptions, build_twin
from traffictwin.twin.predict import PredictSettings
from traffictwin.twin.summary import lead_times, step_ms_medians, summarise
from traffictwin.twin.targets import targets

TWIN = thresholds("twin")

GRID = GridSpec(rows=64, cols=48, cell=0.5)
LIDAR = LidarSpec(azimuth_res_deg=0.8, max_range=50.0)
CFG = CooperativeConfig(critical_thw=1.5, frames=6, vehicles=3)


def _masses(rng: np.random.Generator, shape=(64, 48)) -> np.ndarray:
    """Random masses on the simplex (2, H, W) float32 with some unknown."""
    a = rng.dirichlet([1.0, 1.0, 1.0], size=shape)  # free, occ, unknown
    return np.moveaxis(a[..., :2], -1, 0).astype(np.float32)


# ------------------------------------------------------------------------------------ simulator
def test_sequences_are_deterministic_and_alternate_kinds() -> None:
    a = generate_cooperative_sequence(3, 4, CFG)
    b = generate_cooperative_sequence(3, 4, CFG)
    assert np.array_equal(
        np.stack([f.poses for f in a.frames]), np.stack([f.poses for f in b.frames])
    )
    assert [sequence_kind(i, 0.5) for i in range(4)] == ["open", "occluded", "open", "occluded"]
    assert [sequence_kind(i, 1.0) for i in range(3)] == ["occluded"] * 3
    assert a.roles == ("ego", "oncoming", "follower") and len(a.frames) == 6
    f = a.frames[0]
    assert f.poses.shape == (3, 3) and f.path.shape[1] == 2
    # every vehicle and the hazard are boxes of the scene
    assert set(a.vehicle_ids) <= set(f.boxes.ids) and HAZARD_ID in set(f.boxes.ids)


def test_occluded_sequences_hide_the_hazard_from_the_ego_at_the_critical_onset() -> None:
    cfg = replace(CFG, frames=30)
    seqs = [generate_cooperative_sequence(11, i, cfg, LIDAR) for i in (1, 3, 5)]  # occluded indices
    assert [s.kind for s in seqs] == ["occluded"] * 3
    assert sum(s.hidden_at_onset for s in seqs) >= 2
    for seq in seqs:
        assert (
            0 < seq.onset_frame < 30
        )  # the ego reaches a time headway < 1.5 s within the sequence
        assert seq.hidden_at_onset == (not ego_sees_hazard(seq, LIDAR, seq.onset_frame))
    # without a lidar nothing is selected: the first draw is kept
    assert generate_cooperative_sequence(11, 1, cfg).attempts == 1


def test_cooperative_config_rejects_bad_values() -> None:
    with pytest.raises(ValueError, match="vehicles must be >= 2"):
        CooperativeConfig(critical_thw=1.5, vehicles=1)
    with pytest.raises(ValueError, match="ego_speed"):
        CooperativeConfig(critical_thw=1.5, ego_speed=(5.0, 2.0))
    with pytest.raises(ValueError, match="templates"):
        CooperativeConfig(critical_thw=1.5, templates=("roundabout",))


def test_sequence_arrays_layout() -> None:
    p = TwinDataParams(grid=GRID, lidar=LIDAR, scenario=CFG, predict=PredictSettings(warn_s=1.5))
    a = sequence_arrays(5, 0, p)
    assert a["maps"].shape == (6, 3, 2, 64, 48) and a["maps"].dtype == np.float32
    assert np.all(a["maps"] >= 0) and np.all(a["maps"].sum(2) <= 1 + 1e-5)
    assert a["noise_z"].shape == (6, 3, 3) and np.all(a["noise_z"][:, 0] == 0)
    assert np.any(a["noise_z"][:, 1:] != 0)
    assert a["path"].shape[0] == 6 and a["hazard_seen"].shape == (6, 3)
    # the ego's path starts at its own reference point, ahead along +x at first
    assert np.allclose(a["path"][:, 0], 0.0, atol=1e-6)
    b = sequence_arrays(5, 0, p)
    assert all(np.array_equal(a[k], b[k]) for k in a)


# ------------------------------------------------------------------------------------ risk from a map
def test_occupancy_distance_hand_computed() -> None:
    g = GridSpec(rows=64, cols=48, cell=0.5)
    cfg = twin_risk_config()
    occ = np.zeros(g.shape, bool)
    assert occupancy_distance(occ, g, cfg) == np.inf
    # one cell straight ahead, centre x = (32 - r - 0.5) * 0.5 ; row 8 -> x = 11.75 m, y = 0.25 m
    occ[8, 23] = True
    x, y = g.rc_to_xy(8, 23)
    assert (x, y) == (11.75, 0.25)
    assert occupancy_distance(occ, g, cfg) == pytest.approx(11.75 - cfg.subject_length / 2)
    assert headway(11.75 - 2.4, 5.0) == pytest.approx((11.75 - 2.4) / 5.0)
    assert headway(3.0, 0.0) == np.inf
    # a cell beside the lane (|y| > lane_width / 2) does not count; a wider corridor counts it
    side = np.zeros(g.shape, bool)
    side[8, 24 - 6] = True  # y = (24 - 18 - 0.5) * 0.5 = 2.75 m
    assert occupancy_distance(side, g, cfg) == np.inf
    assert np.isfinite(occupancy_distance(side, g, twin_risk_config(corridor_margin=1.2)))
    # the ego's own footprint (other vehicles' maps show it) is ignored
    own = np.zeros(g.shape, bool)
    own[29, 23] = True  # x = 1.25 m, inside the 4.8 m long car
    assert occupancy_distance(own, g, cfg) == np.inf
    # a curved path: a cell on the path's arc is found at its arc length
    path = np.stack([np.linspace(0, 20, 81), np.zeros(81)], 1)
    path[41:, 1] = np.linspace(0, 5, 40)  # bends left after 10 m
    with pytest.raises(ValueError, match="corridor"):
        occupancy_distance(occ, g, replace(cfg, region="paper"))
    assert np.isfinite(occupancy_distance(occ, g, cfg, path=path, lane_width=3.5))


# ------------------------------------------------------------------------------------ the twin
def test_dempster_twin_is_independent_of_vehicle_order() -> None:
    rng = np.random.default_rng(0)
    maps = np.stack([_masses(rng) for _ in range(4)])
    poses = np.array([[0, 0, 0], [2.0, -1.0, 0.1], [-3.0, 0.5, -0.2], [1.0, 4.0, 0.3]])
    a = build_twin(maps, poses, GRID, TwinOptions("naive"))
    perm = [0, 3, 1, 2]
    b = build_twin(maps[perm], poses[perm], GRID, TwinOptions("naive"))
    np.testing.assert_allclose(a.masses, b.masses, atol=2e-5)
    # = Dempster's rule applied by hand, in either grouping
    w = [warp_masses(maps[k], poses[k], GRID) for k in range(1, 4)]
    by_hand = dempster(dempster(dempster(maps[0], w[0]), w[1]), w[2])
    np.testing.assert_allclose(a.masses, by_hand, atol=2e-5)
    other = dempster(maps[0], dempster(w[2], dempster(w[1], w[0])))
    np.testing.assert_allclose(a.masses, other, atol=2e-5)
    assert a.used.all() and a.masses.dtype == np.float32
    # sequential and reference strategies agree for a noisy-pose method (no registration)
    c = build_twin(maps, poses, GRID, TwinOptions("naive", strategy="sequential"))
    np.testing.assert_allclose(a.masses, c.masses, atol=2e-5)


def test_a_vehicle_whose_registration_fails_is_left_out() -> None:
    rng = np.random.default_rng(1)
    ego = _masses(rng)
    blank = np.zeros_like(
        ego
    )  # nothing known: no estimate can be accepted, the pose explains nothing
    maps = np.stack([ego, blank, ego])
    poses = np.zeros((3, 3))
    step = build_twin(maps, poses, GRID, TwinOptions("registered"))
    assert step.used.tolist() == [True, False, True]
    t = Twin(GRID, TwinOptions("registered"))
    t.update(0.0, maps, poses)
    assert (t.left_out, t.fused) == (1, 1)


@pytest.mark.parametrize(
    ("maps_shape", "poses", "match"),
    [
        ((1, 2, 64, 48), np.zeros((1, 3)), "at least two vehicles"),
        ((2, 2, 32, 48), np.zeros((2, 3)), "differs from the grid"),
        ((2, 2, 64, 48), np.zeros((3, 3)), "poses: expected"),
        (
            (2, 2, 64, 48),
            np.array([[0, 0, 0], [np.nan, 0, 0]]),
            r"vehicle\(s\) \[1\] have a missing",
        ),
    ],
)
def test_bad_twin_inputs_name_the_input(maps_shape, poses, match) -> None:
    with pytest.raises(TwinInputError, match=match):
        build_twin(np.zeros(maps_shape, np.float32), poses, GRID, TwinOptions("naive"))


def test_twin_rejects_nan_masses_and_time_out_of_order() -> None:
    maps = np.zeros((2, 2, 64, 48), np.float32)
    bad = maps.copy()
    bad[1, 0, 3, 3] = np.nan
    with pytest.raises(TwinInputError, match=r"maps: vehicle\(s\) \[1\] have NaN"):
        build_twin(bad, np.zeros((2, 3)), GRID, TwinOptions("naive"))
    t = Twin(GRID, TwinOptions("naive"))
    t.update(0.1, maps, np.zeros((2, 3)))
    with pytest.raises(TwinInputError, match="not after the previous one"):
        t.update(0.1, maps, np.zeros((2, 3)))
    with pytest.raises(ValueError, match="needs the model"):
        build_twin(maps, np.zeros((2, 3)), GRID, TwinOptions("learned"))
    with pytest.raises(ValueError, match="unknown"):
        TwinOptions("bogus")


# ------------------------------------------------------------------------------------ evaluation
def _frame_table() -> pd.DataFrame:
    """Two occluded sequences, 5 frames at 10 Hz; frames 2-4 truly critical. Sequence 0: the twin
    flags 2-4, the ego 4 only; sequence 1: both flag 3-4; the twin also flags frame 0 of sequence 1
    (a false alarm)."""
    rows = []
    flags = {
        (0, "twin"): [0, 0, 1, 1, 1],
        (0, EGO): [0, 0, 0, 0, 1],
        (1, "twin"): [1, 0, 0, 1, 1],
        (1, EGO): [0, 0, 0, 1, 1],
    }
    for (seq, m), fl in flags.items():
        for t, f in enumerate(fl):
            rows.append(
                {
                    "sequence": seq,
                    "kind": "occluded",
                    "hazard": "pedestrian",
                    "vehicles": 3,
                    "frame": t,
                    "time": t / 10,
                    "method": m,
                    "thw": 1.0 if f else 3.0,
                    "thw_true": 1.0 if t >= 2 else 3.0,
                    "left_out": 0,
                    "step_ms": 10.0,
                }
            )
    f = pd.DataFrame(rows).sort_values(["sequence", "frame", "method"], kind="stable")
    f["critical"] = f["thw_true"] < 1.5
    f["flagged"] = f["thw"] < 1.5
    return f


def test_lead_times_and_summary_hand_computed() -> None:
    f = _frame_table()
    lt = lead_times(f, "twin", fps=10.0).set_index("sequence")
    assert lt.loc[0, "lead_s"] == pytest.approx(0.2)  # twin at 0.2 s, ego at 0.4 s
    assert lt.loc[1, "lead_s"] == pytest.approx(0.0)
    s = summarise(
        f,
        ["twin"],
        10.0,
        TwinEvalSettings(critical_thw=1.5, predict=PredictSettings(warn_s=1.5), n_boot=200),
    )
    occ = s["twin"]["occluded"]
    assert occ["recall"] == pytest.approx(
        5 / 6
    )  # critical frames 2,3,4 x 2 sequences; missed: seq 1 frame 2
    assert s[EGO]["occluded"]["recall"] == pytest.approx(3 / 6)
    assert occ["recall_vs_ego"] == pytest.approx(2 / 6)
    assert occ["false_alarm_rate"] == pytest.approx(1 / 4)  # frames 0, 1 of two sequences
    # horizon 2 s: sequence 1's frame-0 warning is 0.2 s before the onset -> an early warning
    # seq 0: twin 0.2 s, ego 0.4 s; seq 1: twin 0.0 s, ego 0.3 s -> 0.2 and 0.3 s
    assert occ["lead_vs_ego_s_mean"] == pytest.approx(0.25)
    assert occ["lead_vs_ego_s_median"] == pytest.approx(0.25)
    assert occ["lead_s_median"] == pytest.approx(0.1)  # leads 0.0 and 0.2 s
    assert occ["warned_before_onset_share"] == pytest.approx(0.5)
    assert occ["false_alarm_share"] == 0.0  # every warning has an episode within 2 s
    assert occ["recall_ci"][0] <= occ["recall"] <= occ["recall_ci"][1]
    short = summarise(
        f,
        ["twin"],
        10.0,
        TwinEvalSettings(
            critical_thw=1.5, predict=PredictSettings(warn_s=1.5), n_boot=200, horizon_s=0.1
        ),
    )
    assert short["twin"]["occluded"]["false_alarm_share"] == pytest.approx(1 / 10)
    assert short["twin"]["occluded"]["lead_vs_ego_s_mean"] == pytest.approx(0.1)  # = the target's
    t = targets({"D": {"methods": s}}, "twin", "D", TWIN)
    assert t["occluded_recall"]["met"] is False
    assert t["occluded_median_lead_vs_ego"]["met"] is False
    assert t["open_false_alarms_frame_noise"]["value"] is None  # no open sequences here
    assert targets({}, "twin", "D", TWIN) == {"configuration": "D", "evaluated": False}
    assert "step_ms_median" not in occ  # wall time: the stage's run record, not twin.json


def test_step_ms_medians_per_method_and_kind() -> None:
    f = _frame_table()
    twin = f["method"] == "twin"
    f.loc[twin, "step_ms"] = np.arange(twin.sum(), dtype=float)  # 0..9 over both sequences
    f.loc[twin & (f["sequence"] == 1), "kind"] = "open"  # sequence 1's frames: 5..9
    assert step_ms_medians(f, ["twin"]) == {"twin": {"occluded": 2.0, "open": 7.0, "all": 4.5}}


# ------------------------------------------------------------------------------------ stages (ci DAG)
@pytest.mark.slow
def test_twin_stages_on_ci_dag(ci_dag: Path) -> None:
    from traffictwin.io.shards import Dataset

    ds = Dataset(ci_dag / "data" / "twin", kind="twin")
    assert len(ds.shard_indices("test")) == 2 and len(ds.shard_indices("validation")) == 2
    data = json.loads((ci_dag / "reports" / "metrics" / "twin_data.json").read_text())
    assert data["twin_data/sequences"] == 2 and data["twin_data/vehicles"] == 3
    # every sequence holds one hazard of HAZARDS; the hazards present are the ones reported
    from traffictwin.sim.cooperative import HAZARDS

    assert sum(data[f"twin_data/{h}"] for h in HAZARDS) == 2
    assert 0 <= data["twin_data/follower_critical_frame_share"] <= 1
    assert data["twin_data/validation_sequences"] == 2
    m = json.loads((ci_dag / "reports" / "metrics" / "twin.json").read_text())
    params = __import__("yaml").safe_load((ci_dag / "params.yaml").read_text())
    # the configurations of twin.configurations (D), in the order of `configurations`
    assert list(m["configurations"]) == [
        c for c in params["configurations"] if c in params["twin"]["configurations"]
    ]
    for c, entry in m["configurations"].items():
        assert EGO in entry["methods"] and "naive" in entry["methods"], c
        for kind in ("occluded", "open", "all"):
            assert entry["methods"]["naive"][kind]["frames"] >= 6
    frames = pd.read_csv(ci_dag / "reports" / "twin_eval_frames.csv")
    assert set(frames["method"]) >= {EGO, "naive", "registered", "learned"}
    # every frame of both sequences is evaluated for every method at every configuration
    d = frames[(frames["configuration"] == "D") & (frames["method"] == "naive")]
    per_frame = d[d["noise"] == "frame"]
    assert len(per_frame) == 2 * params["twin"]["frames"] and "step_ms" not in frames
    # the kinds of twin.bias_kinds again under the persistent pose bias
    bias = d[d["noise"] == "bias"]
    assert set(bias["kind"]) == set(params["twin"]["bias_kinds"])
    assert len(bias) == params["twin"]["frames"] * len(params["twin"]["bias_kinds"])
    pb = m["configurations"]["D"]["pose_bias"]
    assert pb["bias_share"] == params["twin"]["bias_share"]
    assert pb["methods"]["naive"]["open"]["false_alarm_share"] is not None
    occ = m["configurations"]["D"]["methods"]["naive"]["occluded"]
    ref = m["configurations"]["D"]["always_warns"]["occluded"]
    assert ref["episodes"] == occ["episodes"] and ref["lead_s_mean"] >= occ["lead_s_mean"]
    assert "always_warns_value" in m["targets"]["registration_lead_above_naive"]
    naive = m["configurations"]["D"]["methods"]["naive"]
    reported = set(naive["occluded"]["by_hazard"]) | set(naive["open"]["by_hazard"])
    assert reported == {h for h in HAZARDS if data[f"twin_data/{h}"]}
    # the predictive rule, chosen on the 2 validation sequences (never evaluated: ids 2 and 3)
    pr = m["predictive_rule"]
    assert pr["validation_sequences"] == 2 and len(pr["candidates"]) >= 2
    assert sum(c["selected"] for c in pr["candidates"].values()) == 1
    assert set(frames["sequence"]) == {0, 1}
    # every other vehicle's risk: its own map and its view of each twin
    veh = m["configurations"]["D"]["vehicles"]
    assert {k: e["role"] for k, e in veh.items()} == {"1": "oncoming", "2": "follower"}
    assert set(veh["2"]["methods"]) >= {"own", "naive", "learned"}
    vf = pd.read_csv(ci_dag / "reports" / "twin_vehicle_frames.csv")
    assert set(vf["method"]) == {"own"} | set(frames["method"]) - {EGO}
    n_cfg = len(m["configurations"])
    assert len(vf) == n_cfg * 2 * params["twin"]["frames"] * 2 * len(set(frames["method"]))
    assert occ["episodes"] >= 1 and occ["lead_vs_ego_s_median"] is not None
    data_hidden = data["twin_data/occluded_hidden_before_onset_s_median"]
    assert data_hidden is not None and data_hidden >= 0
    rec = run_record(ci_dag, "evaluate_twin")
    assert rec["step_ms_median"]["D"]["naive"]["all"] > 0
    # the classical registration, computed beforehand in a pool, still counts in its step time
    assert (
        rec["step_ms_median"]["D"]["registered"]["all"] > rec["step_ms_median"]["D"]["naive"]["all"]
    )
    timeline = pd.read_csv(ci_dag / "reports" / "plots" / "twin_timeline.csv")
    assert set(timeline["series"]) >= {"truth", "ego map"} and {"time", "thw"} <= set(timeline)
    for fig in ("twin_map", "twin_timeline"):
        assert (ci_dag / "reports" / "figures" / f"{fig}.png").exists()
    assert m["targets"]["configuration"] == params["twin"]["target_configuration"]
    for key in (
        "occluded_median_lead_vs_ego",
        "open_false_alarms_pose_bias",
        "predictive_warns_earlier_than_thw",
        "predictive_no_more_false_alarms",
    ):
        assert {"value", "ci", "met"} <= set(m["targets"][key]), key
    # the predictive measure beside the THW, on the same frames
    assert {"ttc", "ttc_true", "flagged_ttc"} <= set(frames)
    assert "lead_vs_thw_s_mean" in m["configurations"]["D"]["methods"]["naive"]["all"]["predictive"]
    from traffictwin.twin.data import INF_ARRAYS

    shard = Dataset(ci_dag / "data" / "twin", kind="twin", allow_inf=INF_ARRAYS).load_shard(0)
    assert shard["ttc_true"].shape == shard["thw_true"].shape


def test_learned_twin_tables_do_not_follow_the_worker_count(ci_dag: Path) -> None:
    """The learned registration (torch) in two worker processes gives the ci run's sequences the
    same tables as one process (the models reach the workers; the order is kept)."""
    import torch
    import yaml

    from traffictwin.fusion.config import MIXED, grid_config
    from traffictwin.fusion.registration_io import load_registration_model
    from traffictwin.io.shards import Dataset
    from traffictwin.twin.config import twin_config
    from traffictwin.twin.data import INF_ARRAYS
    from traffictwin.twin.evaluation import TwinPass, evaluate_sequences_tables

    cfg = yaml.safe_load((ci_dag / "params.yaml").read_text())
    grid, settings = grid_config(cfg), twin_config(cfg).settings()
    model = load_registration_model(
        ci_dag / "models" / "registration" / "learned" / "model.ckpt",
        expected_grid=grid,
        expected_cfg=MIXED,
    )
    ds = Dataset(ci_dag / "data" / "twin", kind="twin", allow_inf=INF_ARRAYS)
    seqs = [ds.load_shard(i) for i in ds.shard_indices("test")]
    models = {"learned": {"registration": model}}
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        tables = [
            evaluate_sequences_tables(
                seqs,
                TwinPass(grid, (5.0, 20.0), ["learned"], models, settings, workers=w),
                [None] * len(seqs),
            )
            for w in (1, 2)
        ]
    finally:
        torch.set_num_threads(threads)
    for one, two in zip(*tables):
        pd.testing.assert_frame_equal(
            one.frames.drop(columns="step_ms"), two.frames.drop(columns="step_ms")
        )
        assert (one.frames["method"] == "learned").any()


# ------------------------------------------------------------------------------------ report and figures
def test_report_section_shows_the_metrics_file(tmp_path: Path) -> None:
    from traffictwin.io.jsonio import json_clean
    from traffictwin.report.model import ReportInputs, Sources
    from traffictwin.twin import report_section as rs

    f = _frame_table()
    summary = summarise(
        f,
        ["twin"],
        10.0,
        TwinEvalSettings(critical_thw=1.5, predict=PredictSettings(warn_s=1.5), n_boot=200),
    )
    m = {
        "configurations": {"D": {"methods": summary}},
        "targets": targets({"D": {"methods": summary}}, "twin", "D", TWIN),
    }
    (tmp_path / "metrics").mkdir()
    (tmp_path / "metrics" / "twin.json").write_text(json.dumps(json_clean(m)))
    src = Sources(ReportInputs(reports_dir=tmp_path, profile="ci", seed=1, git_commit="x"))
    sec = rs.section(src, [])
    tables = {t.anchor: t for t in sec.tables}
    assert list(tables) == ["twin-maps"]
    occ = tables["twin-maps"]
    # the targets are judged in the acceptance table of the index: one line points there
    assert "twin-targets" not in tables
    assert sum("(../README.md#acceptance-thresholds)" in p for p in sec.paragraphs) == 1
    rows = {r[1].text: r for r in occ.rows}
    assert set(rows) == {rs.LABELS["ego"], "twin"}
    assert rows["twin"][2].src == "metrics/twin.json#configurations.D.methods.twin.occluded.recall"
    assert rows["twin"][2].value == pytest.approx(5 / 6)
    assert rows["twin"][6].value == pytest.approx(0.25)  # median lead over the ego map (s)
    assert rows["twin"][10].src.endswith("methods.twin.open.false_alarm_share")
    assert [c.text for c in rows[rs.LABELS["ego"]][4:8]] == ["—"] * 4  # no gain over itself
    # the rest of twin.json (each hazard kind, the predictive warnings): the appendix
    from pipelines.report import providers
    from traffictwin.report import render as R

    report = R.write_report(src.inputs, providers({}))
    appendix = next(s for s in report.sections if s.title.startswith("Appendix"))
    assert "reports/metrics/twin.json" in [t.title for t in appendix.tables]
    # no metrics file: n/a cells and a hint, never an error
    empty = rs.section(
        Sources(ReportInputs(reports_dir=tmp_path / "none", profile="ci", seed=1, git_commit="x")),
        [],
    )
    assert "missing" in empty.paragraphs[-1]


def test_timeline_figure_plots_the_table() -> None:
    from traffictwin.twin.figure_inputs import THW_CAP, pick_timeline_sequence
    from traffictwin.twin.figures import timeline_figure

    f = _frame_table()
    f.insert(0, "configuration", "D")
    f["ego_sees_hazard"] = f["flagged"]
    f = f.replace({"method": {"twin": "learned"}})
    seq = pick_timeline_sequence(f, "D", "learned", 10.0)
    assert (
        seq == 0
    )  # leads 0.2 / 0.0 s (inside the episode): both 0.1 s off the median, lowest index
    # warnings from 0.2 s before the onset count: leads 0.2 s (sequence 0: twin 0.2, ego 0.4),
    # 0.3 s (sequence 1: twin 0.0, ego 0.3) and 0.4 s (sequence 2: twin 0.0, ego 0.4) -> the
    # median one is sequence 1 (the largest lead would be sequence 2)
    g = f[f["sequence"] == 1].assign(sequence=2)
    g.loc[g["method"] == "learned", "flagged"] = True
    g.loc[g["method"] == EGO, "flagged"] = [False, False, False, False, True]
    three = pd.concat([f, g])
    assert pick_timeline_sequence(three, "D", "learned", 10.0, horizon_s=0.2) == 1
    fig = timeline_figure(f, "D", "learned", seq, 1.5, 2.5)
    ax = fig.axes[0]
    lines = {ln.get_label(): ln for ln in ax.get_lines()}
    assert set(lines["critical: THW < 1.5 s"].get_ydata()) == {1.5}
    assert set(lines["warning: THW < 2.5 s"].get_ydata()) == {2.5}
    truth = f[(f["sequence"] == 0) & (f["method"] == EGO)]
    np.testing.assert_allclose(lines["truth"].get_ydata(), np.minimum(truth["thw_true"], THW_CAP))
    np.testing.assert_allclose(lines["twin (learned)"].get_ydata(), [3.0, 3.0, 1.0, 1.0, 1.0])
    assert ax.get_xlabel() == "time (s)" and "(s" in ax.get_ylabel()
    with pytest.raises(ValueError, match="twin.figure.sequence"):
        pick_timeline_sequence(f, "D", "learned", 10.0, sequence=7)


def test_twin_map_figure_shows_every_vehicle(tmp_path: Path) -> None:
    from traffictwin.twin.figure_inputs import TwinSnapshot, twin_snapshot
    from traffictwin.twin.figures import twin_map_figure

    p = TwinDataParams(grid=GRID, lidar=LIDAR, scenario=CFG, predict=PredictSettings(warn_s=1.5))
    a = sequence_arrays(5, 1, p)
    snap = twin_snapshot(
        a,
        GRID,
        (5.0, 20.0),
        "naive",
        None,
        TwinEvalSettings(critical_thw=1.5, predict=PredictSettings(warn_s=1.5)),
    )
    assert snap.contributions.shape == a["maps"].shape[1:]
    # the snapshot as evaluate_twin keeps it (an .npz) and plot_data reads it back
    from traffictwin.io.figure_inputs import read_arrays_with_meta, write_arrays_with_meta

    write_arrays_with_meta(tmp_path / "snap.npz", snap.arrays(), {"sequence": 5})
    arrays, meta = read_arrays_with_meta(tmp_path / "snap.npz")
    back = TwinSnapshot.from_arrays(arrays)
    assert meta == {"sequence": 5}
    assert back.frame == snap.frame and isinstance(back.frame, int)
    for k in ("rel", "true_rel", "masses", "poses", "used", "contributions"):
        np.testing.assert_array_equal(getattr(back, k), getattr(snap, k))
    fig = twin_map_figure(back, GRID, 5.0, "naive", "D")
    titles = [ax.get_title() for ax in fig.axes]
    assert titles[0].startswith("twin (naive)") and len(titles) == 4
    assert titles[1].startswith("vehicle 0 (ego)") and "used" in titles[2]
    # the dotted circle in plain words: the configuration's pose error bound, in metres
    head = fig.get_suptitle()
    assert "pose error bound r = 5 m" in head and "98 % of the noisy" in head
    from traffictwin.report.colours import LEGEND, map_extent, masses_to_rgb

    assert all(ax.get_xlabel() == "y (m, + = left)" for ax in fig.axes)
    assert all(ax.get_ylabel() == "x (m, forward)" for ax in fig.axes)
    # every map in the shared colour map, in metres, and the colour map's legend
    ext = list(map_extent(GRID.rows, GRID.cols, GRID.cell))
    assert all(ax.get_images()[0].get_extent() == ext for ax in fig.axes)
    np.testing.assert_allclose(
        fig.axes[1].get_images()[0].get_array(),
        masses_to_rgb(a["maps"][max(0, int(a["onset_frame"])), 0]),
    )
    (legend,) = fig.legends
    assert [t.get_text() for t in legend.get_texts()] == [label for label, _ in LEGEND]
    # vehicle markers: one colour each, none of them a colour of the mass map
    from matplotlib.colors import to_rgb

    from traffictwin.twin.figures import VEHICLE_COLOURS

    truth = [ln for ln in fig.axes[0].get_lines() if ln.get_label().endswith("(true)")]
    colours = [to_rgb(ln.get_color()) for ln in truth]
    assert colours == [to_rgb(c) for c in VEHICLE_COLOURS[:3]]
    for c in colours:
        assert all(np.abs(np.subtract(c, ref)).max() > 0.2 for _, ref in LEGEND), c


# ------------------------------------------------------------------------------------ CLI
def _write_maps(tmp_path: Path, cells=(0.5, 0.5, 0.5)) -> tuple[list[str], list[str]]:
    a = sequence_arrays(
        5,
        0,
        TwinDataParams(grid=GRID, lidar=LIDAR, scenario=CFG, predict=PredictSettings(warn_s=1.5)),
    )
    paths, poses = [], []
    for k in range(3):
        p = tmp_path / f"v{k}.npz"
        np.savez(p, m_free=a["maps"][3, k, 0], m_occ=a["maps"][3, k, 1], cell=cells[k])
        paths.append(str(p))
        poses.append("--pose=" + ",".join(f"{v:.6f}" for v in a["poses"][3, k]))
    return paths, poses


def test_cli_twin_builds_a_twin_and_refuses_bad_input(tmp_path: Path, capsys) -> None:
    from traffictwin.cli import main

    paths, poses = _write_maps(tmp_path)
    out = tmp_path / "twin"
    assert main(["twin", *paths, *poses, "--method", "naive", "-o", str(out)]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["vehicles"] == 3 and summary["used"] == [True, True, True]
    with np.load(str(out) + ".npz") as z:
        assert z["m_free"].shape == (64, 48) and z["rel_pose_used"].shape == (3, 3)
        assert np.allclose(z["m_free"] + z["m_occ"] + z["u"], 1.0, atol=1e-5)
    assert (tmp_path / "twin.png").exists()

    def err(args: list[str]) -> str:
        assert main(args) == 1
        return capsys.readouterr().err

    assert "at least two maps" in err(["twin", paths[0], poses[0], "-o", str(out)])
    assert "one x,y,yaw per map" in err(["twin", *paths, *poses[:2], "-o", str(out)])
    assert "would overwrite an input" in err(["twin", *paths, *poses, "-o", paths[1]])
    assert "does not use a registration model" in err(
        [
            "twin",
            *paths,
            *poses,
            "--method",
            "naive",
            "--registration-model",
            paths[0],
            "-o",
            str(out),
        ]
    )
    assert "needs a registration model" in err(
        ["twin", *paths, *poses, "--method", "learned", "-o", str(out)]
    )
    (tmp_path / "bad").mkdir()
    bad, bad_poses = _write_maps(tmp_path / "bad", cells=(0.5, 0.4, 0.5))
    assert "cell size 0.4 m differs" in err(["twin", *bad, *bad_poses, "-o", str(out)])
