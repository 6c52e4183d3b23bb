"""ORB pair check: the paper's rule over reliable matches."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from traffictwin.sim.camera import StereoCamera
from traffictwin.sim.scene import Boxes, Cls
from traffictwin.stereo.orb import (
    TABLE_COLUMNS,
    OrbParams,
    OrbResult,
    check_pair,
    check_pairs,
    orb_frames,
    orb_metrics,
)


@pytest.fixture(scope="module")
def pair():
    cam = StereoCamera()
    boxes = Boxes(
        [[12, 0], [20, 3.5], [8, -3.5], [30, -10], [25, 12]],
        [[4.5, 1.8, 1.5], [4.5, 1.8, 1.5], [4.5, 1.8, 1.5], [20, 10, 12], [15, 8, 9]],
        [0, 0.1, 0, 0, 0.3],
        [Cls.CAR, Cls.CAR, Cls.CAR, Cls.BUILDING, Cls.BUILDING],
    )
    return cam.render_pair((0.0, 0.0, 0.0), boxes, rng=np.random.default_rng(0))


def test_good_pair_passes(pair):
    r = check_pair(pair["left"], pair["right"])
    assert isinstance(r, OrbResult)
    assert not r.outlier
    assert r.n_reliable >= 8 and r.n_matches >= r.n_reliable
    assert r.mean_dx >= 1.0 and r.mean_dy < 1.0
    # the paper's statistics over all cross-checked matches: false matches raise mean |dy|
    assert np.isfinite(r.all_mean_dx) and r.all_mean_dy >= r.mean_dy


def test_vertical_shift_of_8px_fails(pair):
    right = np.zeros_like(pair["right"])
    right[8:] = pair["right"][:-8]
    r = check_pair(pair["left"], right)
    assert r.outlier and r.mean_dy > 5.0


def test_identical_images_fail(pair):
    r = check_pair(pair["left"], pair["left"].copy())
    assert r.outlier and r.mean_dx < 1.0


def test_featureless_pair_is_flagged_unverifiable():
    flat = np.full((80, 160, 3), 128, np.uint8)
    r = check_pair(flat, flat)
    assert r.outlier and r.n_reliable == 0 and np.isnan(r.mean_dx)
    assert r.n_matches == 0 and np.isnan(r.all_mean_dx) and np.isnan(r.all_mean_dy)


def test_reliable_filter_limits_matches(pair):
    r = check_pair(pair["left"], pair["right"], best_n=10)
    assert r.n_reliable == 10
    r = check_pair(pair["left"], pair["right"], max_hamming=0)
    assert r.n_reliable <= r.n_matches


def test_bad_input_raises(pair):
    with pytest.raises(ValueError, match="differ in size"):
        check_pair(pair["left"], pair["right"][:-2])
    with pytest.raises(ValueError, match="statistic"):
        check_pair(pair["left"], pair["right"], statistic="mode")


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


def test_check_pairs_runs_the_check_per_pair(pair):
    shifted = np.zeros_like(pair["right"])
    shifted[8:] = pair["right"][:-8]
    left = np.stack([pair["left"], pair["left"]])
    right = np.stack([pair["right"], shifted])
    rows, secs = check_pairs(left, right, ORB)
    assert [r["idx"] for r in rows] == [0, 1] and secs >= 0
    assert rows[0] == {"idx": 0, **check_pair(pair["left"], pair["right"]).as_dict()}
    assert not rows[0]["outlier"] and rows[1]["outlier"]
    assert ORB.detector() == {
        "n_features": 500,
        "fast_threshold": 12,
        "n_levels": 4,
        "edge_threshold": 19,
    }


def _orb_df() -> pd.DataFrame:
    frames = pd.DataFrame(
        {
            "frame_id": [3, 0, 1, 2, 4, 5],
            "shard": [1, 0, 0, 0, 1, 1],
            "idx": [0, 0, 1, 2, 1, 2],
            "scenario": [1, 0, 0, 0, 1, 1],
            "split": ["test", "train", "train", "train", "test", "test"],
            "fault": ["vertical", "none", "none", "delay", "none", "vertical"],
            "speed": [10.0, 10.0, 2.0, 8.0, 1.0, 3.0],
        }
    )
    res = pd.DataFrame(
        {
            "shard": [0, 0, 0, 1, 1, 1],
            "idx": [0, 1, 2, 0, 1, 2],
            "n_matches": [60, 60, 60, 60, 0, 60],
            "n_reliable": [40, 40, 40, 40, 0, 40],
            "mean_dx": [8.0, 6.0, 0.5, 7.0, np.nan, 7.0],
            "mean_dy": [0.5, 2.5, 0.4, 9.0, np.nan, 4.0],
            "outlier": [False, False, True, True, True, False],
        }
    )
    return orb_frames(frames, res)


def test_orb_frames_joins_by_frame_id():
    df = _orb_df()
    assert list(df.frame_id) == [0, 1, 2, 3, 4, 5]
    assert list(df.fault) == ["none", "none", "delay", "vertical", "none", "vertical"]
    assert list(df.outlier) == [False, False, True, True, True, False]
    assert {
        "frame_id",
        "scenario",
        "fault",
        "n_matches",
        "n_reliable",
        "mean_dx",
        "mean_dy",
    } <= set(df.columns)
    # orb.csv = these, the paper's all-match means, the valid share and one flag per rule
    assert TABLE_COLUMNS[:6] == (
        "frame_id",
        "n_matches",
        "n_reliable",
        "mean_dx",
        "mean_dy",
        "outlier",
    )


def test_orb_metrics_hand_counts():
    m = orb_metrics(_orb_df(), ("train", "val", "test"), ("none", "delay", "vertical"), 8, 1.0)
    assert m["all/frames"] == 6 and m["all/dropped_share"] == pytest.approx(3 / 6)
    assert m["all/false_alarm_rate"] == pytest.approx(1 / 3)  # frame 4 of 0, 1, 4
    assert m["all/detection_rate"] == pytest.approx(2 / 3)  # frames 2, 3 of 2, 3, 5
    assert m["all/faults_delay"] == 1 and m["all/faults_vertical"] == 2
    assert m["vertical/detection_rate"] == pytest.approx(1 / 2)
    assert m["vertical/detection_rate_speed_ge_5"] == pytest.approx(1.0)  # frame 3 only
    assert m["delay/detection_rate"] == 1.0
    assert m["train/dropped_share"] == pytest.approx(1 / 3) and "val/dropped_share" not in m
    assert "all/faults_none" not in m  # fault-free is not a fault group
    # |dy| sweep on the same statistics: 2 px flags frame 1 (2.5 px) and frame 5 (4 px) too
    assert m["sweep/max_dy_2_false_alarm_rate"] == pytest.approx(2 / 3)  # frames 1, 4
    assert m["sweep/max_dy_5_vertical_detection_rate"] == pytest.approx(1 / 2)
    assert m["sweep/max_dy_3_vertical_detection_rate"] == pytest.approx(1.0)
    assert m["none/mean_dy_median"] == pytest.approx(1.5)  # of 0.5, 2.5 (NaN skipped)


def test_sweep_uses_the_configured_min_reliable_and_min_dx():
    df = _orb_df()
    df.loc[df.frame_id == 0, "n_reliable"] = 5  # frame 0: clean, 5 reliable matches, dx 8, dy 0.5
    df.loc[df.frame_id == 5, "mean_dx"] = 3.0  # frame 5: vertical fault, dy 4 px
    faults = ("none", "delay", "vertical")
    loose = orb_metrics(df, ("train", "val", "test"), faults, 1, 1.0)
    strict = orb_metrics(df, ("train", "val", "test"), faults, 8, 4.0)
    # at |dy| > 5 px: loose flags only frame 4 (no matches) of the clean frames 0, 1, 4
    assert loose["sweep/max_dy_5_false_alarm_rate"] == pytest.approx(1 / 3)
    # min_reliable 8 flags frame 0 (5 matches) too
    assert strict["sweep/max_dy_5_false_alarm_rate"] == pytest.approx(2 / 3)
    # min_dx 4 px flags frame 5 (dx 3 px) though its dy of 4 px passes
    assert loose["sweep/max_dy_5_vertical_detection_rate"] == pytest.approx(1 / 2)
    assert strict["sweep/max_dy_5_vertical_detection_rate"] == pytest.approx(1.0)
