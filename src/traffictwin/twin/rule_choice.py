"""Choosing the predictive rule (:mod:`traffictwin.twin.predictive_rule`) on validation sequences.

The criterion, fixed beforehand: among the candidates whose predictive warning leads the THW
warning of the same maps (mean over critical episodes, all kinds, > 0 s), the one with the fewest
false alarms beyond the THW's on open sequences; ties: the earlier warning (larger lead), then the
candidate listed first. No candidate eligible: the first one.
"""

from __future__ import annotations

from dataclasses import asdict
from typing import Any

import pandas as pd

from traffictwin.twin.evaluation import predictive_frame
from traffictwin.twin.predictive_rule import PredictiveRule, apply_rule
from traffictwin.twin.summary import add_false_alarms, predictive_metrics

__all__ = ["candidate_rules", "choose_rule"]


def candidate_rules(
    ttc_warn_s: float, warn_levels: list[float], confirm_frames: list[int], reaction_s: float
) -> list[PredictiveRule]:
    """The rules to choose from: every critical level of ``[ttc_warn_s, *warn_levels]`` (s; each
    warns at the level + ``reaction_s``) with every count of ``[1, *confirm_frames]``, the
    configured level unconfirmed first, no rule twice."""
    levels = [ttc_warn_s, *(w for w in warn_levels if w != ttc_warn_s)]
    confirms = [1, *(c for c in confirm_frames if c != 1)]
    rules = [PredictiveRule(round(w + reaction_s, 6), int(c)) for c in confirms for w in levels]
    return list(dict.fromkeys(rules))


def choose_rule(
    frame: pd.DataFrame,
    method: str,
    candidates: list[PredictiveRule],
    fps: float,
    s: Any,
) -> tuple[PredictiveRule, list[dict[str, Any]]]:
    """The rule of ``candidates`` the module's criterion picks on the validation frame table
    ``frame`` (``method``'s and the ego's rows) and, per candidate, its figures: ``lead_vs_thw_s_mean``
    (all kinds), ``false_alarm_share_vs_thw`` (open), ``eligible`` and ``selected``."""
    if not candidates:
        raise ValueError("predictive rule: no candidates to choose from")
    rows = []
    for rule in candidates:
        f = add_false_alarms(predictive_frame(apply_rule(frame, rule)), s.horizon_s)
        allk = predictive_metrics(f, method, fps, s)
        opn = predictive_metrics(f[f["kind"] == "open"], method, fps, s)
        lead, fa = allk.get("lead_vs_thw_s_mean"), opn.get("false_alarm_share_vs_thw")
        rows.append(
            {
                **asdict(rule),
                "lead_vs_thw_s_mean": lead,
                "false_alarm_share_vs_thw": fa,
                "eligible": lead is not None and fa is not None and lead > 0,
            }
        )
    ok = [i for i, r in enumerate(rows) if r["eligible"]]
    best = min(
        ok,
        key=lambda i: (rows[i]["false_alarm_share_vs_thw"], -rows[i]["lead_vs_thw_s_mean"], i),
        default=0,
    )
    for i, r in enumerate(rows):
        r["selected"] = i == best
    return candidates[best], rows
