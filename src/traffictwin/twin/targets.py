"""The targets on the twin's summary: value, CI and whether met, judged against their acceptance
thresholds (``acceptance.twin``, :mod:`traffictwin.acceptance`)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from traffictwin.acceptance import Threshold, judge
from traffictwin.twin.evaluation import NAIVE

__all__ = ["TARGET_NAMES", "targets"]

#: the targets :func:`targets` judges (the registration ones only for a headline that is not
#: the naive twin)
TARGET_NAMES = (
    "occluded_recall",
    "occluded_recall_above_ego",
    "occluded_median_lead_vs_ego",
    "occluded_warned_before_onset",
    "open_false_alarms_frame_noise",
    "open_false_alarms_pose_bias",
    "registration_lead_above_naive",
    "registration_false_alarms_below_naive_frame_noise",
    "registration_false_alarms_below_naive_pose_bias",
    "predictive_warns_earlier_than_thw",
    "predictive_no_more_false_alarms",
)


def _met(t: Threshold, value: Any, ci: Any) -> bool | None:
    """Whether ``value`` with its interval ``ci`` (``[lo, hi]``) meets ``t``: None when the
    figure ``t`` is judged on is missing (the value, or the interval for a target judged on it),
    False when it is not a finite number."""
    if (value if t.judged_on == "estimate" else ci) is None:
        return None
    lo, hi = (None, None) if ci is None else (ci[0], ci[1])
    figure = value if t.judged_on == "estimate" else t.figure(value, lo, hi)
    return bool(judge(t, figure, lo, hi).met)


def _entry(
    t: Threshold, value: Any, ci: Any, met: bool | None | str = "judge", **extra: Any
) -> dict[str, Any]:
    return {"value": value, "ci": ci, "met": _met(t, value, ci) if met == "judge" else met, **extra}


def targets(
    summary: dict[str, Any],
    headline: str,
    configuration: str,
    thresholds: Mapping[str, Threshold],
) -> dict[str, Any]:
    """The targets at ``configuration`` for the ``headline`` twin (value, CI, met), against
    ``thresholds`` (``acceptance.twin``; the names of :data:`TARGET_NAMES`):

    - occluded: recall and its margin over the ego's own map (CI excluding 0);
    - occluded: median lead over the ego's own map (paired per episode) with its CI wholly above
      0; share of critical episodes warned before their onset;
    - open: false alarms (warnings with no critical frame within the horizon), share of frames,
      under per-frame pose noise and under the persistent bias (``pose_bias``; ``met`` None when
      not evaluated);
    - registration matters: the headline's mean lead over the naive twin's CI above 0 (occluded),
      its false-alarm share minus the naive twin's CI below 0 (open, per-frame noise and bias);
    - predictive measure (TTC, :mod:`traffictwin.twin.predict`) vs THW on the headline's maps:
      warns earlier (mean paired lead difference over all critical episodes, CI above 0) without
      more false alarms (open, per-frame noise: paired difference of the false-alarm share, CI
      including or below 0)."""
    absent = [n for n in TARGET_NAMES if n not in thresholds]
    if absent:
        raise ValueError(f"twin targets: no acceptance threshold for {absent} (acceptance.twin)")
    if configuration not in summary:
        return {"configuration": configuration, "evaluated": False}
    entry = summary[configuration]
    occ = entry["methods"].get(headline, {}).get("occluded", {})
    opn = entry["methods"].get(headline, {}).get("open", {})
    bias = (entry.get("pose_bias") or {}).get("methods", {}).get(headline, {}).get("open", {})
    out: dict[str, Any] = {
        "configuration": configuration,
        "method": headline,
        "evaluated": bool(occ),
    }
    if not occ:
        return out
    out.update(_warning_targets(thresholds, occ, opn, bias))
    if headline != NAIVE:
        always = (entry.get("always_warns") or {}).get("occluded", {})
        out.update(_registration_targets(thresholds, occ, opn, bias, always))
    pall = entry["methods"].get(headline, {}).get("all", {}).get("predictive", {})
    out.update(_predictive_targets(thresholds, pall, opn.get("predictive", {})))
    return out


def _warning_targets(
    th: Mapping[str, Threshold], occ: dict, opn: dict, bias: dict
) -> dict[str, Any]:
    """Recall, lead over the ego's map and warned-before-onset (occluded); false alarms (open)."""
    out: dict[str, Any] = {}
    name = "occluded_recall"
    out[name] = _entry(th[name], occ.get("recall"), occ.get("recall_ci"))
    name = "occluded_recall_above_ego"
    d, ci = occ.get("recall_vs_ego"), occ.get("recall_vs_ego_ci")
    ok = _met(th[name], d, ci)  # and the interval excludes 0
    out[name] = _entry(
        th[name], d, ci, None if ok is None else bool(ok and occ["recall_vs_ego_excludes_zero"])
    )
    name = "occluded_median_lead_vs_ego"
    out[name] = _entry(
        th[name], occ.get("lead_vs_ego_s_median"), occ.get("lead_vs_ego_s_median_ci")
    )
    name = "occluded_warned_before_onset"
    out[name] = _entry(
        th[name], occ.get("warned_before_onset_share"), occ.get("warned_before_onset_share_ci")
    )
    name = "open_false_alarms_frame_noise"
    out[name] = _entry(th[name], opn.get("false_alarm_share"), opn.get("false_alarm_share_ci"))
    name = "open_false_alarms_pose_bias"
    out[name] = _entry(th[name], bias.get("false_alarm_share"), bias.get("false_alarm_share_ci"))
    return out


