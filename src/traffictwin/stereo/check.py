"""Stereo pair fault detection: the ORB rules and the SGM valid-share rule side by side.

Per pair three flags (each True = "this pair looks broken"):

- ``flag_orb_paper``: the paper's literal rule (Sec. 3.3) over *all* cross-checked ORB matches:
  mean |dx| < ``min_dx`` or mean |dy| > ``max_dy`` (px); no matches -> flagged.
- ``flag_orb``: the same rule over the reliable matches only, plus swapped cameras (median
  signed disparity <= -``min_dx``; :mod:`traffictwin.stereo.orb`).
- ``flag_valid_share``: the SGM map of the pair has a valid share (:func:`~traffictwin.stereo.sgm.valid_share`)
  below ``min_valid_share``. A delayed right image breaks the left-right check wherever the
  scene moved between the two exposures, a vertical shift breaks matching everywhere; a clean
  pair of the default data keeps >= 0.75 of its matchable pixels valid.

``outlier`` (drop the pair) is the configured ``rule``: one flag or ``orb_or_valid_share``
(robust ORB OR valid share). :func:`traffictwin.stereo.detection.detection_table` measures
every rule against the injected faults with scenario-cluster bootstrap intervals.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from traffictwin.config import spec

if TYPE_CHECKING:  # the rules work on data frames they are given (risk_data.check reads none)
    import pandas as pd

#: rule names -> the flag columns they OR together
RULES: dict[str, tuple[str, ...]] = {
    "orb_paper": ("flag_orb_paper",),
    "orb": ("flag_orb",),
    "valid_share": ("flag_valid_share",),
    "orb_or_valid_share": ("flag_orb", "flag_valid_share"),
}
#: the ``fault`` value of a fault-free pair
NO_FAULT = "none"
#: valid-share thresholds of the sensitivity sweep
SWEEP_MIN_VALID_SHARE = (0.7, 0.75, 0.8, 0.85, 0.9)


@dataclass
class StereoCheckParams:
    """``risk_data.check``: which rule drops a pair (``rule``: a key of :data:`RULES`), the
    valid-share threshold (fraction of matchable pixels; ``None``: chosen on the validation split
    by :func:`choose_min_valid_share` among :data:`SWEEP_MIN_VALID_SHARE`, the most faults caught
    with at most ``max_false_alarm`` of the fault-free pairs dropped) and the range bins of the
    depth-error metric (``depth_bins_m``: increasing distances, m)."""

    rule: str = spec(choices=tuple(RULES))
    min_valid_share: float | None = spec(min=0.0, max=1.0)  # None: chosen on validation
    depth_bins_m: list[float] = spec(min=0.0)
    max_false_alarm: float = spec(0.02, min=0.0, max=1.0)  # of the validation choice

    def __post_init__(self) -> None:  # rule and min_valid_share: checked by their spec bounds
        e = np.asarray(self.depth_bins_m, float)
        if e.ndim != 1 or e.size < 2 or e[0] < 0 or np.any(np.diff(e) <= 0):
            raise ValueError(
                f"'check.depth_bins_m' must be >= 2 increasing distances >= 0 m, got {list(self.depth_bins_m)}"
            )


def check_rule(rule: str) -> None:
    """Raise ValueError unless ``rule`` is one of :data:`RULES`."""
    if rule not in RULES:
        raise ValueError(f"'check.rule' must be one of {list(RULES)}, got {rule!r}")


def paper_flag(
    n_matches: pd.Series,
    all_mean_dx: pd.Series,
    all_mean_dy: pd.Series,
    min_dx: float,
    max_dy: float,
) -> pd.Series:
    """The paper's literal ORB rule over all cross-checked matches (no match -> flagged)."""
    return (n_matches < 1) | (all_mean_dx < min_dx) | (all_mean_dy > max_dy) | all_mean_dy.isna()


