"""Risk data stages: shard contents, splits by scenario, determinism, bad input, ci DAG outputs."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from tests.conftest import composed, run, stage_in_process
from traffictwin.grid import GridSpec
from traffictwin.io.shards import Dataset
from traffictwin.risk.dataset import (
    RiskDataSpec,
    assign_splits,
    frame_table,
    make_shard,
    summarise_frames,
)
from traffictwin.risk.metric import RiskConfig
from traffictwin.sim.camera import StereoCamera
from traffictwin.sim.driving import DrivingConfig

SPEC = RiskDataSpec(
    DrivingConfig(frames=3, warmup=1.0),
    StereoCamera(width=96, height=48),
    GridSpec(128, 96, 0.64),
    RiskConfig(subject_length=4.8, subject_width=1.9),
    1.5,  # critical THW (s)
)


def test_assign_splits_by_sequence():
    s = assign_splits(100, 1)
    assert (s.count("train"), s.count("val"), s.count("test")) == (70, 10, 20)
    assert assign_splits(100, 1) == s and assign_splits(100, 2) != s
    small = assign_splits(3, 0)
    assert sorted(small) == ["test", "train", "val"]
    with pytest.raises(ValueError, match="fractions"):
        assign_splits(10, 0, (0.5, 0.5, 0.5))


def test_assign_splits_stratified_by_situation():
    strata = ["follow"] * 50 + ["cut_in"] * 30 + ["free"] * 20
    s = assign_splits(100, 1, strata=strata)
    assert (s.count("train"), s.count("val"), s.count("test")) == (70, 10, 20)
    for name, n in (("follow", 50), ("cut_in", 30), ("free", 20)):
        part = [sp for sp, st in zip(s, strata) if st == name]
        # every stratum split 70/10/20 up to one sequence
        assert abs(part.count("test") - 0.2 * n) <= 1 and abs(part.count("val") - 0.1 * n) <= 1
    assert assign_splits(100, 1, strata=strata) == s  # deterministic
    tiny = assign_splits(4, 0, strata=["a", "b", "c", "d"])  # strata of one: still 3 splits
    assert set(tiny) == {"train", "val", "test"}
    with pytest.raises(ValueError, match="one stratum per sequence"):
        assign_splits(5, 0, strata=["a"])


def test_make_shard_contents():
    arrays, rows = make_shard(11, 2, SPEC)
    n = len(rows)
    assert n == 3
    assert arrays["left"].shape == (n, 48, 96, 3) and arrays["left"].dtype == np.uint8
    assert arrays["right"].shape == arrays["left"].shape
    assert arrays["disp_gt"].shape == (n, 48, 96) and arrays["disp_gt"].dtype == np.float32
    assert np.all(arrays["disp_gt"] >= 0)
    for r in rows:
        assert r["scenario"] == 2 and r["fault"] in ("none", "delay", "vertical")
        for k in ("risk_thw_corridor", "risk_thw_paper", "risk_thw_fov", "risk_ttc", "risk_wttc"):
            assert 0.0 <= r[k] <= 1.0
        assert r["risk_thw_fov"] <= r["risk_thw_paper"] + 1e-12  # the FOV region is a subset
        # the headline label: corridor THW (s) -> risk, and critical below 1.5 s
        assert r["thw"] == r["thw_corridor"] and r["risk"] == r["risk_thw_corridor"]
        assert r["critical"] == (r["thw"] < 1.5)
    again, _ = make_shard(11, 2, SPEC)
    assert all(np.array_equal(arrays[k], again[k]) for k in arrays)


@pytest.mark.slow
def test_ci_dag_risk_outputs(ci_dag: Path):
    ds = Dataset(ci_dag / "data" / "risk", kind="risk")
    cam = ds.manifest["camera"]
    for k in ("width", "height", "fx", "fy", "cx", "cy", "baseline", "mount_x", "mount_height"):
        assert k in cam
    frames = ds.table("frames.csv")
    need = [
        "frame_id",
        "shard",
        "idx",
        "scenario",
        "split",
        "t",
        "speed",
        "thw",
        "risk",
        "situation",
        "thw_corridor",
        "risk_thw_corridor",
        "risk_thw_paper",
        "risk_thw_fov",
        "risk_ttc",
        "risk_wttc",
        "fault",
    ]
    assert set(need) <= set(frames.columns)
    assert frames.frame_id.is_unique and len(frames) == len(ds)
    # no scenario in two splits; every split present
    assert (frames.groupby("scenario").split.nunique() == 1).all()
    assert set(frames.split) == {"train", "val", "test"}
    sh = ds.load_shard(0)
    assert sh["left"].shape[1:3] == (cam["height"], cam["width"])
    # disparity shards aligned 1:1
    dd = Dataset(ci_dag / "data" / "disparity", kind="disparity")
    assert [s["count"] for s in dd.shards] == [s["count"] for s in ds.shards]
    assert [s["split"] for s in dd.shards] == [s["split"] for s in ds.shards]
    d0 = dd.load_shard(0)["disp_sgm"]
    assert d0.shape == sh["disp_gt"].shape and d0.dtype == np.float32 and d0.min() == -1.0
    dj = json.loads((ci_dag / "reports" / "metrics" / "disparity.json").read_text())
    assert 0 <= dj["all/bad2"] <= 1 and dj["fault_none/bad2"] < 0.1 and 0 < dj["all/density"] <= 1
    orb = pd.read_csv(ci_dag / "data" / "orb" / "orb.csv")
    assert list(orb.columns[:6]) == [
        "frame_id",
        "n_matches",
        "n_reliable",
        "mean_dx",
        "mean_dy",
        "outlier",
    ]
    assert len(orb) == len(frames) and orb.outlier.dtype == bool
    oj = json.loads((ci_dag / "reports" / "metrics" / "orb.json").read_text())
    assert oj["vertical/detection_rate"] > 0.5
    for f in ("risk_metric_example.png", "stereo_example.png", "orb_outlier_example.png"):
        assert (ci_dag / "reports" / "figures" / f).stat().st_size > 1000


def test_frame_table_and_summary():
    rows = {i: make_shard(11, i, SPEC)[1] for i in (1, 0)}  # completion order does not matter
    df = frame_table(rows, ["train", "test"])
    assert list(df.columns[:5]) == ["frame_id", "shard", "idx", "scenario", "split"]
    assert df.frame_id.tolist() == list(range(6)) and df.shard.tolist() == [0, 0, 0, 1, 1, 1]
    assert df.split.tolist() == ["train"] * 3 + ["test"] * 3
    assert df.idx.tolist() == [0, 1, 2, 0, 1, 2] and (df.scenario == df.shard).all()
    s = summarise_frames(df, SPEC.critical_thw_s)
    assert s["all/frames"] == 6 and s["train/frames"] == 3 and "val/frames" not in s
    assert s["all/sequences"] == 2
    assert s["all/critical_share"] == pytest.approx(float((df.thw < 1.5).mean()))
    for region in ("corridor", "paper", "fov"):
        share = float((df[f"risk_thw_{region}"] > 1 / 30).mean())
        assert s[f"all/critical_share_{region}"] == pytest.approx(share)
        train = df[df.split == "train"]
        assert s[f"train/critical_share_{region}"] == pytest.approx(
            float((train[f"risk_thw_{region}"] > 1 / 30).mean())
        )
    for sit, part in df.groupby("situation"):
        assert s[f"situation/{sit}/critical_share"] == pytest.approx(float(part.critical.mean()))
    assert sum(v for k, v in s.items() if k.startswith("all/fault_share_")) == pytest.approx(1.0)
    assert sum(v for k, v in s.items() if k.startswith("all/sequences_")) == 2


def test_shard_compresslevel_is_checked_and_left_out_of_the_data_version():
    """``risk_data.compresslevel`` (zlib level of the shards) must be 0..9; it changes the files'
    bytes, not the arrays, so the data version's recorded params leave it out (like ``workers``)."""
    from omegaconf import OmegaConf

    from pipelines.generate_risk import read_config, recorded_params
    from traffictwin.config import ConfigError

    cfg = OmegaConf.create(composed())
    rd, _, _ = read_config(cfg)
    assert rd.compresslevel == cfg.risk_data.compresslevel
    assert "compresslevel" not in recorded_params(cfg) and "workers" not in recorded_params(cfg)
    assert "sequences" in recorded_params(cfg)
    for bad in (10, -1, "fast"):
        cfg.risk_data.compresslevel = bad
        with pytest.raises(ConfigError, match="compresslevel"):
            read_config(cfg)