def _registration_targets(
    th: Mapping[str, Threshold], occ: dict, opn: dict, bias: dict, always: dict
) -> dict[str, Any]:
    """The headline against the naive twin: mean lead (occluded), false alarms (open). Beside the
    lead, what a constant warning (``always``, :func:`traffictwin.twin.summary.always_warning_reference`)
    scores on the same comparison: the lead rewards warning more often."""
    name = "registration_lead_above_naive"
    out = {
        name: _entry(
            th[name],
            occ.get(f"lead_vs_{NAIVE}_s_mean"),
            occ.get(f"lead_vs_{NAIVE}_s_mean_ci"),
            always_warns_value=always.get(f"lead_vs_{NAIVE}_s_mean"),
            always_warns_ci=always.get(f"lead_vs_{NAIVE}_s_mean_ci"),
            note="occluded, per critical episode: the headline's lead minus the naive twin's "
            "(mean, s; CI above 0 = met); always_warns_*: the same for a warning at every frame",
        )
    }
    name = "registration_false_alarms_below_naive_frame_noise"
    out[name] = _entry(
        th[name],
        opn.get(f"false_alarm_share_vs_{NAIVE}"),
        opn.get(f"false_alarm_share_vs_{NAIVE}_ci"),
    )
    name = "registration_false_alarms_below_naive_pose_bias"
    out[name] = _entry(
        th[name],
        bias.get(f"false_alarm_share_vs_{NAIVE}"),
        bias.get(f"false_alarm_share_vs_{NAIVE}_ci"),
    )
    return out


def _predictive_targets(th: Mapping[str, Threshold], pall: dict, popen: dict) -> dict[str, Any]:
    """The predictive measure against THW on the headline's maps: earlier, no more false alarms."""
    name = "predictive_warns_earlier_than_thw"
    out = {
        name: _entry(
            th[name],
            pall.get("lead_vs_thw_s_mean"),
            pall.get("lead_vs_thw_s_mean_ci"),
            note="all kinds, per critical episode: predictive (TTC) first warning minus THW's, "
            "same maps (mean, s; CI above 0 = met)",
            median=pall.get("lead_vs_thw_s_median"),
            median_ci=pall.get("lead_vs_thw_s_median_ci"),
        )
    }
    name = "predictive_no_more_false_alarms"
    out[name] = _entry(
        th[name],
        popen.get("false_alarm_share_vs_thw"),
        popen.get("false_alarm_share_vs_thw_ci"),
        note="open, per-frame noise: predictive minus THW false-alarm share, same frames "
        "(CI including or below 0 = met)",
    )
    return out
