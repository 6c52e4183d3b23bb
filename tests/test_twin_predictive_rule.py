"""The predictive warning's rule (level + confirmation), chosen on validation sequences."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from traffictwin.twin.evaluation import TwinEvalSettings
from traffictwin.twin.predict import PredictSettings
from traffictwin.twin.predictive_rule import PredictiveRule, apply_rule, confirmed
from traffictwin.twin.rule_choice import candidate_rules, choose_rule


def test_confirmed_counts_consecutive_rows_within_each_group() -> None:
    b = np.array([1, 1, 0, 1, 1, 1, 1, 0, 1], bool)
    g = np.array([0, 0, 0, 0, 0, 1, 1, 1, 1])
    np.testing.assert_array_equal(confirmed(b, g, 1), b)
    # a run does not carry over into the next group (row 5 starts group 1)
    np.testing.assert_array_equal(confirmed(b, g, 2), [0, 1, 0, 0, 1, 0, 1, 0, 0])
    assert not confirmed(b, g, 3).any()
    assert confirmed(np.zeros(0, bool), np.zeros(0), 2).shape == (0,)


def test_predictive_rule_rejects_bad_values() -> None:
    with pytest.raises(ValueError, match="confirm_frames >= 1"):
        PredictiveRule(2.0, 0)
    with pytest.raises(ValueError, match="warn_s > 0"):
        PredictiveRule(0.0, 1)


def _table() -> pd.DataFrame:
    """10 Hz, 10 frames. Sequence 0 (occluded): critical from frame 6, THW warns from 6, the TTC
    is 2.2 s at frame 3 and 1.8 s from frame 4. Sequence 1 (open): no episode, the TTC dips to
    1.0 s at frame 2 only (one frame pair's motion)."""
    rows = []
    for seq, kind in ((0, "occluded"), (1, "open")):
        for i in range(10):
            if seq == 0:
                ttc = 2.2 if i == 3 else (1.8 if i >= 4 else np.inf)
            else:
                ttc = 1.0 if i == 2 else np.inf
            crit = seq == 0 and i >= 6
            rows.append(
                {
                    "sequence": seq,
                    "kind": kind,
                    "hazard": "pedestrian",
                    "vehicles": 3,
                    "method": "twin",
                    "frame": i,
                    "time": i / 10,
                    "thw_true": 1.0 if crit else 3.0,
                    "ttc_true": np.inf,
                    "critical": crit,
                    "flagged": crit,
                    "ttc": ttc,
                }
            )
    return pd.DataFrame(rows)


def test_apply_rule_flags_per_method_and_sequence_in_frame_order() -> None:
    f = _table().sample(frac=1.0, random_state=0)  # row order must not matter
    a = apply_rule(f, PredictiveRule(2.5, 1)).sort_values(["sequence", "frame"])
    assert a["flagged_ttc"].tolist() == [i >= 3 for i in range(10)] + [i == 2 for i in range(10)]
    b = apply_rule(f, PredictiveRule(2.5, 2)).sort_values(["sequence", "frame"])
    assert b["flagged_ttc"].tolist() == [i >= 4 for i in range(10)] + [False] * 10
    c = apply_rule(f, PredictiveRule(2.0, 1)).sort_values(["sequence", "frame"])
    assert c["flagged_ttc"].tolist() == [i >= 4 for i in range(10)] + [i == 2 for i in range(10)]


def test_choose_rule_takes_the_fewest_false_alarms_among_those_that_warn_earlier() -> None:
    s = TwinEvalSettings(
        critical_thw=1.5, predict=PredictSettings(warn_s=1.5), n_boot=50, horizon_s=0.3
    )
    cands = [PredictiveRule(2.5, 1), PredictiveRule(2.5, 2)]
    rule, rows = choose_rule(_table(), "twin", cands, 10.0, s)
    # unconfirmed: first warning at 0.3 s (the window opens at 0.6 - 0.3), THW's at the onset;
    # the open dip is a false alarm (1 of the 7 judged frames)
    assert rows[0]["lead_vs_thw_s_mean"] == pytest.approx(0.3)
    assert rows[0]["false_alarm_share_vs_thw"] == pytest.approx(1 / 7)
    # confirmed over 2 frames: 0.1 s later, no false alarm
    assert rows[1]["lead_vs_thw_s_mean"] == pytest.approx(0.2)
    assert rows[1]["false_alarm_share_vs_thw"] == pytest.approx(0.0)
    assert rule == cands[1] and [r["selected"] for r in rows] == [False, True]
    assert all(r["eligible"] for r in rows)
    # a rule that never warns earlier than THW is not eligible, however few its false alarms
    late = [PredictiveRule(2.5, 1), PredictiveRule(0.5, 1)]
    rule, rows = choose_rule(_table(), "twin", late, 10.0, s)
    assert rule == late[0] and rows[1]["eligible"] is False
    with pytest.raises(ValueError, match="no candidates"):
        choose_rule(_table(), "twin", [], 10.0, s)


def test_twin_config_lists_the_configured_rule_first_and_checks_the_candidates() -> None:
    from pathlib import Path

    from omegaconf import OmegaConf

    from traffictwin.config import ConfigError
    from traffictwin.twin.config import twin_config

    base = OmegaConf.load(Path(__file__).resolve().parents[1] / "params.yaml")
    tc = twin_config(base)
    cands = candidate_rules(
        tc.ttc_warn_s, tc.ttc_warn_candidates, tc.ttc_confirm_candidates, tc.reaction_s
    )
    assert cands[0] == PredictiveRule(tc.ttc_warn_s + tc.reaction_s, 1)
    n_levels = len(set(tc.ttc_warn_candidates) | {tc.ttc_warn_s})
    assert len(cands) == len(set(cands)) == n_levels * len(set(tc.ttc_confirm_candidates) | {1})
    assert candidate_rules(1.5, [1.0, 1.5], [2, 1, 2], 1.0) == [
        PredictiveRule(2.5, 1),
        PredictiveRule(2.0, 1),
        PredictiveRule(2.5, 2),
        PredictiveRule(2.0, 2),
    ]
    bad = OmegaConf.merge(base, {"twin": {"ttc_warn_candidates": [1.0, 9.0]}})
    with pytest.raises((ValueError, ConfigError), match="ttc_warn_candidates"):
        twin_config(bad)
    bad = OmegaConf.merge(base, {"twin": {"ttc_confirm_candidates": [0]}})
    with pytest.raises((ValueError, ConfigError), match="ttc_confirm_candidates"):
        twin_config(bad)
