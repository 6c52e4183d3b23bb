"""generate_fusion / prealign: pairs and labels, splits, determinism, tamper detection, bad input."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import run
from omegaconf import OmegaConf

from traffictwin.config import ConfigError
from traffictwin.evidential.dempster import dempster
from traffictwin.evidential.noise import scale_noise, standard_normal_draws
from traffictwin.evidential.warp import warp_masses
from traffictwin.fusion.pairs import FusionDataParams, generate_shard, prealign_arrays, shard_splits
from traffictwin.geometry import relative_pose
from traffictwin.grid import GridSpec
from traffictwin.io.shards import Dataset, DatasetError
from traffictwin.sim.lidar import LidarSpec

ROOT = Path(__file__).resolve().parents[1]
SMALL = FusionDataParams(
    grid=GridSpec(64, 48, 0.8),
    lidar=LidarSpec(azimuth_res_deg=1.0, max_range=40.0),
    scenarios_per_shard=1,
    encounters_per_scenario=1,
)


def test_shard_pairs_and_labels():
    a = generate_shard(5, 3, SMALL)
    assert a["map1"].shape == (2, 2, 64, 48) and a["map1"].dtype == np.float32
    assert set(a) >= {"map1", "map2", "label", "pose1", "pose2", "scenario", "pair_id"}
    np.testing.assert_array_equal(a["scenario"], [3, 3])
    # the two perspectives mirror each other
    np.testing.assert_array_equal(a["map1"][0], a["map2"][1])
    np.testing.assert_array_equal(a["pose1"][1], a["pose2"][0])
    for i in range(2):
        rel = relative_pose(a["pose1"][i], a["pose2"][i])
        np.testing.assert_allclose(
            a["label"][i],
            dempster(a["map1"][i], warp_masses(a["map2"][i], rel, SMALL.grid)),
            atol=1e-7,
        )
    assert (a["map1"][:, 1] > 0).any() and (
        a["map1"][:, 0] > 0
    ).any()  # both free and occupied evidence
    # the label knows more than map 1 alone (the other vehicle saw more)
    assert (a["label"].sum(1) > 0).sum() > (a["map1"].sum(1) > 0).sum()
    b = generate_shard(5, 3, SMALL)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])


def test_prealign_zero_noise_is_exact_warp_and_noise_moves_it():
    a = generate_shard(1, 0, SMALL)
    z = standard_normal_draws(7, a["pair_id"])
    exact = prealign_arrays(a, scale_noise(z, 0.0, 0.0), SMALL.grid)
    for i in range(2):
        np.testing.assert_allclose(
            exact["inputs"][i, 2:], warp_masses(a["map2"][i], exact["rel_pose_true"][i], SMALL.grid)
        )
    np.testing.assert_allclose(exact["rel_pose_true"], exact["rel_pose_noisy"])
    noisy = prealign_arrays(a, scale_noise(z, 5.0, 20.0), SMALL.grid)
    assert not np.allclose(noisy["inputs"][:, 2:], exact["inputs"][:, 2:])
    np.testing.assert_array_equal(noisy["label"], a["label"])
    np.testing.assert_array_equal(noisy["inputs"][:, :2], a["map1"])
    with pytest.raises(ValueError, match="multiple"):
        prealign_arrays(a, np.zeros((3, 3)), SMALL.grid)


def test_shard_splits():
    s = shard_splits(50, 1)
    assert s.count("val") == 5 and s.count("test") == 5 and s.count("train") == 40
    assert shard_splits(50, 1) == s and shard_splits(50, 2) != s
    small = shard_splits(5, 0)
    assert small.count("val") == 1 and small.count("test") == 1
    with pytest.raises(ValueError, match="sum to 1"):
        shard_splits(10, 0, (0.5, 0.1, 0.1))


def _cfg(**over):
    cfg = OmegaConf.create(yaml.safe_load((ROOT / "params.yaml").read_text()))
    for k, v in over.items():
        OmegaConf.update(cfg, k, v, merge=False)
    return cfg


def spec_from_params(cfg):
    from traffictwin.fusion.config import fusion_data_config, grid_config

    return fusion_data_config(cfg).params(grid_config(cfg))


def test_bad_parameters_name_the_key():
    spec_from_params(_cfg())  # the committed params are valid
    with pytest.raises(ConfigError, match="fusion_data.scenarios"):
        spec_from_params(_cfg(**{"fusion_data.scenarios": -4}))
    with pytest.raises(ConfigError, match="fusion_data.encounters_per_scenario"):
        spec_from_params(_cfg(**{"fusion_data.encounters_per_scenario": 0}))
    with pytest.raises(ConfigError, match="divisible by 16"):
        spec_from_params(_cfg(**{"grid.rows": 250}))
    with pytest.raises(ConfigError, match="unknown template.*'spaghetti'"):
        spec_from_params(_cfg(**{"fusion_data.templates": ["cross4", "spaghetti"]}))
    with pytest.raises(ConfigError, match="multiple"):
        spec_from_params(_cfg(**{"fusion_data.scenarios": 7, "fusion_data.scenarios_per_shard": 5}))
    with pytest.raises(ValueError, match="unknown road template"):
        FusionDataParams(templates=("cross4", "spaghetti"))
    # typed schema: unknown, missing and mistyped keys name the dotted key
    with pytest.raises(ConfigError, match="fusion_data.lidar.beams"):
        spec_from_params(_cfg(**{"fusion_data.lidar.beams": 32}))
    with pytest.raises(ConfigError, match="fusion_data.splits"):
        spec_from_params(_cfg(**{"fusion_data.splits.train": 0.5}))
    with pytest.raises(ConfigError, match="fusion_data.traffic.*'cars'"):
        spec_from_params(_cfg(**{"fusion_data.traffic.cars": 3}))
    with pytest.raises(ConfigError, match="fusion_data.compresslevel"):
        spec_from_params(_cfg(**{"fusion_data.compresslevel": "fast"}))


def test_fusion_data_params_from_config_equal_the_explicit_ones():
    from traffictwin.evidential.ism import IsmParams

    cfg = _cfg()
    fd = cfg["fusion_data"]
    p = spec_from_params(cfg)
    assert p.grid == GridSpec(cfg["grid"]["rows"], cfg["grid"]["cols"], cfg["grid"]["cell"])
    assert p.lidar.uniform == fd["lidar"]["uniform_elevations"]
    assert p.lidar.azimuth_res_deg == fd["lidar"]["azimuth_res_deg"]
    assert p.ism == IsmParams(**fd["ism"])
    assert p.templates == tuple(fd["templates"]) and p.meet_distance == tuple(fd["meet_distance"])
    assert p.density == {k: float(v) for k, v in fd["traffic"].items()}
    assert p.scenarios_per_shard == fd["scenarios_per_shard"]


def test_prealign_is_the_warp_by_the_noisy_relative_pose():
    from traffictwin.evidential.noise import apply_pose_noise
    from traffictwin.fusion.pairs import prealign

    rng = np.random.default_rng(4)
    m2 = np.moveaxis(rng.dirichlet([1, 1, 1], size=(64, 48))[..., :2], -1, 0).astype(np.float32)
    p1, p2 = np.array([1.0, 2.0, 0.3]), np.array([5.0, -1.0, 3.0])
    warped, rel = prealign(m2, p1, p2, SMALL.grid)
    np.testing.assert_array_equal(rel, relative_pose(p1, p2))
    np.testing.assert_array_equal(warped, warp_masses(m2, rel, SMALL.grid))
    noise = np.array([0.5, -0.2, 0.4])
    warped, rel = prealign(m2, p1, p2, SMALL.grid, noise=noise)
    np.testing.assert_array_equal(rel, relative_pose(p1, apply_pose_noise(p2, noise)))
    np.testing.assert_array_equal(warped, warp_masses(m2, rel, SMALL.grid))


@pytest.mark.slow
def test_bad_input_writes_nothing(repo_copy: Path):
    p = repo_copy / "params.yaml"
    cfg = yaml.safe_load(p.read_text())
    cfg["fusion_data"]["scenarios"] = -3
    p.write_text(yaml.safe_dump(cfg))
    proc = run([sys.executable, "-m", "pipelines.generate_fusion"], repo_copy, check=False)
    assert proc.returncode != 0 and "fusion_data.scenarios" in proc.stderr
    assert not (repo_copy / "data" / "fusion").exists()


@pytest.mark.slow
def test_generate_fusion_deterministic_and_tamper_detected(repo_copy: Path):
    cmd = [sys.executable, "-m", "pipelines.generate_fusion"]
    run(cmd, repo_copy)
    first = repo_copy / "data" / "fusion_first"
    shutil.move(repo_copy / "data" / "fusion", first)
    run(cmd, repo_copy)
    second = repo_copy / "data" / "fusion"
    names = sorted(x.name for x in first.iterdir())
    assert names == sorted(x.name for x in second.iterdir()) and len(names) >= 4
    for n in names:
        assert (first / n).read_bytes() == (second / n).read_bytes(), n
    # tamper with one shard: the reader names it
    victim = sorted(second.glob("shard-*.npz"))[1]
    data = bytearray(victim.read_bytes())
    data[len(data) // 2] ^= 0xFF
    victim.write_bytes(bytes(data))
    with pytest.raises(DatasetError, match=victim.name):
        Dataset(second, kind="fusion")


# ---- on the whole ci DAG --------------------------------------------------------------------
@pytest.mark.slow
def test_fusion_dataset_on_ci_dag(ci_dag: Path):
    ds = Dataset(ci_dag / "data" / "fusion", kind="fusion")
    grid = GridSpec(**yaml.safe_load((ci_dag / "params.yaml").read_text())["grid"])
    assert 16 <= len(ds) <= 24
    assert set(ds.manifest["split_counts"]) == {"train", "val", "test"}
    scen = {
        s: set(ds.load_all(s, ["scenario"])["scenario"].tolist()) for s in ("train", "val", "test")
    }
    assert (
        not (scen["train"] & scen["val"])
        and not (scen["train"] & scen["test"])
        and not (scen["val"] & scen["test"])
    )
    sh = ds.load_shard(0)
    assert sh["map1"].shape[1:] == (2, grid.rows, grid.cols) and sh["label"].dtype == np.float32
    assert sh["pose1"].shape == (len(sh["map1"]), 3)
    assert (ci_dag / "reports" / "figures" / "fusion_data_samples.png").stat().st_size > 10_000


@pytest.mark.slow
def test_prealigned_on_ci_dag(ci_dag: Path):
    src = Dataset(ci_dag / "data" / "fusion", kind="fusion")
    dsets = {c: Dataset(ci_dag / "data" / "prealigned" / c, kind="prealigned") for c in "ABCD"}
    grid = GridSpec(**yaml.safe_load((ci_dag / "params.yaml").read_text())["grid"])
    a = dsets["A"].load_all("test")
    assert a["inputs"].shape[1:] == (4, grid.rows, grid.cols)
    assert np.all(a["noise"] == 0)
    np.testing.assert_allclose(a["rel_pose_noisy"], a["rel_pose_true"])
    f = src.load_all("test")
    np.testing.assert_array_equal(a["label"], f["label"])
    np.testing.assert_array_equal(a["inputs"][:, :2], f["map1"])
    b, d = dsets["B"].load_all("test"), dsets["D"].load_all("test")
    # the same draw per pair in every configuration, scaled by sigma
    np.testing.assert_allclose(b["noise"][:, :2] / 1.0, d["noise"][:, :2] / 5.0, rtol=1e-9)
    assert np.abs(d["noise"][:, :2]).max() > 0.1
    assert not np.allclose(d["inputs"][:, 2:], a["inputs"][:, 2:])
    # the splits of fusion_data.prealign.splits (val, test), shard for shard as data/fusion's
    want = [s["split"] for s in src.shards if s["split"] in ("val", "test")]
    for c, ds in dsets.items():
        assert [s["split"] for s in ds.shards] == want, c
    # the one model's training set: train and val, every draw's noise from one configuration
    mixed = Dataset(ci_dag / "data" / "prealigned" / "mixed", kind="prealigned")
    assert {s["split"] for s in mixed.shards} == {"train", "val"}
    m = mixed.load_all("train", keys=["noise", "noise_sigma"])
    assert len(m["noise"]) == 2 * sum(s["count"] for s in src.shards if s["split"] == "train")
    assert len({tuple(r) for r in m["noise_sigma"]}) > 1  # several noise levels
