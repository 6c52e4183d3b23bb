"""Warnings against critical episodes (lead from the first warning, false alarms by
horizon), the persistent pose bias, hidden scenarios — hand-computed cases."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from _acceptance import thresholds

from traffictwin.twin.alerts import (
    alarm_events,
    critical_episodes,
    episode_table,
    false_alarm_frames,
    judged_frames,
)
from traffictwin.twin.evaluation import EGO, TwinEvalSettings
from traffictwin.twin.noise import pose_noise_z
from traffictwin.twin.predict import PredictSettings
from traffictwin.twin.summary import always_warning_reference, summarise
from traffictwin.twin.targets import targets

TWIN = thresholds("twin")


def test_false_alarm_frames_by_horizon() -> None:
    t = np.arange(8) * 0.5  # 0 .. 3.5 s
    crit = np.array([0, 0, 0, 0, 1, 1, 0, 0], bool)  # episode 2.0-2.5 s
    flag = np.array([1, 1, 0, 0, 1, 0, 1, 0], bool)
    # h = 1 s: t = 0 (next critical 2.0 s) and 0.5 (1.5 s) false; 2.0 in the episode; 3.0 after
    # it, but its window (3.0-4.0 s) runs past the last frame (3.5 s): not judged
    np.testing.assert_array_equal(false_alarm_frames(t, crit, flag, 1.0), [1, 1, 0, 0, 0, 0, 0, 0])
    np.testing.assert_array_equal(judged_frames(t, crit, 1.0), [1, 1, 1, 1, 1, 1, 0, 0])
    # h = 0.5 s: the window of t = 3.0 s ends at the last frame: judged, a false alarm
    np.testing.assert_array_equal(false_alarm_frames(t, crit, flag, 0.5), [1, 1, 0, 0, 0, 0, 1, 0])
    # h = 1.5 s: t = 0.5 s is 1.5 s before the onset -> an early warning, not a false alarm
    np.testing.assert_array_equal(false_alarm_frames(t, crit, flag, 1.5), [1, 0, 0, 0, 0, 0, 0, 0])
    # no episode: every judged warning is a false alarm (h = 0.4 s: up to t = 3.1 s judged)
    assert false_alarm_frames(t, np.zeros(8, bool), flag, 0.4).sum() == 4
    # ... and a horizon longer than the sequence judges nothing without an episode
    assert not judged_frames(t, np.zeros(8, bool), 9.0).any()
    np.testing.assert_array_equal(alarm_events(np.array([1, 1, 0, 1, 0], bool)), [1, 0, 0, 1, 0])
    with pytest.raises(ValueError, match="horizon_s"):
        false_alarm_frames(t, crit, flag, -1.0)


def test_censored_warnings_are_not_false_alarms_in_the_summary() -> None:
    # one open sequence, 10 frames at 10 Hz, no episode; the map warns at frames 2 and 8. With
    # h = 0.3 s frames 7-9 are not judged (their window runs past 0.9 s): frame 8's warning may
    # announce an episode after the recording, so one false alarm in 7 judged frames
    rows = [
        {
            "sequence": 0,
            "kind": "open",
            "hazard": "pedestrian",
            "vehicles": 3,
            "method": m,
            "frame": i,
            "time": i / 10,
            "critical": False,
            "flagged": m == "twin" and i in (2, 8),
            "left_out": 0,
        }
        for m in (EGO, "twin")
        for i in range(10)
    ]
    s = summarise(
        pd.DataFrame(rows),
        ["twin"],
        10.0,
        TwinEvalSettings(
            critical_thw=1.5, predict=PredictSettings(warn_s=1.5), n_boot=50, horizon_s=0.3
        ),
    )
    opn = s["twin"]["open"]
    assert opn["false_alarm_share"] == pytest.approx(1 / 7)
    assert opn["driving_min"] == pytest.approx(7 / 10 / 60, abs=1e-4)
    assert opn["false_alarm_share_vs_ego"] == pytest.approx(1 / 7)


def test_critical_episodes_and_episode_table() -> None:
    assert critical_episodes(np.array([0, 1, 1, 0, 1], bool)) == [(1, 2), (4, 4)]
    assert critical_episodes(np.zeros(3, bool)) == []
    rows = []
    for seq, flags in ((0, [0, 1, 0, 0, 1, 1]), (1, [0, 0, 0, 0, 0, 0])):
        for i, fl in enumerate(flags):
            rows.append(
                {
                    "sequence": seq,
                    "kind": "occluded",
                    "hazard": "pedestrian",
                    "method": "m",
                    "frame": i,
                    "time": i / 10,
                    "critical": 3 <= i <= 4,
                    "flagged": bool(fl),
                }
            )
    f = pd.DataFrame(rows)
    ep = episode_table(f, "m", fps=10.0, horizon_s=0.2).set_index("sequence")
    # seq 0: onset 0.3 s, a warning at 0.1 s (0.2 s before: counts) -> lead 0.2 s, before onset
    assert ep.loc[0, "lead_s"] == pytest.approx(0.2) and ep.loc[0, "before_onset"]
    assert ep.loc[0, "horizon_covered"]
    # seq 1: never warned -> one frame after the end (0.5 s): lead 0.3 - 0.5 = -0.2 s
    assert ep.loc[1, "lead_s"] == pytest.approx(-0.2) and not ep.loc[1, "warned"]
    # a horizon of 0.1 s misses the 0.1 s warning: first warning at 0.4 s, lead -0.1 s
    ep = episode_table(f, "m", fps=10.0, horizon_s=0.1).set_index("sequence")
    assert ep.loc[0, "lead_s"] == pytest.approx(-0.1) and not ep.loc[0, "before_onset"]


def test_pose_noise_models() -> None:
    z = np.zeros((4, 3, 3))
    z[:, 1] = [[1.0, 0, 0], [-1.0, 0, 0], [0.5, 0, 0], [0, 0, 0]]
    b = np.zeros((3, 3))
    b[1] = [2.0, 0.0, 1.0]
    np.testing.assert_array_equal(pose_noise_z(z, b, "frame"), z)
    out = pose_noise_z(z, b, "bias", bias_share=0.64)  # sqrt 0.8 * bias + sqrt 0.36 = 0.6 * z
    np.testing.assert_allclose(out[0, 1], [0.8 * 2 + 0.6, 0, 0.8])
    np.testing.assert_allclose(out[3, 1], [1.6, 0, 0.8])  # the bias persists
    assert np.all(out[:, 0] == 0)  # the ego knows its frame
    np.testing.assert_allclose(pose_noise_z(z, b, "bias", 1.0)[2, 1], b[1])
    with pytest.raises(ValueError, match="unknown"):
        pose_noise_z(z, b, "gnss")
    with pytest.raises(ValueError, match="bias_share"):
        pose_noise_z(z, b, "bias", 1.5)
    with pytest.raises(ValueError, match="bias_z"):
        pose_noise_z(z, None, "bias")


def test_bias_draws_persist_and_differ_from_frame_draws() -> None:
    from traffictwin.twin.data import bias_draws, noise_draws

    b = bias_draws(3, 7, 3)
    assert b.shape == (3, 3) and np.all(b[0] == 0) and np.all(b[1:] != 0)
    assert np.array_equal(b, bias_draws(3, 7, 3))
    assert not np.any(np.isclose(noise_draws(3, 7, 5, 3)[:, 1:], b[None, 1:]))


def test_hidden_before_onset_hand_computed() -> None:
    from pipelines.generate_twin import hidden_before_onset_s

    seen = np.array([1, 1, 0, 0, 0, 1, 1], bool)
    assert hidden_before_onset_s(seen, 4, 10.0) == pytest.approx(0.3)  # frames 2, 3, 4
    assert hidden_before_onset_s(seen, 5, 10.0) == 0.0  # seen at the onset
    assert hidden_before_onset_s(np.zeros(5, bool), 4, 10.0) == pytest.approx(0.5)


def _table() -> pd.DataFrame:
    """Two open sequences (no episode), 10 frames at 10 Hz: naive warns 3 frames of sequence 0,
    the twin 1; and one occluded sequence where both warn at the onset."""
    rows = []
    for seq, kind, fl in (
        (
            0,
            "open",
            {"naive": [0, 1, 1, 1, 0, 0, 0, 0, 0, 0], "twin": [0, 1, 0, 0, 0, 0, 0, 0, 0, 0]},
        ),
        (1, "open", {"naive": [0] * 10, "twin": [0] * 10}),
        (2, "occluded", {"naive": [0] * 5 + [1] * 5, "twin": [0] * 5 + [1] * 5}),
    ):
        fl[EGO] = [0] * 10
        for m, flags in fl.items():
            for i, x in enumerate(flags):
                rows.append(
                    {
                        "sequence": seq,
                        "kind": kind,
                        "hazard": "pedestrian",
                        "vehicles": 3,
                        "method": m,
                        "frame": i,
                        "time": i / 10,
                        "thw": 1.0 if x else 3.0,
                        "thw_true": 1.0 if kind == "occluded" and i >= 5 else 3.0,
                        "left_out": 0,
                    }
                )
    f = pd.DataFrame(rows)
    f["critical"] = f["thw_true"] < 1.5
    f["flagged"] = f["thw"] < 1.5
    return f


def test_false_alarm_rates_paired_with_naive_and_targets() -> None:
    # h = 0: every frame of these 1 s sequences is judged (a 2 s horizon would judge none)
    s = summarise(
        _table(),
        ["naive", "twin"],
        10.0,
        TwinEvalSettings(
            critical_thw=1.5, predict=PredictSettings(warn_s=1.5), n_boot=200, horizon_s=0.0
        ),
    )
    opn = s["twin"]["open"]
    assert opn["false_alarm_share"] == pytest.approx(1 / 20)
    # one run of false alarms in 20 frames = 2 s of driving -> 30 per minute
    assert opn["false_alarms_per_min"] == pytest.approx(30.0)
    assert s["naive"]["open"]["false_alarms_per_min"] == pytest.approx(30.0)  # one run of 3
    assert opn["false_alarm_share_vs_naive"] == pytest.approx(1 / 20 - 3 / 20)
    assert s[EGO]["occluded"]["lead_s_median"] == pytest.approx(-0.5)  # never: 0.5 - 1.0
    assert s["twin"]["occluded"]["lead_vs_ego_s_median"] == pytest.approx(0.5)
    assert s["twin"]["occluded"]["by_hazard"]["pedestrian"]["episodes"] == 1
    t = targets({"D": {"methods": s, "pose_bias": {"methods": s}}}, "twin", "D", TWIN)
    assert t["open_false_alarms_frame_noise"]["met"] is True
    assert t["open_false_alarms_pose_bias"]["value"] == pytest.approx(0.05)
    assert t["occluded_warned_before_onset"]["met"] is False  # warned at the onset
    assert t["predictive_warns_earlier_than_thw"]["met"] is None
    nob = targets({"D": {"methods": s}}, "twin", "D", TWIN)
    assert nob["open_false_alarms_pose_bias"]["met"] is None  # not evaluated


def test_a_warning_at_every_frame_reaches_the_most_lead_the_horizon_allows() -> None:
    # the occluded sequence's episode starts at 0.5 s; with h = 0.3 s a constant warning's first
    # warning is at 0.2 s (lead 0.3 s = h), the twin's and naive's at the onset (lead 0)
    st = TwinEvalSettings(
        critical_thw=1.5, predict=PredictSettings(warn_s=1.5), n_boot=200, horizon_s=0.3
    )
    ref = always_warning_reference(_table(), ["naive", "twin"], 10.0, st)
    occ = ref["occluded"]
    assert occ["episodes"] == 1
    assert occ["lead_s_median"] == pytest.approx(0.3)
    assert occ["warned_before_onset_share"] == 1.0
    assert occ["lead_vs_naive_s_mean"] == pytest.approx(0.3)
    assert occ["lead_vs_ego_s_median"] == pytest.approx(0.3 - (0.5 - 1.0))  # ego never warns
    # open: every judged frame is a false alarm (frames 0-6 of each 10-frame sequence judged)
    assert ref["open"]["false_alarm_share"] == pytest.approx(1.0)
    assert ref["open"]["false_alarms_per_min"] == pytest.approx(60.0 * 10.0 / 7)
    s = summarise(_table(), ["naive", "twin"], 10.0, st)
    t = targets({"D": {"methods": s, "always_warns": ref}}, "twin", "D", TWIN)
    reg = t["registration_lead_above_naive"]
    assert reg["value"] == pytest.approx(0.0)  # the twin and naive both warn at the onset
    assert reg["always_warns_value"] == pytest.approx(0.3)
    assert reg["met"] is False


def test_the_report_shows_the_constant_warning_beside_the_methods(tmp_path) -> None:
    import json

    from traffictwin.io.jsonio import json_clean
    from traffictwin.report.model import ReportInputs, Sources
    from traffictwin.twin import report_section as rs

    st = TwinEvalSettings(
        critical_thw=1.5, predict=PredictSettings(warn_s=1.5), n_boot=200, horizon_s=0.3
    )
    s = summarise(_table(), ["naive", "twin"], 10.0, st)
    ref = always_warning_reference(_table(), ["naive", "twin"], 10.0, st)
    entry = {"methods": s, "always_warns": ref}
    m = {"configurations": {"D": entry}, "targets": targets({"D": entry}, "twin", "D", TWIN)}
    (tmp_path / "metrics").mkdir()
    (tmp_path / "metrics" / "twin.json").write_text(json.dumps(json_clean(m)))
    src = Sources(ReportInputs(reports_dir=tmp_path, profile="ci", seed=1, git_commit="x"))
    (table,) = rs.section(src, []).tables
    row = next(r for r in table.rows if r[1].text == rs.ALWAYS_LABEL)
    assert row[6].value == pytest.approx(0.8)  # median lead over the ego map: 0.3 - (-0.5)
    assert row[8].value == 1.0  # warned before the onset
    assert row[10].value == pytest.approx(1.0)  # every judged open frame a false alarm


def _twin_cfg(**twin: object):
    from pathlib import Path

    from omegaconf import OmegaConf

    cfg = OmegaConf.load(Path(__file__).resolve().parents[1] / "conf" / "twin" / "base.yaml")
    cfg = OmegaConf.merge(cfg, OmegaConf.create(twin))
    return OmegaConf.create(
        {
            "twin": cfg,
            "configurations": {"D": {"r": 5.0, "alpha": 20.0}},
            "evaluation": {"risk": {"thresholds_s": [1.5, 1.0]}},  # twin.critical_thw's home
        }
    )


def test_a_map_warns_a_reaction_time_before_the_critical_threshold() -> None:
    from traffictwin.twin.config import twin_config

    tc = twin_config(_twin_cfg(reaction_s=1.0, critical_thw=1.5, ttc_warn_s=1.5, horizon_s=2.0))
    s = tc.settings()
    assert s.critical_thw == 1.5 and s.warn_thw == pytest.approx(2.5)
    # the TTC warns below 1.5 + 1.0 s and is computed that far (beyond the 2 s horizon)
    assert s.predict.warn_s == pytest.approx(2.5) and s.predict.horizon_s == pytest.approx(2.5)
    s0 = twin_config(_twin_cfg(reaction_s=0.0)).settings()
    assert s0.warn_thw == s0.critical_thw and s0.predict.horizon_s == pytest.approx(2.0)
    with pytest.raises(ValueError, match=r"'twin.reaction_s' \(2.5 s\) must not exceed"):
        twin_config(_twin_cfg(reaction_s=2.5, horizon_s=2.0))


def test_a_reaction_time_turns_a_warning_at_the_onset_into_an_early_one() -> None:
    """A map that sees a static hazard from the start (THW falling 0.1 s per 0.1 s frame): with
    the warning at the critical level it warns at the onset (lead 0); a reaction time of 0.5 s
    warns 5 frames before it (lead 0.5 s) and is no false alarm (the episode follows within the
    2 s horizon)."""
    t = np.arange(30) / 10
    thw = 3.0 - t  # truth = the map's estimate
    rows = [
        {
            "sequence": 0,
            "kind": "occluded",
            "hazard": "pedestrian",
            "method": "twin",
            "time": x,
            "frame": i,
            "thw": y,
            "thw_true": y,
        }
        for i, (x, y) in enumerate(zip(t, thw))
    ]
    f = pd.DataFrame(rows)
    f["critical"] = f["thw_true"] < 1.5
    for warn, lead in ((1.5, 0.0), (2.0, 0.5)):
        f["flagged"] = f["thw"] < warn
        ep = episode_table(f, "twin", 10.0, 2.0)
        assert ep["lead_s"].iloc[0] == pytest.approx(lead)
        assert ep["before_onset"].iloc[0] == (lead > 0)
        assert not false_alarm_frames(t, f["critical"], f["flagged"], 2.0).any()
