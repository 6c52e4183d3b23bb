"""examples/: the committed sample inputs load with the CLI's own readers, fit the grids and camera
that the default and ci profiles' models are trained on (conf/), and regenerate byte for byte."""

from __future__ import annotations

import json
import runpy
from pathlib import Path

import numpy as np
import pytest
from conftest import composed

from traffictwin.api import DIVISOR, load_masses, read_image
from traffictwin.cli import parse_pose

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
PROFILES = ("default", "ci")


@pytest.fixture(scope="module")
def confs() -> dict[str, dict]:
    return {p: composed(f"profile={p}") for p in PROFILES}


@pytest.mark.parametrize("profile", PROFILES)
def test_grids_fit_the_profiles_grid(profile: str, confs: dict[str, dict]) -> None:
    grid = confs[profile]["grid"]
    maps = []
    for name in ("map1", "map2"):
        m, cell, _ = load_masses(EXAMPLES / "fuse" / profile / f"{name}.npz")  # the CLI's checks
        assert m.shape == (2, grid["rows"], grid["cols"]) and m.dtype == np.float32
        assert cell == pytest.approx(grid["cell"])
        assert m.shape[1] % DIVISOR == 0 and m.shape[2] % DIVISOR == 0
        assert (m >= 0).all() and (m.sum(0) <= 1 + 1e-6).all()
        # a lidar map: some cells free, some occupied, many unknown (not a blank or a full grid)
        assert 0.05 < (m[0] > 0).mean() < 0.95 and 0.001 < (m[1] > 0).mean() < 0.2
        maps.append(m)
    assert not np.array_equal(maps[0], maps[1])


@pytest.mark.parametrize("profile", PROFILES)
def test_poses_are_cli_pose_strings_with_config_d_noise(
    profile: str, confs: dict[str, dict]
) -> None:
    meta = json.loads((EXAMPLES / "fuse" / profile / "poses.json").read_text())
    p1, p2 = parse_pose(meta["pose1"], "pose1"), parse_pose(meta["pose2"], "pose2")
    true2 = parse_pose(meta["pose2_true"], "pose2_true")
    d = confs[profile]["configurations"]["D"]
    assert (meta["noise_r_m"], meta["noise_alpha_deg"]) == (d["r"], d["alpha"])
    assert meta["grid"] == confs[profile]["grid"]
    # one draw of the noise: nonzero, and within 3 sigma (sigma = r / 2.326 per axis)
    dxy, dyaw = p2[:2] - true2[:2], (p2[2] - true2[2] + np.pi) % (2 * np.pi) - np.pi
    assert 0 < np.abs(dxy).max() < 3 * d["r"] / 2.326
    assert 0 < abs(dyaw) < 3 * np.deg2rad(d["alpha"]) / 2.326
    # the two vehicles meet (conf meet_distance) and are within each other's grid
    dist = np.hypot(*(true2[:2] - p1[:2]))
    assert dist == pytest.approx(meta["distance_m"], abs=2e-3)
    lo, hi = confs[profile]["fusion_data"]["meet_distance"]
    assert lo - 5 <= dist <= hi + 5


@pytest.mark.parametrize("profile", PROFILES)
def test_stereo_pair_fits_the_profiles_camera(profile: str, confs: dict[str, dict]) -> None:
    cam = confs[profile]["risk_data"]["camera"]
    left = read_image(EXAMPLES / "risk" / "000_left.png")
    right = read_image(EXAMPLES / "risk" / "000_right.png")
    assert left.shape == right.shape == (cam["height"], cam["width"], 3)
    assert left.dtype == np.uint8 and 20 < left.std() and not np.array_equal(left, right)
    meta = json.loads((EXAMPLES / "risk" / "000.json").read_text())
    assert meta["fault"] == "none" and meta["critical"] is True
    assert 0 < meta["thw_corridor_s"] < 1.5 and meta["speed_m_s"] > 0


@pytest.mark.slow
def test_regenerating_gives_identical_files(tmp_path: Path) -> None:
    mod = runpy.run_path(str(EXAMPLES / "make_examples.py"))
    written = mod["write_examples"](tmp_path)
    committed = sorted(
        p.relative_to(EXAMPLES)
        for p in EXAMPLES.rglob("*")
        if p.is_file() and p.suffix in (".npz", ".png", ".json")
    )
    assert sorted(p.relative_to(tmp_path) for p in written) == committed
    for rel in committed:
        assert (tmp_path / rel).read_bytes() == (EXAMPLES / rel).read_bytes(), f"{rel} differs"


@pytest.mark.slow
def test_quick_start_risk_verdict_matches_the_example(ci_dag: Path) -> None:
    """The Quick start's `traffictwin risk` on the sample pair, with the ci DAG's shipped
    predictor: the verdict the example's own labels give (a critical cut-in), and a predictor
    description without a NaN validation score (the ci validation split is too small to rank
    predictors, so the shipped rule says so)."""
    from traffictwin.api import Frame, assess_risk, load_risk

    meta = json.loads((EXAMPLES / "risk" / "000.json").read_text())
    risk = load_risk(ci_dag / "models" / "risk_shipped")
    pair = Frame("000", EXAMPLES / "risk" / "000_left.png", EXAMPLES / "risk" / "000_right.png")
    (row,) = assess_risk(risk, [pair], speed=meta["speed_m_s"])
    assert row["critical"] is meta["critical"]
    assert row["thw_s"] < 1.5
    assert "nan" not in risk.predictor
