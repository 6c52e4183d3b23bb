"""The predictive warning's rule, chosen on validation sequences: its level and its confirmation.

A map's time to conflict (TTC, :mod:`traffictwin.twin.predict`) warns when it is below a level
``warn_s`` (s, the critical level + the reaction time) for ``confirm_frames`` consecutive frames
of the same source (1: at once). Confirmation is the usual M-of-M track confirmation: a moving
object whose motion is seen in one frame pair only — a partly hidden object's occupied component
changing shape as the ego moves, so its centroid jumps — does not warn.

The rule is chosen (:func:`traffictwin.twin.rule_choice.choose_rule`) on sequences that are not evaluated (the twin data's
``validation`` split), at the target configuration with the headline twin, by a criterion fixed
beforehand: among the candidates whose predictive warning leads the THW warning of the same maps
(mean over critical episodes, all kinds, > 0 s), the one with the fewest false alarms beyond the
THW's on open sequences; ties: the earlier warning (larger lead), then the candidate listed first.
No candidate eligible: the first one. Units: s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

__all__ = ["PredictiveRule", "confirmed", "apply_rule"]


@dataclass(frozen=True)
class PredictiveRule:
    """Warn when the TTC is below ``warn_s`` (s) in ``confirm_frames`` consecutive frames."""

    warn_s: float
    confirm_frames: int = 1

    @property
    def key(self) -> str:
        """A name for tables and JSON keys, e.g. ``below_2.5s_x2``."""
        return f"below_{self.warn_s:g}s_x{self.confirm_frames}"

    def __post_init__(self) -> None:
        if self.warn_s <= 0 or self.confirm_frames < 1:
            raise ValueError(
                f"predictive rule: need warn_s > 0 s and confirm_frames >= 1, got "
                f"{self.warn_s}, {self.confirm_frames}"
            )


def confirmed(below: np.ndarray, group: np.ndarray, frames: int) -> np.ndarray:
    """Per row (rows in time order within each ``group``): whether ``below`` held in this row and
    the ``frames - 1`` rows before it of the same group. ``(n,)`` bool."""
    b = np.asarray(below, bool)
    g = np.asarray(group)
    n = len(b)
    if n == 0 or frames <= 1:
        return b.copy()
    start = np.r_[True, g[1:] != g[:-1]]
    idx = np.arange(n)
    last = np.maximum.accumulate(np.where(~b | start, idx, 0))  # where the current run began
    run = np.where(b, idx - last + b[last], 0)  # consecutive rows below, this one included
    return run >= frames


def apply_rule(frame: pd.DataFrame, rule: PredictiveRule) -> pd.DataFrame:
    """``frame`` (a frame table with ``ttc``) with ``flagged_ttc`` by ``rule``: per method and
    sequence (and ``configuration`` / ``noise`` where present), in frame order."""
    keys = [k for k in ("configuration", "noise", "method", "sequence") if k in frame]
    f = frame.sort_values([*keys, "frame"], kind="stable")
    group = f.groupby(keys, sort=False).ngroup().to_numpy()
    flags = confirmed(f["ttc"].to_numpy(float) < rule.warn_s, group, rule.confirm_frames)
    out = frame.copy()
    out.loc[f.index, "flagged_ttc"] = flags
    out["flagged_ttc"] = out["flagged_ttc"].astype(bool)
    return out
