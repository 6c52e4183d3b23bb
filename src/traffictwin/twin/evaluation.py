"""Risk from the twin vs from the ego's own map vs the simulator's truth, with sequence-bootstrap CIs.

For every sequence, frame and twin method the ego's corridor time headway is computed from a map
(:func:`traffictwin.risk.metric.occupancy_distance` on ``m_O >= occ_threshold``, the ego's own
footprint ignored) and compared with the truth (``thw_true``: the same metric on the simulator's
boxes). Row ``ego`` is the ego's own map (no cooperation). A frame is *critical* when the true
THW is below ``critical_thw`` (1.5 s) and *flagged* (the map warns) when the map's THW is below
``warn_thw`` = ``critical_thw`` + the reaction time ``twin.reaction_s``: a warning that leaves the
driver time to react comes before the episode (at constant speed, ``reaction_s`` before the onset
for a map that sees the hazard); ``reaction_s = 0`` warns at the critical threshold itself.

Numbers per configuration, method and scenario kind (``occluded`` / ``open`` / ``all``):

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

from traffictwin.evidential.noise import apply_pose_noise, scale_noise
from traffictwin.geometry import relative_pose
from traffictwin.grid import GridSpec
from traffictwin.risk.metric import headway, occupancy_distance
from traffictwin.sim.cooperative import HAZARDS, KINDS
from traffictwin.stats import (
    Interval,
    excludes_zero,
    mean_ci,
    paired_mean_difference_ci,
    statistic_ci,
)
from traffictwin.twin.alerts import alarm_events, episode_table, false_alarm_frames
from traffictwin.twin.config import TwinEvalSettings
from traffictwin.twin.data import twin_risk_config
from traffictwin.twin.fuse import TWIN_METHODS, Twin
from traffictwin.twin.predict import cell_velocities, map_ttc

__all__ = [
    "TwinEvalSettings",
    "noisy_relative_poses",
    "map_thw",
    "evaluate_sequence",
    "summarise",
    "step_ms_medians",
    "lead_times",
]

EGO = "ego"
NAIVE = "naive"
TTC = "+ttc"  # suffix of a method's predictive warnings (TTC) in the summaries' frame tables


def scalar(a: np.ndarray) -> int:
    """The one integer a per-sequence scalar array holds (stored 0-d or (1,))."""
    return int(np.asarray(a).reshape(-1)[0])


def noisy_relative_poses(
    poses: np.ndarray, noise_z: np.ndarray, r: float, alpha_deg: float
) -> np.ndarray:
    """Every vehicle's noisy pose in the ego's frame per frame: ``poses (T, N, 3)`` exact world
    poses, ``noise_z (T, N, 3)`` standard-normal draws scaled to the configuration ``(r m,
    alpha deg)`` and added to the world pose (the ego, row 0, knows its own frame). ``(T, N, 3)``."""
    T, N, _ = poses.shape
    out = np.zeros((T, N, 3))
    for t in range(T):
        for k in range(1, N):
            noisy = apply_pose_noise(poses[t, k], scale_noise(noise_z[t, k][None], r, alpha_deg)[0])
            out[t, k] = relative_pose(poses[t, 0], noisy)
    return out


def map_thw(
    masses: np.ndarray,
    speed: float,
    path: np.ndarray,
    lane_width: float,
    grid: GridSpec,
    s: TwinEvalSettings,
) -> float:
    """The ego's corridor THW (s) read from a map ``(2, H, W)`` in its frame (see the module docstring)."""
    occ = np.asarray(masses[1]) >= s.occ_threshold
    d = occupancy_distance(
        occ, grid, twin_risk_config(s.corridor_margin), path, lane_width, s.self_margin
    )
    return float(headway(d, speed))


