"""Stages disparity and orb_filter on a tiny rendered data set: the depth-error metrics, the
valid share handed from disparity to orb_filter, the pair-check table and its bad inputs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipelines import disparity as disparity_stage
from pipelines import orb_filter as orb_stage
from traffictwin.grid import GridSpec
from traffictwin.io.shards import Dataset, DatasetError, DatasetWriter
from traffictwin.risk.dataset import RiskDataSpec, assign_splits, frame_table, make_shard
from traffictwin.risk.metric import RiskConfig
from traffictwin.sim.camera import StereoCamera
from traffictwin.sim.driving import DrivingConfig
from traffictwin.stereo.check import StereoCheckParams
from traffictwin.stereo.orb import TABLE_COLUMNS, OrbParams
from traffictwin.stereo.sgm import SgmParams

SPEC = RiskDataSpec(
    DrivingConfig(frames=3, warmup=1.0, fault_delay=0.3, fault_vertical=0.3),
    StereoCamera(width=128, height=64),
    GridSpec(128, 96, 0.64),
    RiskConfig(subject_length=4.8, subject_width=1.9),
    1.5,  # critical THW (s)
)
SGM = SgmParams(
    num_disparities=16,
    block_size=5,
    uniqueness_ratio=10,
    speckle_window=100,
    speckle_range=2,
    gray=False,
)
ORB = OrbParams(
    n_features=500,
    fast_threshold=12,
    n_levels=4,
    edge_threshold=19,
    max_hamming=40.0,
    best_n=50,
    min_reliable=8,
    statistic="mean",
    min_dx=1.0,
    max_dy=5.0,
)
CHECK = StereoCheckParams(
    rule="orb_or_valid_share", min_valid_share=0.8, depth_bins_m=[0.0, 10.0, 30.0, 90.0]
)


def _risk(root: Path, seed: int = 3, n: int = 3) -> Dataset:
    splits = assign_splits(n, seed)
    w = DatasetWriter(root, "risk", {"seed": seed}, seed)
    rows = {}
    for i in range(n):
        arrays, rows[i] = make_shard(seed, i, SPEC)
        w.add_shard(i, arrays, split=splits[i])
    w.add_table("frames.csv", frame_table(rows, splits))
    w.finalize(extra={"camera": SPEC.camera.intrinsics()})
    return Dataset(root, kind="risk")


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("stereo_stages")
    _risk(root / "risk")
    return root


@pytest.fixture(scope="module")
def disparity_metrics(data: Path) -> dict:
    return disparity_stage.run(
        SGM, 1, CHECK.depth_bins_m, src=data / "risk", out=data / "disparity"
    )


def test_disparity_writes_depth_error_and_valid_share(data: Path, disparity_metrics: dict) -> None:
    m = disparity_metrics
    for b in ("z0-10m", "z10-30m", "z30-90m"):
        assert {f"all/{b}_relerr_median", f"all/{b}_relerr_p90", f"all/{b}_valid_share"} <= set(m)
    # a valid 0 px estimate ranges to infinity: a percentile beyond the histogram is inf, written
    # as null (the 30 % faulty pairs of this tiny set can put the 90th percentile there)
    for part in ("all", "fault_none"):
        med, p90 = m[f"{part}/z0-10m_relerr_median"], m[f"{part}/z0-10m_relerr_p90"]
        assert 0 <= med and (p90 is None or med <= p90)
    assert m["all/z0-10m_gt_pixels"] > 0 and "fault_none/z0-10m_gt_pixels" in m
    json.dumps(m, allow_nan=True)  # no inf (written as null)
    assert not any(isinstance(v, float) and np.isinf(v) for v in m.values())
    frames = Dataset(data / "disparity", kind="disparity").table("frames.csv")
    assert list(frames.columns) == ["frame_id", "density", "bad2", "d1", "epe", "valid_share"]
    assert frames.valid_share.between(0, 1).all() and len(frames) == 9


def test_depth_metrics_groups_per_split_and_fault() -> None:
    c = {"n_gt": np.array([2, 0]), "n_valid": np.array([1, 0]), "hist": np.zeros((2, 5), int)}
    out = disparity_stage.depth_metrics(
        {0: {"none": c}, 1: {"delay": c, "none": c}}, {0: "train", 1: "test"}, [0.0, 10.0, 30.0]
    )
    assert out["all/z0-10m_gt_pixels"] == 6 and out["train/z0-10m_gt_pixels"] == 2
    assert out["test/z0-10m_gt_pixels"] == 4 and out["fault_none/z0-10m_gt_pixels"] == 4
    assert out["fault_delay/z0-10m_valid_share"] == 0.5 and "val/z0-10m_gt_pixels" not in out


def test_orb_filter_table_and_metrics(data: Path, disparity_metrics: dict) -> None:
    table, m = orb_stage.run(ORB, CHECK, 1, src=data / "risk", disparity=data / "disparity")
    assert tuple(table.columns) == TABLE_COLUMNS and len(table) == 9
    assert (table.outlier == (table.flag_orb | table.flag_valid_share)).all()
    assert (table.flag_valid_share == (table.valid_share < 0.8)).all()
    shares = Dataset(data / "disparity", kind="disparity").table("frames.csv")
    assert np.allclose(table.valid_share, shares.valid_share)
    assert m["rule_orb_or_valid_share/configured"] == 1 and m["rule_orb/configured"] == 0
    assert m["check/min_valid_share"] == 0.8
    assert m["all/dropped_share"] == pytest.approx(table.outlier.mean())
    assert "rule_valid_share/false_alarm" in m and "sweep/min_valid_share_0p8_false_alarm_rate" in m
    # the sweep at the configured max_dy reproduces the robust ORB rule
    clean = table.fault == "none"
    assert m["sweep/max_dy_5_false_alarm_rate"] == pytest.approx(table.flag_orb[clean].mean())
    other, _ = orb_stage.run(
        ORB,
        StereoCheckParams("orb", 0.8, [0.0, 90.0]),
        1,
        src=data / "risk",
        disparity=data / "disparity",
    )
    assert (other.outlier == other.flag_orb).all()


def test_orb_filter_rejects_a_stale_or_old_disparity(
    tmp_path: Path, data: Path, disparity_metrics: dict
) -> None:
    risk = _risk(
        tmp_path / "risk", seed=4, n=1
    )  # another data/risk than data/disparity was made from
    with pytest.raises(DatasetError, match="made from another data/risk.*run the disparity stage"):
        orb_stage.valid_shares(risk, data / "disparity")
    # a data/disparity of the same risk data but without the column (an older stage version)
    old = tmp_path / "old_disparity"
    w = DatasetWriter(old, "disparity", {"source": Dataset(data / "risk").manifest_hash()}, 0)
    w.add_table("frames.csv", pd.DataFrame({"frame_id": range(9), "density": 0.9}))
    w.finalize()
    with pytest.raises(
        DatasetError, match="column 'valid_share' missing.*rerun the disparity stage"
    ):
        orb_stage.valid_shares(Dataset(data / "risk"), old)