@pytest.mark.slow
def test_generate_risk_is_deterministic_and_rejects_bad_input(repo_copy: Path):
    py = sys.executable
    run([py, "-m", "pipelines.generate_risk"], repo_copy)
    m1 = json.loads((repo_copy / "data" / "risk" / "manifest.json").read_text())
    run([py, "-m", "pipelines.generate_risk"], repo_copy)
    m2 = json.loads((repo_copy / "data" / "risk" / "manifest.json").read_text())
    assert m1 == m2  # byte-identical shards (SHA-256 in the manifest) and tables
    run([py, "-m", "pipelines.disparity"], repo_copy)
    d1 = (repo_copy / "data" / "disparity" / "manifest.json").read_bytes()
    run([py, "-m", "pipelines.disparity"], repo_copy)
    assert (
        repo_copy / "data" / "disparity" / "manifest.json"
    ).read_bytes() == d1  # no timings in the data version
    # truncated image shard -> a clear error naming the file, nothing written
    shard = repo_copy / "data" / "risk" / m1["shards"][1]["name"]
    good = shard.read_bytes()
    shard.write_bytes(good[: len(good) // 2])
    before = (repo_copy / "reports" / "metrics" / "disparity.json").read_bytes()
    # the failures in this process (the stage's main under run_stage): no interpreter start each
    code, err = stage_in_process(repo_copy, "disparity")
    assert code != 0 and shard.name in err and "SHA-256" in err
    code, err = stage_in_process(repo_copy, "orb_filter")
    assert code != 0 and shard.name in err
    assert (repo_copy / "reports" / "metrics" / "disparity.json").read_bytes() == before
    shard.write_bytes(good)
    # mismatched left/right sizes inside a (validly hashed) shard -> a clear error
    from traffictwin.io.shards import DatasetWriter

    ds = Dataset(repo_copy / "data" / "risk", kind="risk")
    frames = ds.table("frames.csv")
    w = DatasetWriter(repo_copy / "data" / "risk_bad", "risk", {}, 0)
    for i, s in enumerate(ds.shards):
        a = ds.load_shard(i)
        if i == 0:
            a["right"] = a["right"][:, :-2]
        w.add_shard(i, a, split=s["split"])
    w.add_table("frames.csv", frames)
    w.finalize(extra={"camera": ds.manifest["camera"]})
    import shutil

    shutil.rmtree(repo_copy / "data" / "risk")
    (repo_copy / "data" / "risk_bad").rename(repo_copy / "data" / "risk")
    code, err = stage_in_process(repo_copy, "disparity")
    assert code != 0 and "differ in size" in err and "shard-00000.npz" in err
