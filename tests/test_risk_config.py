"""Typed configuration of the risk problem: risk_data and evaluation.risk validated once."""

from __future__ import annotations

from pathlib import Path

import conftest
import pytest
from omegaconf import OmegaConf

from traffictwin.config import ConfigError, typed
from traffictwin.grid import GridSpec
from traffictwin.risk.config import EvalRiskConfig, MetricParams, RiskDataConfig
from traffictwin.stereo.orb import OrbParams
from traffictwin.stereo.sgm import SgmParams

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module", params=["ci", "default", "paper"])
def composed(request) -> dict:
    return conftest.composed(f"profile={request.param}")


def _risk_data(cfg: dict, **dotted) -> RiskDataConfig:
    node = OmegaConf.create(cfg["risk_data"])
    for k, v in dotted.items():
        OmegaConf.update(node, k, v, force_add=True)
    return typed(node, RiskDataConfig, key="risk_data")


def test_every_profile_validates(composed: dict) -> None:
    rd = _risk_data(composed)
    assert isinstance(rd.sgm, SgmParams) and isinstance(rd.orb, OrbParams)
    assert rd.sgm.num_disparities % 16 == 0 and rd.orb.statistic in ("mean", "median")
    ev = typed(composed["evaluation"]["risk"], EvalRiskConfig, key="evaluation.risk")
    ev.check_variants(list(composed["risk_model"]["run_variants"]))
    assert ev.thresholds_s[0] > 0
    geo = ev.geometric.params(rd.metric.subject_length, rd.metric.subject_width)
    assert geo.subject_length == rd.metric.subject_length and geo.min_pixels >= 1


def test_data_spec_carries_every_setting(composed: dict) -> None:
    rd = _risk_data(composed)
    spec = rd.data_spec(GridSpec(256, 48, 0.32), 1.5)
    c = composed["risk_data"]
    assert (
        spec.camera.width == c["camera"]["width"]
        and spec.camera.baseline == c["camera"]["baseline"]
    )
    assert spec.driving.frames == c["frames_per_sequence"] and spec.driving.fps == c["fps"]
    assert spec.driving.fault_vertical == c["faults"]["vertical_share"]
    assert spec.driving.vertical_px == tuple(c["faults"]["vertical_px"])
    assert spec.driving.templates == tuple(c["templates"])
    # the metric's camera_fov region uses the camera's geometry
    assert spec.risk.hfov_deg == spec.camera.hfov_deg and spec.risk.mount_x == spec.camera.mount_x
    assert spec.risk.subject_length == c["metric"]["subject_length"]
    assert spec.label == c["label"] and spec.ground_res == c["ground_res"]
    assert spec.grid.shape == (256, 48)
    assert spec.risk.corridor_margin == c["metric"]["corridor_margin"]
    assert dict(spec.driving.situations) == {k: float(v) for k, v in c["situations"].items()}
    assert spec.driving.parked_prob == tuple(c["parked_prob"])
    assert rd.data_seed(7) == 7 + 1_000_003 * c["seed"]
    assert rd.split_fractions() == tuple(float(x) for x in c["splits"])


@pytest.mark.parametrize(
    ("dotted", "match"),
    [
        ({"orb.n_levels": 0}, r"'risk_data\.orb\.n_levels' must be >= 1"),
        ({"sgm.speckle_range": -1}, r"'risk_data\.sgm\.speckle_range' must be >= 0"),
        ({"orb.statistic": "max"}, r"'risk_data\.orb\.statistic' must be one of"),
        ({"camera.hfov_deg": 170.0}, r"'risk_data\.camera\.hfov_deg' must be <= 150"),
        ({"camera.lens": 1}, r"risk_data\.camera\.lens"),
        ({"label": "thw"}, r"'risk_data\.label' must be one of"),
        ({"splits": [0.5, 0.5]}, r"'splits' must be 3 fractions"),
        ({"faults.vertical_px": [4.0]}, r"'faults\.vertical_px' must be \[low, high\]"),
        ({"workers": "two"}, r"risk_data\.workers"),
        ({"situations.joyride": 1.0}, r"'situations': unknown situation\(s\) \['joyride'\]"),
        ({"situations.free": -1.0}, r"'situations': weights must be >= 0"),
        ({"parked_prob": [0.9, 0.1]}, r"'parked_prob' must be \[low, high\]"),
        ({"metric.corridor_margin": 5.0}, r"'risk_data\.metric\.corridor_margin' must be <= 3"),
    ],
)
def test_bad_risk_data_names_the_key(dotted: dict, match: str) -> None:
    cfg = conftest.composed("profile=ci")
    with pytest.raises(ConfigError, match=match):
        _risk_data(cfg, **dotted)


