"""Warnings measured against critical episodes: lead time from the first warning, false alarms by horizon.

A map *warns* at a frame when the risk read from it crosses its threshold (column ``flagged`` of the
evaluation's frame table); a frame is *critical* when the truth does (``critical``). A *critical
episode* is a run of consecutive critical frames of one sequence, from its *onset* ``t0`` (s) to
its last frame ``t1``. With the horizon ``h`` (s, ``twin.horizon_s``):

- a warning at time ``t`` is an *early warning* of an episode when ``t0 - h <= t <= t1`` (and
  after the previous episode's end); the episode's *first warning* ``tw`` is the earliest such
  frame — an episode never warned counts as warned one frame after its end (``t1 + 1/fps``);
- the episode's *lead time* is ``t0 - tw`` (s; > 0: warned before the onset, 0: at the onset,
  < 0: late); it is *warned before its onset* when ``tw < t0``;
- a warning is a *false alarm* when no critical frame lies within ``[t, t + h]`` (no episode
  under way or starting within the horizon) and that window ends by the sequence's last frame;
- a frame is *judged* when its outcome is known: a critical frame lies within ``[t, t + h]`` or
  the window ends by the last frame. A warning in the last ``h`` seconds with no critical frame
  up to the end is right-censored — the episode it announces may start after the recording —
  and counts neither as an early warning nor as a false alarm; false-alarm shares and rates are
  over the judged frames.

With ``h = 0`` the lead time of a method over the ego's own map is the one the evaluation used
at first (the first flag inside the episode). Units: s; rates per minute of judged
driving (1/fps s per judged frame).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

__all__ = [
    "judged_frames",
    "false_alarm_frames",
    "critical_episodes",
    "episode_table",
    "alarm_events",
]

EPS = 1e-6


def _next_critical_gap(time: np.ndarray, critical: np.ndarray, horizon_s: float) -> np.ndarray:
    """Per frame: the time (s) from it to the first critical frame at or after it (inf: none)."""
    if horizon_s < 0:
        raise ValueError(f"horizon_s must be >= 0 s, got {horizon_s}")
    t = np.asarray(time, dtype=np.float64)
    crit_t = t[np.asarray(critical, bool)]
    if crit_t.size == 0:
        return np.full(t.shape, np.inf)
    i = np.searchsorted(crit_t, t - EPS)  # the first critical frame at or after t
    nxt = np.where(i < crit_t.size, crit_t[np.minimum(i, crit_t.size - 1)], np.inf)
    return nxt - t


def judged_frames(time: np.ndarray, critical: np.ndarray, horizon_s: float) -> np.ndarray:
    """Per frame of one sequence (``time`` increasing, s): whether its outcome is known — a
    critical frame within ``[t, t + horizon_s]``, or that window ends by the last frame.
    ``(T,)`` bool."""
    t = np.asarray(time, dtype=np.float64)
    gap = _next_critical_gap(t, critical, horizon_s)
    if t.size == 0:
        return np.zeros(0, bool)
    return (gap <= horizon_s + EPS) | (t + horizon_s <= t[-1] + EPS)


def false_alarm_frames(
    time: np.ndarray, critical: np.ndarray, flagged: np.ndarray, horizon_s: float
) -> np.ndarray:
    """Per frame of one sequence (``time`` increasing, s): flagged and judged
    (:func:`judged_frames`) with no critical frame within ``[t, t + horizon_s]``. ``(T,)`` bool."""
    gap = _next_critical_gap(time, critical, horizon_s)
    judged = judged_frames(time, critical, horizon_s)
    return np.asarray(flagged, bool) & (gap > horizon_s + EPS) & judged


def alarm_events(false_alarm: np.ndarray) -> np.ndarray:
    """Per frame of one sequence: True where a run of false-alarm frames starts (one event per run)."""
    fa = np.asarray(false_alarm, bool)
    prev = np.concatenate([[False], fa[:-1]])
    return fa & ~prev


def critical_episodes(critical: np.ndarray) -> list[tuple[int, int]]:
    """Runs of consecutive critical frames of one sequence: ``[(first, last), ...]`` frame indices."""
    c = np.asarray(critical, bool).astype(np.int8)
    d = np.diff(np.concatenate([[0], c, [0]]))
    starts, ends = np.flatnonzero(d == 1), np.flatnonzero(d == -1) - 1
    return list(zip(starts.tolist(), ends.tolist()))


def episode_table(frame: pd.DataFrame, method: str, fps: float, horizon_s: float) -> pd.DataFrame:
    """One row per critical episode of every sequence of ``frame`` (the evaluation's frame table)
    for ``method``: sequence, kind, hazard, onset_s, end_s, first_warning_s (``end_s + 1/fps``
    when never warned), warned (any warning from ``onset - horizon_s`` to the end), lead_s
    (onset - first warning), before_onset (first warning < onset), horizon_covered (the sequence
    starts at least ``horizon_s`` before the onset)."""
    if horizon_s < 0:
        raise ValueError(f"horizon_s must be >= 0 s, got {horizon_s}")
    dt = 1.0 / fps
    out = []
    g_all = frame[frame["method"] == method]
    for seq, g in g_all.groupby("sequence", sort=True):
        g = g.sort_values("frame")
        t = g["time"].to_numpy(np.float64)
        fl = g["flagged"].to_numpy(bool)
        prev_end = -np.inf
        for a, b in critical_episodes(g["critical"].to_numpy(bool)):
            t0, t1 = t[a], t[b]
            win = (t >= t0 - horizon_s - EPS) & (t <= t1 + EPS) & (t > prev_end + EPS)
            hits = t[win & fl]
            tw = float(hits.min()) if hits.size else t1 + dt
            out.append(
                {
                    "sequence": seq,
                    "kind": g["kind"].iloc[0],
                    "hazard": g["hazard"].iloc[0],
                    "method": method,
                    "onset_s": float(t0),
                    "end_s": float(t1),
                    "first_warning_s": tw,
                    "warned": bool(hits.size),
                    "lead_s": float(t0 - tw),
                    "before_onset": bool(tw < t0 - EPS),
                    "horizon_covered": bool(t[0] <= t0 - horizon_s + EPS),
                }
            )
            prev_end = t1
    cols = [
        "sequence",
        "kind",
        "hazard",
        "method",
        "onset_s",
        "end_s",
        "first_warning_s",
        "warned",
        "lead_s",
        "before_onset",
        "horizon_covered",
    ]
    return pd.DataFrame(out, columns=cols)
