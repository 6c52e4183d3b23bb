"""Stereo pair fault detection: the rules on synthetic pairs, hand-counted rates, config errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import composed
from omegaconf import OmegaConf

from traffictwin.config import ConfigError, typed
from traffictwin.risk.config import RiskDataConfig
from traffictwin.sim.camera import StereoCamera
from traffictwin.sim.scene import Boxes, Cls
from traffictwin.stereo.check import (
    RULES,
    StereoCheckParams,
    add_flags,
    paper_flag,
    rule_flag,
    valid_share_sweep,
)
from traffictwin.stereo.detection import detection_table
from traffictwin.stereo.orb import check_pair
from traffictwin.stereo.sgm import compute_disparity, valid_share

ROOT = Path(__file__).resolve().parents[1]
FAULTS = ("none", "delay", "vertical")


@pytest.fixture(scope="module")
def pairs() -> dict[str, dict]:
    """A clean pair, the right image 8 px lower, and the right eye 0.5 m further ahead (a right
    image 88 ms late at 5.7 m/s)."""
    cam = StereoCamera()
    boxes = Boxes(
        [[12, 0], [20, 3.5], [8, -3.5], [30, -10], [25, 12]],
        [[4.5, 1.8, 1.5], [4.5, 1.8, 1.5], [4.5, 1.8, 1.5], [20, 10, 12], [15, 8, 9]],
        [0, 0.1, 0, 0, 0.3],
        [Cls.CAR, Cls.CAR, Cls.CAR, Cls.BUILDING, Cls.BUILDING],
    )
    pose = (0.0, 0.0, 0.0)
    return {
        "clean": cam.render_pair(pose, boxes, rng=np.random.default_rng(0)),
        "vertical": cam.render_pair(pose, boxes, right_cy_offset=8.0, rng=np.random.default_rng(0)),
        "delay": cam.render_pair(
            pose, boxes, pose_right=(0.5, 0.0, 0.0), rng=np.random.default_rng(0)
        ),
    }


def _flags(pairs: dict[str, dict], rule: str = "orb_or_valid_share") -> pd.DataFrame:
    rows = []
    for name, p in pairs.items():
        r = check_pair(p["left"], p["right"])
        d = compute_disparity(p["left"], p["right"], num_disparities=32)
        rows.append(
            {
                "pair": name,
                "n_matches": r.n_matches,
                "all_mean_dx": r.all_mean_dx,
                "all_mean_dy": r.all_mean_dy,
                "flag_orb": r.outlier,
                "valid_share": float(valid_share(d, 32)),
            }
        )
    df = pd.DataFrame(rows)
    return add_flags(df, min_dx=1.0, max_dy=5.0, min_valid_share=0.8, rule=rule).set_index("pair")


def test_rules_on_synthetic_pairs(pairs) -> None:
    f = _flags(pairs)
    clean, vertical, delay = f.loc["clean"], f.loc["vertical"], f.loc["delay"]
    assert not clean.flag_orb and not clean.flag_valid_share and not clean.outlier
    assert clean.valid_share > 0.9
    assert vertical.flag_orb and vertical.flag_valid_share and vertical.flag_orb_paper
    assert vertical.outlier
    # the delayed pair passes the robust ORB rule but loses its valid SGM pixels
    assert not delay.flag_orb and delay.flag_valid_share and delay.outlier
    only_orb = _flags(pairs, rule="orb")
    assert not only_orb.loc["delay"].outlier and only_orb.loc["vertical"].outlier


def _table() -> pd.DataFrame:
    """Eight pairs in four scenarios: three clean, three delayed, two vertical."""
    return pd.DataFrame(
        {
            "scenario": [0, 0, 1, 1, 2, 2, 3, 3],
            "fault": ["none", "delay", "none", "delay", "none", "vertical", "delay", "vertical"],
            "speed": [3.0, 0.2, 8.0, 8.0, 12.0, 12.0, 20.0, 20.0],
            "n_matches": [100, 100, 100, 0, 100, 100, 100, 100],
            "all_mean_dx": [4.0, 4.0, 0.5, np.nan, 4.0, 4.0, 4.0, 4.0],
            "all_mean_dy": [1.0, 1.0, 1.0, np.nan, 6.0, 9.0, 2.0, 9.0],
            "flag_orb": [False, False, False, True, False, True, False, False],
            "valid_share": [0.95, 0.9, 0.85, 0.7, 0.79, 0.5, 0.6, 0.6],
        }
    )


def test_add_flags_hand_table() -> None:
    df = add_flags(_table(), min_dx=1.0, max_dy=5.0, min_valid_share=0.8, rule="orb_or_valid_share")
    # paper: dx 0.5 < 1 (row 2), no matches (row 3), dy 6, 9, 9 > 5 (rows 4, 5, 7)
    assert df.flag_orb_paper.tolist() == [False, False, True, True, True, True, False, True]
    assert df.flag_valid_share.tolist() == [False, False, False, True, True, True, True, True]
    assert df.outlier.tolist() == [False, False, False, True, True, True, True, True]
    assert rule_flag(df, "orb").tolist() == df.flag_orb.tolist()
    assert rule_flag(df, "orb_paper").tolist() == df.flag_orb_paper.tolist()
    s = paper_flag(df.n_matches, df.all_mean_dx, df.all_mean_dy, 0.4, 9.5)
    assert s.tolist() == [False, False, False, True, False, False, False, False]
    with pytest.raises(ValueError, match="'check.rule' must be one of"):
        add_flags(_table(), min_dx=1.0, max_dy=5.0, min_valid_share=0.8, rule="orb_and_valid_share")
    with pytest.raises(ValueError, match=r"'check.min_valid_share' must be in \[0, 1\]"):
        add_flags(_table(), min_dx=1.0, max_dy=5.0, min_valid_share=1.2, rule="orb")


def test_detection_table_hand_counts() -> None:
    df = add_flags(_table(), min_dx=1.0, max_dy=5.0, min_valid_share=0.8, rule="orb")
    m = detection_table(df, FAULTS, speed_edges=(0.0, 0.5, 10.0, 40.0), n_boot=500)
    assert set(m) >= {f"rule_{r}/false_alarm" for r in RULES}
    # valid share: clean pairs 0, 2, 4 -> row 4 flagged; delay 1, 3, 6 -> 3, 6; vertical 5, 7 -> both
    vs = "rule_valid_share/"
    assert m[vs + "false_alarm"] == pytest.approx(1 / 3) and m[vs + "false_alarm_n"] == 3
    assert m[vs + "delay_detection"] == pytest.approx(2 / 3) and m[vs + "delay_detection_n"] == 3
    assert m[vs + "vertical_detection"] == 1.0
    assert m[vs + "vertical_detection_lo"] == 1.0 == m[vs + "vertical_detection_hi"]
    assert m[vs + "false_alarm_lo"] <= 1 / 3 <= m[vs + "false_alarm_hi"]
    # delay by speed: 0.2 m/s (row 1) missed; 8 m/s (row 3) and 20 m/s (row 6) caught
    assert m[vs + "delay_detection_v0-0p5"] == 0.0 and m[vs + "delay_detection_v0-0p5_n"] == 1
    assert m[vs + "delay_detection_v0p5-10"] == 1.0 and m[vs + "delay_detection_v10-40"] == 1.0
    # robust ORB: row 3 (delay) and row 5 (vertical) only; the OR adds nothing to valid share here
    assert m["rule_orb/delay_detection"] == pytest.approx(1 / 3)
    assert m["rule_orb/vertical_detection"] == pytest.approx(1 / 2)
    assert m["rule_orb/false_alarm"] == 0.0
    assert m["rule_orb_or_valid_share/delay_detection"] == pytest.approx(2 / 3)
    # paper: clean row 2 (dx 0.5) and 4 (dy 6) -> 2/3 false alarms; delay: row 3 only
    assert m["rule_orb_paper/false_alarm"] == pytest.approx(2 / 3)
    assert m["rule_orb_paper/delay_detection"] == pytest.approx(1 / 3)
    # no delay faults -> no delay keys; deterministic for the seed
    no_delay = detection_table(df[df.fault != "delay"], FAULTS, n_boot=200)
    assert not any("delay" in k for k in no_delay)
    again = detection_table(df, FAULTS, speed_edges=(0.0, 0.5, 10.0, 40.0), n_boot=500)
    assert again == m


def test_valid_share_sweep_hand_counts() -> None:
    m = valid_share_sweep(_table(), FAULTS, thresholds=(0.75, 0.9))
    assert m["sweep/min_valid_share_0p75_false_alarm_rate"] == 0.0
    assert m["sweep/min_valid_share_0p9_false_alarm_rate"] == pytest.approx(2 / 3)  # 0.85, 0.79
    assert m["sweep/min_valid_share_0p75_delay_detection_rate"] == pytest.approx(2 / 3)
    assert m["sweep/min_valid_share_0p9_delay_detection_rate"] == pytest.approx(
        2 / 3
    )  # 0.9 not < 0.9
    assert m["sweep/min_valid_share_0p75_vertical_detection_rate"] == 1.0


def _risk_data(**dotted) -> RiskDataConfig:
    node = OmegaConf.create(composed("profile=ci")["risk_data"])
    for k, v in dotted.items():
        OmegaConf.update(node, k, v, force_add=True)
    return typed(node, RiskDataConfig, key="risk_data")


def test_check_config_validates() -> None:
    c = _risk_data().check
    assert isinstance(c, StereoCheckParams) and c.rule in RULES
    assert 0.0 <= c.min_valid_share <= 1.0 and list(c.depth_bins_m) == [0.0, 10.0, 30.0, 90.0]
    assert _risk_data(**{"check.rule": "orb_paper"}).check.rule == "orb_paper"


@pytest.mark.parametrize(
    ("dotted", "match"),
    [
        ({"check.rule": "orb_and_valid_share"}, r"'risk_data\.check\.rule' must be one of"),
        ({"check.min_valid_share": 1.5}, r"'risk_data\.check\.min_valid_share' must be <= 1"),
        ({"check.min_valid_share": -0.1}, r"'risk_data\.check\.min_valid_share' must be >= 0"),
        (
            {"check.depth_bins_m": [0.0, 30.0, 10.0]},
            r"'check\.depth_bins_m' must be >= 2 increasing",
        ),
        ({"check.depth_bins_m": [-5.0, 10.0]}, r"check\.depth_bins_m"),
        ({"check.max_valid_share": 0.5}, r"risk_data\.check\.max_valid_share"),
    ],
)
def test_bad_check_config_names_the_key(dotted: dict, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        _risk_data(**dotted)


def test_min_valid_share_is_chosen_on_validation_within_the_false_alarm_budget() -> None:
    """The most faults caught with at most max_false_alarm of the clean pairs flagged (by hand)."""
    from traffictwin.stereo.check import choose_min_valid_share

    df = pd.DataFrame(
        {
            "fault": ["none"] * 4 + ["delay"] * 4,
            "valid_share": [0.95, 0.93, 0.88, 0.86, 0.50, 0.72, 0.78, 0.87],
        }
    )
    # t=0.8: detection 3/4, false alarms 0; t=0.9: detection 4/4, false alarms 2/4
    t, table = choose_min_valid_share(df, max_false_alarm=0.0, candidates=(0.7, 0.8, 0.9))
    assert t == 0.8
    rows = {r["min_valid_share"]: r for r in table}
    assert rows[0.9]["detection_rate"] == 1.0 and rows[0.9]["false_alarm_rate"] == 0.5
    assert rows[0.7]["detection_rate"] == 0.25
    assert choose_min_valid_share(df, 0.5, (0.7, 0.8, 0.9))[0] == 0.9
    # nothing within the budget: the lowest threshold
    assert choose_min_valid_share(df, 0.0, (0.9, 0.95))[0] == 0.9
    with pytest.raises(ValueError, match="fault-free and faulty"):
        choose_min_valid_share(df[df.fault == "none"], 0.02)
