"""Aggregates of the twin's frame table over sequences, with sequence-bootstrap CIs.

Numbers (:func:`summarise`) per configuration, method and scenario kind (``occluded`` / ``open`` / ``all``):

- ``recall`` — share of critical frames flagged; ``false_alarm_rate`` — share of non-critical
  frames flagged (frame-level means, CIs resample sequences);
- ``recall_vs_ego`` — paired difference of recall to the ego's own map (same frames);
- warnings against critical episodes (:mod:`traffictwin.twin.alerts`, horizon ``horizon_s``):
  ``lead_s_median`` / ``lead_s_mean`` (per episode: onset - first warning, s, warnings from
  ``horizon_s`` before the onset counting), ``warned_before_onset_share``, ``false_alarm_share``
  (share of all frames that warn with no critical frame within the horizon) and
  ``false_alarms_per_min`` (runs of such frames per minute of driving), and paired per episode /
  frame against the ego's own map and the naive twin (``lead_vs_ego_s_median``,
  ``lead_vs_naive_s_mean``, ``false_alarm_share_vs_naive``, ...); ``by_hazard`` per hazard;
- ``left_out_share`` — share of the other vehicles left out of the twin (registration rejected).

The frame table's ``step_ms`` (wall time of each twin update) differs between identical runs:
:func:`step_ms_medians` summarises it for the stage's run record, and the stage drops the column
before writing the table.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from traffictwin.sim.cooperative import KINDS, cooperator_role
from traffictwin.stats import (
    Interval,
    excludes_zero,
    mean_ci,
    paired_mean_difference_ci,
    statistic_ci,
)
from traffictwin.twin.alerts import alarm_events, episode_table, false_alarm_frames, judged_frames
from traffictwin.twin.config import TwinEvalSettings
from traffictwin.twin.evaluation import EGO, NAIVE, TTC, predictive_frame

__all__ = [
    "lead_times",
    "add_false_alarms",
    "warning_metrics",
    "summarise",
    "predictive_metrics",
    "always_warning_reference",
    "vehicle_summaries",
    "OWN",
    "step_ms_medians",
]

ALWAYS = "always"  # the reference warner: warns at every frame (a constant, not a method)


def lead_times(
    frame: pd.DataFrame, method: str, fps: float, horizon_s: float = 0.0
) -> pd.DataFrame:
    """Per critical episode (:func:`traffictwin.twin.alerts.episode_table`, first warning from
    ``horizon_s`` before the onset): the first warning of ``method`` and of ``ego`` (s; one frame
    after the episode's end when never) and ``lead_s`` = ego - method (the method's lead over the
    ego's own map). ``horizon_s = 0``: only warnings inside the episode count."""
    a = episode_table(frame, method, fps, horizon_s)
    e = episode_table(frame, EGO, fps, horizon_s)
    if a.empty:
        return pd.DataFrame(
            columns=[
                "sequence",
                "kind",
                "hazard",
                "onset_s",
                "first_flag_s",
                "ego_first_flag_s",
                "lead_s",
            ]
        )
    m = a.merge(
        e[["sequence", "onset_s", "first_warning_s"]],
        on=["sequence", "onset_s"],
        suffixes=("", "_ego"),
    )
    return pd.DataFrame(
        {
            "sequence": m["sequence"],
            "kind": m["kind"],
            "hazard": m["hazard"],
            "onset_s": m["onset_s"],
            "first_flag_s": m["first_warning_s"],
            "ego_first_flag_s": m["first_warning_s_ego"],
            "lead_s": m["first_warning_s_ego"] - m["first_warning_s"],
        }
    )


def add_false_alarms(frame: pd.DataFrame, horizon_s: float) -> pd.DataFrame:
    """``frame`` with columns ``judged`` (the frame's outcome is known within ``horizon_s``,
    :func:`traffictwin.twin.alerts.judged_frames`), ``false_alarm`` (a judged warning with no
    critical frame within ``horizon_s``, :func:`traffictwin.twin.alerts.false_alarm_frames`) and
    ``alarm_event`` (the first frame of a run of false alarms), per method and sequence."""
    f = frame.copy()
    f["judged"] = False
    f["false_alarm"] = False
    f["alarm_event"] = False
    for _, idx in f.groupby(["method", "sequence"], sort=False).groups.items():
        g = f.loc[idx].sort_values("frame")
        t, crit = g["time"].to_numpy(), g["critical"].to_numpy()
        fa = false_alarm_frames(t, crit, g["flagged"].to_numpy(), horizon_s)
        f.loc[g.index, "judged"] = judged_frames(t, crit, horizon_s)
        f.loc[g.index, "false_alarm"] = fa
        f.loc[g.index, "alarm_event"] = alarm_events(fa)
    return f


def _median_ci(values: np.ndarray, groups: np.ndarray, boot: dict[str, Any]) -> Interval:
    v = np.asarray(values, dtype=np.float64)
    return statistic_ci(lambda idx: float(np.median(v[idx])), len(v), groups, **boot)


def warning_metrics(
    f: pd.DataFrame,
    m: str,
    fps: float,
    s: TwinEvalSettings,
    baselines: tuple[str, ...] = (EGO,),
) -> dict[str, Any]:
    """Episode and false-alarm metrics of method ``m`` on the frame table ``f`` (one scenario kind;
    columns ``false_alarm``, ``alarm_event`` of :func:`add_false_alarms`), with sequence-bootstrap
    CIs: ``episodes``; ``lead_s_median`` / ``lead_s_mean`` (onset - first warning, s);
    ``warned_before_onset_share``; ``false_alarm_share`` (of the judged frames: right-censored
    warnings at the end of a sequence are not judged) and ``false_alarms_per_min`` (runs of false
    alarms per minute of judged driving, ``driving_min``); per baseline ``b`` in
    ``baselines`` (other than ``m``): ``lead_vs_<b>_s_median`` / ``_mean`` (paired, same
    episodes) and ``false_alarm_share_vs_<b>`` (paired, same frames)."""
    boot = dict(n_boot=s.n_boot, seed=s.seed, level=s.level)
    out: dict[str, Any] = {}
    ep = episode_table(f, m, fps, s.horizon_s)
    out["episodes"] = int(len(ep))
    keys = ["lead_s_median", "lead_s_mean", "warned_before_onset_share", "false_alarm_share"]
    keys += ["false_alarms_per_min"]
    for b in baselines:
        if b != m:
            keys += [f"lead_vs_{b}_s_median", f"lead_vs_{b}_s_mean", f"false_alarm_share_vs_{b}"]
    for k in keys:
        out[k], out[f"{k}_ci"] = None, None

    def put(key: str, iv: Interval) -> None:
        out[key], out[f"{key}_ci"] = round(iv.estimate, 6), _ci(iv)

    if len(ep):
        grp = ep["sequence"].to_numpy()
        put("lead_s_median", _median_ci(ep["lead_s"].to_numpy(), grp, boot))
        put("lead_s_mean", mean_ci(ep["lead_s"].to_numpy(), grp, **boot))
        put("warned_before_onset_share", mean_ci(ep["before_onset"].to_numpy(float), grp, **boot))
        out["horizon_covered_share"] = round(float(ep["horizon_covered"].mean()), 6)
    g = f[f["method"] == m].sort_values(["sequence", "frame"], kind="stable")
    g = g[g["judged"]] if "judged" in g else g
    if len(g):
        grp = g["sequence"].to_numpy()
        put("false_alarm_share", mean_ci(g["false_alarm"].to_numpy(float), grp, **boot))
        per_min = g["alarm_event"].to_numpy(float) * 60.0 * fps  # events per minute per frame
        put("false_alarms_per_min", mean_ci(per_min, grp, **boot))
        out["driving_min"] = round(len(g) / fps / 60.0, 4)
    for b in baselines:
        if b == m:
            continue
        eb = episode_table(f, b, fps, s.horizon_s)
        if len(ep) and len(eb):
            j = ep.merge(eb, on=["sequence", "onset_s"], suffixes=("", "_b"))
            d = (j["lead_s"] - j["lead_s_b"]).to_numpy()
            grp = j["sequence"].to_numpy()
            put(f"lead_vs_{b}_s_median", _median_ci(d, grp, boot))
            put(f"lead_vs_{b}_s_mean", mean_ci(d, grp, **boot))
        gb = f[f["method"] == b].sort_values(["sequence", "frame"], kind="stable")
        gb = gb[gb["judged"]] if "judged" in gb else gb  # the same frames: judged by the truth
        if len(g) and len(gb) == len(g):
            put(
                f"false_alarm_share_vs_{b}",
                paired_mean_difference_ci(
                    g["false_alarm"].to_numpy(float),
                    gb["false_alarm"].to_numpy(float),
                    g["sequence"].to_numpy(),
                    **boot,
                ),
            )
    return out


def _ci(iv: Interval) -> list[float]:
    return [round(iv.lo, 6), round(iv.hi, 6)]


def frame_metrics(f: pd.DataFrame, m: str, boot: dict[str, Any]) -> dict[str, Any]:
    """Frame-level numbers of method ``m`` on ``f`` (one scenario kind): frames, sequences,
    ``recall`` / ``false_alarm_rate`` with CIs and, for a method other than the ego's own map, the
    paired ``recall_vs_ego``; every key present, null where undefined (no critical / calm frame)."""
    g = f[f["method"] == m]
    res: dict[str, Any] = {"frames": int(len(g)), "sequences": int(g["sequence"].nunique())}
    undefined = ["recall", "recall_ci", "false_alarm_rate", "false_alarm_rate_ci"]
    if m != EGO:
        undefined += ["recall_vs_ego", "recall_vs_ego_ci", "recall_vs_ego_excludes_zero"]
    res.update(dict.fromkeys(undefined))
    crit = g[g["critical"]]
    res["critical_frames"] = int(len(crit))
    if len(crit):
        iv = mean_ci(crit["flagged"].to_numpy(float), crit["sequence"].to_numpy(), **boot)
        res["recall"], res["recall_ci"] = round(iv.estimate, 6), _ci(iv)
        if m != EGO:
            e = f[f["method"] == EGO]
            ec = e[e["critical"]]
            d = paired_mean_difference_ci(
                crit["flagged"].to_numpy(float),
                ec["flagged"].to_numpy(float),
                crit["sequence"].to_numpy(),
                **boot,
            )
            res["recall_vs_ego"], res["recall_vs_ego_ci"] = round(d.estimate, 6), _ci(d)
            res["recall_vs_ego_excludes_zero"] = excludes_zero(d)
    calm = g[~g["critical"]]
    if len(calm):
        iv = mean_ci(calm["flagged"].to_numpy(float), calm["sequence"].to_numpy(), **boot)
        res["false_alarm_rate"], res["false_alarm_rate_ci"] = round(iv.estimate, 6), _ci(iv)
    return res


def summarise(
    frame: pd.DataFrame, methods: list[str], fps: float, s: TwinEvalSettings
) -> dict[str, Any]:
    """Aggregates of one configuration's frame table (see the module docstring): ``{method: {kind: {...}}}``."""
    boot = dict(n_boot=s.n_boot, seed=s.seed, level=s.level)
    has_ttc = "flagged_ttc" in frame  # hand-built tables may hold THW warnings only
    if has_ttc and not frame["method"].str.endswith(TTC).any():
        frame = predictive_frame(frame)
    if "false_alarm" not in frame:
        frame = add_false_alarms(frame, s.horizon_s)
    baselines = (EGO, NAIVE) if NAIVE in methods else (EGO,)
    out: dict[str, Any] = {}
    for m in [EGO, *methods]:
        out[m] = {}
        for kind in (*KINDS, "all"):
            f = frame if kind == "all" else frame[frame["kind"] == kind]
            res = frame_metrics(f, m, boot)
            res.update(warning_metrics(f, m, fps, s, baselines))
            if has_ttc:
                res["predictive"] = predictive_metrics(f, m, fps, s)
            if kind != "all":
                res["by_hazard"] = {
                    hz: warning_metrics(f[f["hazard"] == hz], m, fps, s, (EGO,))
                    for hz in sorted(set(f["hazard"]))
                }
            if m != EGO:
                g = f[f["method"] == m]
                others = g["vehicles"] - 1
                res["left_out_share"] = round(float(g["left_out"].sum() / max(others.sum(), 1)), 6)
            out[m][kind] = res
    return out


def predictive_metrics(f: pd.DataFrame, m: str, fps: float, s: TwinEvalSettings) -> dict[str, Any]:
    """The predictive warnings (TTC < ``predict.warn_s``) of method ``m``'s maps on the frame
    table ``f`` (one scenario kind, with the rows of :func:`predictive_frame` and
    :func:`add_false_alarms`): :func:`warning_metrics` against the same critical episodes, the
    paired differences to the THW warnings on the same maps (``lead_vs_thw_s_median`` / ``_mean``:
    > 0 the predictive measure warns earlier; ``false_alarm_share_vs_thw``: > 0 more false alarms),
    and its agreement with the simulator's TTC (``ttc_true_recall``: share of frames with a true
    TTC below ``warn_s`` warned; ``ttc_true_false_alarm_rate``: share of the others warned)."""
    boot = dict(n_boot=s.n_boot, seed=s.seed, level=s.level)
    out = warning_metrics(f, m + TTC, fps, s, (m,))
    out = {k.replace(f"_vs_{m}", "_vs_thw"): v for k, v in out.items()}
    g = f[f["method"] == m]
    tt = g["ttc_true"].to_numpy(float) if "ttc_true" in g else np.full(len(g), np.nan)
    label = tt < s.predict.warn_s
    known = ~np.isnan(tt)
    for key, sel in (("ttc_true_recall", label), ("ttc_true_false_alarm_rate", known & ~label)):
        out[key], out[f"{key}_ci"] = None, None
        if sel.any():
            iv = mean_ci(
                g["flagged_ttc"].to_numpy(float)[sel], g["sequence"].to_numpy()[sel], **boot
            )
            out[key], out[f"{key}_ci"] = round(iv.estimate, 6), _ci(iv)
    return out


def always_warning_reference(
    frame: pd.DataFrame, methods: list[str], fps: float, s: TwinEvalSettings
) -> dict[str, Any]:
    """What a constant warning scores: a reference that warns at every frame (``always``, built
    on the ego's rows, so the same frames and episodes), per scenario kind (``occluded`` /
    ``open`` / ``all``): :func:`warning_metrics` paired with the ego's own map and every method of
    ``methods``. Its lead is the most the lead-time definition allows (``horizon_s``, less where a
    sequence starts within it): a method's lead shows what it sees only beside its false alarms."""
    e = frame[frame["method"] == EGO]
    a = e.assign(method=ALWAYS, flagged=True)
    keep = frame[frame["method"].isin(methods)]
    f = add_false_alarms(pd.concat([e, keep, a], ignore_index=True), s.horizon_s)
    baselines = (EGO, *methods)
    return {
        kind: warning_metrics(
            f if kind == "all" else f[f["kind"] == kind], ALWAYS, fps, s, baselines
        )
        for kind in (*KINDS, "all")
    }


OWN = "own"  # the key of a vehicle's own map in :func:`vehicle_summaries`


def vehicle_summaries(
    vehicles: pd.DataFrame, methods: list[str], fps: float, s: TwinEvalSettings
) -> dict[str, Any]:
    """Risk for every other vehicle (the ``vehicles`` frame table of
    :func:`traffictwin.twin.evaluation.evaluate_sequence_tables`): per vehicle ``k`` (key
    ``str(k)``) its ``role`` and, per map it reads — ``own`` (its own map) and every twin method —
    and scenario kind, :func:`summarise`'s numbers (THW warnings; the twin paired with the own
    map in ``*_vs_ego*``) without the per-hazard split."""
    out: dict[str, Any] = {}
    if vehicles.empty:
        return out
    for k, g in vehicles.groupby("vehicle", sort=True):
        res = summarise(g.drop(columns=["vehicle"]).reset_index(drop=True), methods, fps, s)
        out[str(int(k))] = {
            "role": cooperator_role(int(k)),
            "methods": {
                (OWN if m == EGO else m): {
                    kind: {key: v for key, v in r.items() if key != "by_hazard"}
                    for kind, r in kinds.items()
                }
                for m, kinds in res.items()
            },
        }
    return out


def step_ms_medians(frame: pd.DataFrame, methods: list[str]) -> dict[str, dict[str, float]]:
    """Median wall time of a twin update (ms, column ``step_ms``) per method and scenario kind
    (``occluded`` / ``open`` / ``all``) of one configuration's frame table: ``{method: {kind: ms}}``."""
    out: dict[str, dict[str, float]] = {}
    for m in methods:
        g = frame[frame["method"] == m]
        out[m] = {
            kind: round(
                float((g if kind == "all" else g[g["kind"] == kind])["step_ms"].median()), 3
            )
            for kind in (*KINDS, "all")
        }
    return out