def ttc_reader(grid: GridSpec, s: TwinEvalSettings, fps: float) -> Any:
    """A callable ``(prev_masses | None, masses, ego_prev, ego_now, speed, path, lane_width) ->
    TTC (s)``: the predictive measure (:mod:`traffictwin.twin.predict`) of one map given the
    previous map of the same source, ``1/fps`` s earlier."""
    rc = twin_risk_config(s.corridor_margin)

    def read(
        prev: np.ndarray | None,
        masses: np.ndarray,
        ego_prev: np.ndarray,
        ego_now: np.ndarray,
        speed: float,
        path: np.ndarray,
        lane_width: float,
    ) -> float:
        vel = cell_velocities(
            prev, masses, ego_prev, ego_now, 1.0 / fps, grid, s.occ_threshold, s.predict
        )
        return map_ttc(
            masses,
            vel,
            path,
            lane_width,
            speed,
            grid,
            s.occ_threshold,
            s.self_margin,
            rc.subject_length,
            rc.subject_width,
            s.predict,
            s.corridor_margin,
        )

    return read


def evaluate_sequence(
    arrays: dict[str, np.ndarray],
    grid: GridSpec,
    noise: tuple[float, float],
    methods: list[str],
    models: dict[str, dict[str, Any]],
    s: TwinEvalSettings,
    registration: Any = None,
    workers: int = 1,
    registered: dict[int, list[Any]] | None = None,
    include_ego: bool = True,
) -> pd.DataFrame:
    """One row per (method incl. ``ego``, frame) of one sequence's arrays (:mod:`traffictwin.twin.data`)
    at pose noise ``(r m, alpha deg)``; ``models[method]`` the models the method needs. Columns
    ``thw`` and ``ttc`` (s): the map's time headway and its time to conflict with the motion
    predicted from the previous frame's map of the same method (:func:`ttc_reader`; at the
    first frame: no motion), ``ttc_true`` the simulator's. ``include_ego=False``: no ``ego`` rows
    (they do not depend on the pose noise: a second noise model reuses the first one's). With the
    ``reference`` strategy the classical registrations of every frame are computed once
    (``registered``: given, from :func:`classical_registrations`; else here, in ``workers``
    processes) and shared by the methods that use them."""
    maps = arrays["maps"]
    T, N = maps.shape[:2]
    rel = noisy_relative_poses(arrays["poses"], arrays["noise_z"], *noise)
    base = {
        "sequence": scalar(arrays["sequence"]),
        "kind": KINDS[scalar(arrays["kind"])],
        "hazard": HAZARDS[scalar(arrays["hazard"])],
        "vehicles": N,
    }
    twins = {
        m: Twin(grid, m, strategy=s.strategy, models=models.get(m), registration=registration)
        for m in methods
    }
    pre: dict[int, list[Any]] = {}
    if uses_classical(methods, s):
        pre = (
            registered
            if registered is not None
            else classical_registrations([arrays], grid, noise, registration, workers)[0]
        )
    fps = 1.0 / float(np.median(np.diff(arrays["time"]))) if T > 1 else 1.0
    read_ttc = ttc_reader(grid, s, fps)
    ego_pose = arrays["poses"][:, 0]
    ttc_true = arrays["ttc_true"] if "ttc_true" in arrays else np.full(T, np.nan)
    prev: dict[str, np.ndarray | None] = dict.fromkeys([EGO, *methods])
    rows = []
    for t in range(T):
        v = float(arrays["speeds"][t, 0])
        path, lw = arrays["path"][t], float(arrays["lane_width"][t])
        ep = ego_pose[max(t - 1, 0)]

        frame_args = (ep, ego_pose[t], v, path, lw)
        common = {
            **base,
            "frame": t,
            "time": float(arrays["time"][t]),
            "speed": v,
            "thw_true": float(arrays["thw_true"][t]),
            "ttc_true": float(ttc_true[t]),
            "ego_sees_hazard": bool(arrays["hazard_seen"][t, 0]),
            "others_see_hazard": bool(arrays["hazard_seen"][t, 1:].any()),
        }
        if include_ego:
            thw = map_thw(maps[t, 0], v, path, lw, grid, s)
            ttc = read_ttc(prev[EGO], maps[t, 0], *frame_args)
            prev[EGO] = maps[t, 0]
            rows.append(
                {**common, "method": EGO, "thw": thw, "ttc": ttc, "left_out": 0, "step_ms": 0.0}
            )
        # each registration of this frame once, for every method using it
        shared: dict = {"registered_results": pre[t]} if t in pre else {}
        for m in methods:
            step = twins[m].update(float(arrays["time"][t]), maps[t], rel[t], shared)
            thw = map_thw(step.masses, v, path, lw, grid, s)
            ttc = read_ttc(prev[m], step.masses, *frame_args)
            prev[m] = step.masses
            rows.append(
                {
                    **common,
                    "method": m,
                    "thw": thw,
                    "ttc": ttc,
                    "left_out": int(N - step.used.sum()),
                    "step_ms": 1000.0 * step.seconds,
                }
            )
    f = pd.DataFrame(rows)
    f["critical"] = f["thw_true"] < s.critical_thw
    f["flagged"] = f["thw"] < s.warn_thw
    f["flagged_ttc"] = f["ttc"] < s.predict.warn_s
    return f