def add_flags(
    df: pd.DataFrame, *, min_dx: float, max_dy: float, min_valid_share: float, rule: str
) -> pd.DataFrame:
    """``df`` (per pair: ``n_matches``, ``all_mean_dx``, ``all_mean_dy``, ``flag_orb``,
    ``valid_share``) with ``flag_orb_paper``, ``flag_valid_share`` and ``outlier`` (the ``rule``)
    added; thresholds in px and as a fraction."""
    check_rule(rule)
    if not 0.0 <= min_valid_share <= 1.0:
        raise ValueError(f"'check.min_valid_share' must be in [0, 1], got {min_valid_share!r}")
    out = df.copy()
    out["flag_orb_paper"] = paper_flag(
        out.n_matches, out.all_mean_dx, out.all_mean_dy, min_dx, max_dy
    ).astype(bool)
    out["flag_orb"] = out.flag_orb.astype(bool)
    vs = out.valid_share.astype(float)
    if vs.isna().any():
        raise ValueError(f"valid_share missing for {int(vs.isna().sum())} pairs")
    out["flag_valid_share"] = (vs < min_valid_share).astype(bool)
    out["outlier"] = rule_flag(out, rule)
    return out


def rule_flag(df: pd.DataFrame, rule: str) -> pd.Series:
    """The flag of ``rule`` (OR of its :data:`RULES` columns) per row of ``df``."""
    check_rule(rule)
    cols = RULES[rule]
    return df[list(cols)].any(axis=1).astype(bool)


def key_fragment(x: float) -> str:
    """A number as a metrics-key fragment without '.' (0.75 -> 0p75, 5 -> 5)."""
    return f"{float(x):g}".replace(".", "p")


def valid_share_sweep(
    df: pd.DataFrame, faults: Sequence[str], thresholds: Sequence[float] = SWEEP_MIN_VALID_SHARE
) -> dict[str, float]:
    """Sensitivity of the valid-share rule: ``sweep/min_valid_share_<t>_false_alarm_rate`` and
    ``..._<fault>_detection_rate`` for each threshold ``t`` (point estimates)."""
    out: dict[str, float] = {}
    clean = df.fault == NO_FAULT
    for t in thresholds:
        flag = df.valid_share < t
        pre = f"sweep/min_valid_share_{key_fragment(t)}"
        if clean.any():
            out[f"{pre}_false_alarm_rate"] = float(flag[clean].mean())
        for f in faults:
            sel = df.fault == f
            if f != NO_FAULT and sel.any():
                out[f"{pre}_{f}_detection_rate"] = float(flag[sel].mean())
    return out


def choose_min_valid_share(
    df: pd.DataFrame,
    max_false_alarm: float,
    candidates: Sequence[float] = SWEEP_MIN_VALID_SHARE,
) -> tuple[float, list[dict[str, float]]]:
    """The valid-share threshold with the highest detection rate of the injected faults among
    those whose false-alarm rate on the fault-free pairs is at most ``max_false_alarm`` (a
    Neyman–Pearson choice on ``df``, the validation split's pairs: ``fault``, ``valid_share``);
    ties: the lower threshold (fewer dropped pairs); none within the budget: the lowest
    threshold. Returns the threshold and every candidate's rates. ValueError without both
    fault-free and faulty pairs."""
    if not len(candidates):
        raise ValueError("choose_min_valid_share: no candidate thresholds")
    clean = (df["fault"] == NO_FAULT).to_numpy()
    if clean.all() or not clean.any():
        raise ValueError(
            "choose_min_valid_share: the validation split needs fault-free and faulty pairs "
            f"({int(clean.sum())} fault-free of {len(df)})"
        )
    vs = df["valid_share"].to_numpy(np.float64)
    table = []
    for t in sorted(float(c) for c in candidates):
        flag = vs < t
        table.append(
            {
                "min_valid_share": t,
                "detection_rate": float(flag[~clean].mean()),
                "false_alarm_rate": float(flag[clean].mean()),
            }
        )
    ok = [r for r in table if r["false_alarm_rate"] <= max_false_alarm]
    if not ok:
        return table[0]["min_valid_share"], table
    best = max(ok, key=lambda r: (round(r["detection_rate"], 12), -r["min_valid_share"]))
    return best["min_valid_share"], table
