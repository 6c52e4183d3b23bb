"""The learned stereo network's targets: values, thresholds and the interval rule, by hand."""

from __future__ import annotations

from _acceptance import thresholds

from traffictwin.stereo.targets import stereo_targets

STEREO = thresholds("stereo")  # acceptance.stereo


def test_point_targets_and_the_interval_target_by_hand() -> None:
    m = {
        "learned/own/crit_obj_relerr_median": 0.03,
        "learned/own/crit_obj_relerr_median_lo": 0.02,
        "learned/own/crit_obj_relerr_median_hi": 0.04,  # the interval crosses: a point target
        "learned/own/crit_obj_relerr_p90": 0.12,
        "diff_learned_minus_sgm/common/epe": -0.05,
        "diff_learned_minus_sgm/common/epe_lo": -0.08,
        "diff_learned_minus_sgm/common/epe_hi": 0.01,  # reaches 0: not shown below
    }
    t = stereo_targets(m, STEREO)
    assert set(t) == set(STEREO)
    assert t["learned_crit_obj_relerr_median"]["met"] is True
    assert t["learned_crit_obj_relerr_median"]["value_hi"] == 0.04
    assert t["learned_crit_obj_relerr_p90"]["met"] is False
    assert t["learned_minus_sgm_epe"]["met"] is False
    m["diff_learned_minus_sgm/common/epe_hi"] = -0.001
    assert stereo_targets(m, STEREO)["learned_minus_sgm_epe"]["met"] is True


def test_a_missing_value_is_not_evaluated_never_met() -> None:
    t = stereo_targets({}, STEREO)
    assert all(e["met"] is None and e["value"] is None for e in t.values())


def test_the_stereo_targets_follow_their_thresholds() -> None:
    """Moving a threshold in the config moves the verdict, the reported threshold and operator."""
    import dataclasses

    m = {"learned/own/crit_obj_relerr_median": 0.03}
    assert stereo_targets(m, STEREO)["learned_crit_obj_relerr_median"]["met"] is True
    t = {"x": dataclasses.replace(STEREO["learned_crit_obj_relerr_median"], value=0.02)}
    e = stereo_targets(m, t)["x"]
    assert e["met"] is False and e["threshold"] == 0.02 and e["op"] == "<="