def predictive_frame(frame: pd.DataFrame) -> pd.DataFrame:
    """``frame`` with, for every method ``m``, rows ``m + TTC`` (``"+ttc"``): the same frames with
    ``flagged`` = the predictive warning (``flagged_ttc``), so warnings of both measures on the
    same maps are compared by :func:`warning_metrics` (baseline ``m``)."""
    p = frame.copy()
    p["method"] = p["method"] + TTC
    p["flagged"] = p["flagged_ttc"]
    return pd.concat([frame, p], ignore_index=True)


def uses_classical(methods: list[str], s: TwinEvalSettings) -> bool:
    """Whether a twin method of ``methods`` registers the maps classically onto the reference."""
    return s.strategy == "reference" and any(TWIN_METHODS[m].pose == "registered" for m in methods)


def classical_registrations(
    sequences: list[dict[str, np.ndarray]],
    grid: GridSpec,
    noise: tuple[float, float],
    registration: Any = None,
    workers: int = 1,
) -> list[dict[int, list[Any]]]:
    """The classical registration of every other vehicle's map onto the ego's, for every frame of
    every sequence at pose noise ``(r m, alpha deg)``: per sequence ``{frame: [result of vehicle 1,
    2, ...]}``. All in one :func:`~traffictwin.fusion.methods.register_many` call (one pool of
    ``workers`` processes); the results do not depend on ``workers``."""
    from traffictwin.fusion.methods import register_many

    tasks, m1, m2, poses = [], [], [], []
    for j, arrays in enumerate(sequences):
        maps = arrays["maps"]
        T, N = maps.shape[:2]
        rel = noisy_relative_poses(arrays["poses"], arrays["noise_z"], *noise)
        for t in range(T):
            for k in range(1, N):
                tasks.append((j, t))
                m1.append(maps[t, 0])
                m2.append(maps[t, k])
                poses.append(rel[t, k])
    res = register_many(np.stack(m1), np.stack(m2), np.stack(poses), grid, registration, workers)
    out: list[dict[int, list[Any]]] = [{} for _ in sequences]
    for (j, t), r in zip(tasks, res):
        out[j].setdefault(t, []).append(r)
    return out


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
    """``frame`` with columns ``false_alarm`` (a warning with no critical frame within
    ``horizon_s``, :func:`traffictwin.twin.alerts.false_alarm_frames`) and ``alarm_event`` (the
    first frame of a run of false alarms), per method and sequence."""
    f = frame.copy()
    f["false_alarm"] = False
    f["alarm_event"] = False
    for _, idx in f.groupby(["method", "sequence"], sort=False).groups.items():
        g = f.loc[idx].sort_values("frame")
        fa = false_alarm_frames(
            g["time"].to_numpy(), g["critical"].to_numpy(), g["flagged"].to_numpy(), horizon_s
        )
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
    ``warned_before_onset_share``; ``false_alarm_share`` (of all frames) and
    ``false_alarms_per_min`` (runs of false alarms per minute of driving); per baseline ``b`` in
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
            g = f[f["method"] == m]
            e = f[f["method"] == EGO]
            res: dict[str, Any] = {"frames": int(len(g)), "sequences": int(g["sequence"].nunique())}
            # every key is present; null where undefined (no critical / calm frame of this kind)
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
            res.update(warning_metrics(f, m, fps, s, baselines))
            if has_ttc:
                res["predictive"] = predictive_metrics(f, m, fps, s)
            if kind != "all":
                res["by_hazard"] = {
                    hz: warning_metrics(f[f["hazard"] == hz], m, fps, s, ())
                    for hz in sorted(set(f["hazard"]))
                }
            if m != EGO:
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