def test_missing_key_is_named() -> None:
    cfg = conftest.composed("profile=ci")
    del cfg["risk_data"]["sgm"]["gray"]
    with pytest.raises(ConfigError, match=r"risk_data\.sgm\.gray"):
        typed(cfg["risk_data"], RiskDataConfig, key="risk_data")


@pytest.mark.parametrize(
    ("change", "match"),
    [
        ({"thresholds_s": []}, "non-empty list of positive seconds"),
        ({"thresholds_s": [1.5, -1.0]}, "non-empty list of positive seconds"),
        ({"thw_cap_s": 0.0}, r"'evaluation\.risk\.thw_cap_s' must be >= 0.1"),
        ({"batch_size": 0}, r"'evaluation\.risk\.batch_size' must be >= 1"),
        ({"geometric": {"min_height": 3.0}}, "min_height must be < max_height"),
    ],
)
def test_bad_evaluation_risk_names_the_key(change: dict, match: str) -> None:
    cfg = conftest.composed("profile=ci")
    node = OmegaConf.merge(cfg["evaluation"]["risk"], change)
    with pytest.raises(ConfigError, match=match):
        typed(node, EvalRiskConfig, key="evaluation.risk")


def test_main_variant_must_be_evaluated() -> None:
    cfg = conftest.composed("profile=ci")
    ev = typed(cfg["evaluation"]["risk"], EvalRiskConfig, key="evaluation.risk")
    with pytest.raises(ConfigError, match="main_variant"):
        ev.check_variants(["some_other_variant"])


def test_metric_group_alone() -> None:
    m = typed(
        {
            "subject_length": 4.8,
            "subject_width": 1.9,
            "fill": "border",
            "include_pedestrians": False,
            "corridor_margin": 0.0,
            "horizon_s": 1.5,
        },
        MetricParams,
        key="risk_data.metric",
    )
    assert m.subject_width == 1.9
    with pytest.raises(ConfigError, match=r"risk_data\.metric\.fill"):
        typed(
            {
                "subject_length": 4.8,
                "subject_width": 1.9,
                "fill": "dots",
                "include_pedestrians": False,
                "corridor_margin": 0.0,
                "horizon_s": 1.5,
            },
            MetricParams,
            key="risk_data.metric",
        )


def test_sgm_settings_opencv_rejects_fail_at_validation() -> None:
    cfg = conftest.composed("profile=ci")
    with pytest.raises(ConfigError, match="multiple of 16"):
        _risk_data(cfg, **{"sgm.num_disparities": 24})
    with pytest.raises(ConfigError, match="odd"):
        _risk_data(cfg, **{"sgm.block_size": 4})


@pytest.mark.parametrize("max_speed,ok", [(25.0, True), (26.0, False)])
def test_grid_must_cover_the_look_ahead(max_speed: float, ok: bool) -> None:
    """25 m/s x 1.5 s + 2.4 m = 39.9 m fits the 256 x 0.32 m grid (40.96 m ahead); 26 m/s does not."""
    cfg = conftest.composed("profile=ci")
    rd = _risk_data(cfg, max_speed=max_speed)
    grid = GridSpec(256, 176, 0.32)
    if ok:
        rd.data_spec(grid, 1.5)
    else:
        with pytest.raises(ConfigError, match=r"'risk_data\.max_speed' 26.0 m/s .* 'grid\.rows'"):
            rd.data_spec(grid, 1.5)
