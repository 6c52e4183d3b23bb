"""The targets on the twin's summary: value, CI and whether met."""

from __future__ import annotations

from typing import Any

from traffictwin.twin.evaluation import NAIVE

__all__ = ["targets"]


def _entry(value: Any, ci: Any, met: bool | None, **extra: Any) -> dict[str, Any]:
    return {"value": value, "ci": ci, "met": met, **extra}


def targets(summary: dict[str, Any], headline: str, configuration: str) -> dict[str, Any]:
    """The targets at ``configuration`` for the ``headline`` twin (value, CI, met):

    - occluded: recall >= 0.9 and above the ego's own map (CI excluding 0);
    - occluded: median lead over the ego's own map (paired per episode) >= 0.8 s with its CI
      wholly above 0; >= 95 % of critical episodes warned before their onset;
    - open: false alarms (warnings with no critical frame within the horizon) <= 5 % of frames,
      under per-frame pose noise and under the persistent bias (``pose_bias``; ``met`` None when
      not evaluated);
    - registration matters: the headline's mean lead over the naive twin's CI above 0 (occluded),
      its false-alarm share minus the naive twin's CI below 0 (open, per-frame noise and bias);
    - predictive measure (TTC, :mod:`traffictwin.twin.predict`) vs THW on the headline's maps:
      warns earlier (mean paired lead difference over all critical episodes, CI above 0) without
      more false alarms (open, per-frame noise: paired difference of the false-alarm share, CI
      including or below 0)."""
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
    out.update(_warning_targets(occ, opn, bias))
    if headline != NAIVE:
        always = (entry.get("always_warns") or {}).get("occluded", {})
        out.update(_registration_targets(occ, opn, bias, always))
    pall = entry["methods"].get(headline, {}).get("all", {}).get("predictive", {})
    out.update(_predictive_targets(pall, opn.get("predictive", {})))
    return out


def _ge(v: Any, x: float) -> bool | None:
    return None if v is None else bool(v >= x)


def _le(v: Any, x: float) -> bool | None:
    return None if v is None else bool(v <= x)


def _above0(ci: Any) -> bool | None:
    return None if ci is None else bool(ci[0] > 0)


def _below0(ci: Any) -> bool | None:
    return None if ci is None else bool(ci[1] < 0)


def _warning_targets(occ: dict, opn: dict, bias: dict) -> dict[str, Any]:
    """Recall, lead over the ego's map and warned-before-onset (occluded); false alarms (open)."""
    out: dict[str, Any] = {}
    r = occ.get("recall")
    out["occluded_recall_ge_0.9"] = _entry(r, occ.get("recall_ci"), _ge(r, 0.9))
    d = occ.get("recall_vs_ego")
    out["occluded_recall_above_ego"] = _entry(
        d,
        occ.get("recall_vs_ego_ci"),
        None if d is None else bool(d > 0 and occ["recall_vs_ego_excludes_zero"]),
    )
    v, ci = occ.get("lead_vs_ego_s_median"), occ.get("lead_vs_ego_s_median_ci")
    ok = _ge(v, 0.8)
    out["occluded_median_lead_vs_ego_ge_0.8s"] = _entry(
        v, ci, None if ok is None else bool(ok and _above0(ci))
    )
    v = occ.get("warned_before_onset_share")
    out["occluded_warned_before_onset_ge_0.95"] = _entry(
        v, occ.get("warned_before_onset_share_ci"), _ge(v, 0.95)
    )
    v = opn.get("false_alarm_share")
    out["open_false_alarms_le_0.05_frame_noise"] = _entry(
        v, opn.get("false_alarm_share_ci"), _le(v, 0.05)
    )
    v = bias.get("false_alarm_share")
    out["open_false_alarms_le_0.05_pose_bias"] = _entry(
        v, bias.get("false_alarm_share_ci"), _le(v, 0.05)
    )
    return out


def _registration_targets(occ: dict, opn: dict, bias: dict, always: dict) -> dict[str, Any]:
    """The headline against the naive twin: mean lead (occluded), false alarms (open). Beside the
    lead, what a constant warning (``always``, :func:`traffictwin.twin.summary.always_warning_reference`)
    scores on the same comparison: the lead rewards warning more often."""
    ci = occ.get(f"lead_vs_{NAIVE}_s_mean_ci")
    out = {
        "registration_lead_above_naive": _entry(
            occ.get(f"lead_vs_{NAIVE}_s_mean"),
            ci,
            _above0(ci),
            always_warns_value=always.get(f"lead_vs_{NAIVE}_s_mean"),
            always_warns_ci=always.get(f"lead_vs_{NAIVE}_s_mean_ci"),
            note="occluded, per critical episode: the headline's lead minus the naive twin's "
            "(mean, s; CI above 0 = met); always_warns_*: the same for a warning at every frame",
        )
    }
    ci = opn.get(f"false_alarm_share_vs_{NAIVE}_ci")
    out["registration_false_alarms_below_naive_frame_noise"] = _entry(
        opn.get(f"false_alarm_share_vs_{NAIVE}"), ci, _below0(ci)
    )
    ci = bias.get(f"false_alarm_share_vs_{NAIVE}_ci")
    out["registration_false_alarms_below_naive_pose_bias"] = _entry(
        bias.get(f"false_alarm_share_vs_{NAIVE}"), ci, _below0(ci)
    )
    return out


def _predictive_targets(pall: dict, popen: dict) -> dict[str, Any]:
    """The predictive measure against THW on the headline's maps: earlier, no more false alarms."""
    ci = pall.get("lead_vs_thw_s_mean_ci")
    out = {
        "predictive_warns_earlier_than_thw": _entry(
            pall.get("lead_vs_thw_s_mean"),
            ci,
            _above0(ci),
            note="all kinds, per critical episode: predictive (TTC) first warning minus THW's, "
            "same maps (mean, s; CI above 0 = met)",
            median=pall.get("lead_vs_thw_s_median"),
            median_ci=pall.get("lead_vs_thw_s_median_ci"),
        )
    }
    ci = popen.get("false_alarm_share_vs_thw_ci")
    out["predictive_no_more_false_alarms"] = _entry(
        popen.get("false_alarm_share_vs_thw"),
        ci,
        None if ci is None else bool(ci[0] <= 0),
        note="open, per-frame noise: predictive minus THW false-alarm share, same frames "
        "(CI including or below 0 = met)",
    )
    return out