def _entry(value: Any, ci: Any, met: bool | None, **extra: Any) -> dict[str, Any]:
    return {"value": value, "ci": ci, "met": met, **extra}


def targets(summary: dict[str, Any], headline: str, configuration: str) -> dict[str, Any]:
    """The issue's targets at ``configuration`` for the ``headline`` twin (value, CI, met):

    - occluded: recall >= 0.9 and above the ego's own map (CI excluding 0) (issue 19);
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

    def ge(v: Any, x: float) -> bool | None:
        return None if v is None else bool(v >= x)

    def le(v: Any, x: float) -> bool | None:
        return None if v is None else bool(v <= x)

    def above0(ci: Any) -> bool | None:
        return None if ci is None else bool(ci[0] > 0)

    def below0(ci: Any) -> bool | None:
        return None if ci is None else bool(ci[1] < 0)

    r = occ.get("recall")
    out["occluded_recall_ge_0.9"] = _entry(r, occ.get("recall_ci"), ge(r, 0.9))
    d = occ.get("recall_vs_ego")
    out["occluded_recall_above_ego"] = _entry(
        d,
        occ.get("recall_vs_ego_ci"),
        None if d is None else bool(d > 0 and occ["recall_vs_ego_excludes_zero"]),
    )
    v, ci = occ.get("lead_vs_ego_s_median"), occ.get("lead_vs_ego_s_median_ci")
    ok = ge(v, 0.8)
    out["occluded_median_lead_vs_ego_ge_0.8s"] = _entry(
        v, ci, None if ok is None else bool(ok and above0(ci))
    )
    v = occ.get("warned_before_onset_share")
    out["occluded_warned_before_onset_ge_0.95"] = _entry(
        v, occ.get("warned_before_onset_share_ci"), ge(v, 0.95)
    )
    v = opn.get("false_alarm_share")
    out["open_false_alarms_le_0.05_frame_noise"] = _entry(
        v, opn.get("false_alarm_share_ci"), le(v, 0.05)
    )
    v = bias.get("false_alarm_share")
    out["open_false_alarms_le_0.05_pose_bias"] = _entry(
        v, bias.get("false_alarm_share_ci"), le(v, 0.05)
    )
    if headline != NAIVE:
        ci = occ.get(f"lead_vs_{NAIVE}_s_mean_ci")
        out["registration_lead_above_naive"] = _entry(
            occ.get(f"lead_vs_{NAIVE}_s_mean"), ci, above0(ci)
        )
        ci = opn.get(f"false_alarm_share_vs_{NAIVE}_ci")
        out["registration_false_alarms_below_naive_frame_noise"] = _entry(
            opn.get(f"false_alarm_share_vs_{NAIVE}"), ci, below0(ci)
        )
        ci = bias.get(f"false_alarm_share_vs_{NAIVE}_ci")
        out["registration_false_alarms_below_naive_pose_bias"] = _entry(
            bias.get(f"false_alarm_share_vs_{NAIVE}"), ci, below0(ci)
        )
    pall = entry["methods"].get(headline, {}).get("all", {}).get("predictive", {})
    popen = opn.get("predictive", {})
    ci = pall.get("lead_vs_thw_s_mean_ci")
    out["predictive_warns_earlier_than_thw"] = _entry(
        pall.get("lead_vs_thw_s_mean"),
        ci,
        above0(ci),
        note="all kinds, per critical episode: predictive (TTC) first warning minus THW's, "
        "same maps (mean, s; CI above 0 = met)",
        median=pall.get("lead_vs_thw_s_median"),
        median_ci=pall.get("lead_vs_thw_s_median_ci"),
    )
    ci = popen.get("false_alarm_share_vs_thw_ci")
    out["predictive_no_more_false_alarms"] = _entry(
        popen.get("false_alarm_share_vs_thw"),
        ci,
        None if ci is None else bool(ci[0] <= 0),
        note="open, per-frame noise: predictive minus THW false-alarm share, same frames "
        "(CI including or below 0 = met)",
    )
    return out
