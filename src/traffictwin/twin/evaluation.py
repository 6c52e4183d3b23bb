"""Risk from the twin vs from the ego's own map vs the simulator's truth, with sequence-bootstrap CIs.

For every sequence, frame and twin method the ego's corridor time headway is computed from a map
(:func:`traffictwin.risk.metric.occupancy_distance` on ``m_O >= occ_threshold``, the ego's own
footprint ignored) and compared with the truth (``thw_true``: the same metric on the simulator's
boxes). Row ``ego`` is the ego's own map (no cooperation). A frame is *critical* when the true
THW is below ``critical_thw`` (1.5 s) and *flagged* by a map when the map's THW is below it.

Numbers per configuration, method and scenario kind (``occluded`` / ``open`` / ``all``):

- ``recall`` — share of critical frames flagged; ``false_alarm_rate`` — share of non-critical
  frames flagged (frame-level means, CIs resample sequences);
- ``recall_vs_ego`` — paired difference of recall to the ego's own map (same frames);
- ``lead_time_s`` — per sequence with a critical frame: time of the ego's first flag within the
  critical episode minus the method's (a method that never flags in the episode counts as
  flagging one frame after its end), mean over sequences with its CI;
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
from traffictwin.grid import GridSpec
from traffictwin.risk.metric import headway, occupancy_distance
from traffictwin.sim.cooperative import HAZARDS, KINDS
from traffictwin.sim.scene import relative_pose
from traffictwin.stats import Interval, excludes_zero, mean_ci, paired_mean_difference_ci
from traffictwin.twin.config import TwinEvalSettings
from traffictwin.twin.data import twin_risk_config
from traffictwin.twin.fuse import TWIN_METHODS, Twin

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
) -> pd.DataFrame:
    """One row per (method incl. ``ego``, frame) of one sequence's arrays (:mod:`traffictwin.twin.data`)
    at pose noise ``(r m, alpha deg)``; ``models[method]`` the models the method needs. With the
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
    rows = []
    for t in range(T):
        v = float(arrays["speeds"][t, 0])
        common = {
            **base,
            "frame": t,
            "time": float(arrays["time"][t]),
            "speed": v,
            "thw_true": float(arrays["thw_true"][t]),
            "ego_sees_hazard": bool(arrays["hazard_seen"][t, 0]),
            "others_see_hazard": bool(arrays["hazard_seen"][t, 1:].any()),
        }
        thw = map_thw(maps[t, 0], v, arrays["path"][t], float(arrays["lane_width"][t]), grid, s)
        rows.append({**common, "method": EGO, "thw": thw, "left_out": 0, "step_ms": 0.0})
        # each registration of this frame once, for every method using it
        shared: dict = {"registered_results": pre[t]} if t in pre else {}
        for m in methods:
            step = twins[m].update(float(arrays["time"][t]), maps[t], rel[t], shared)
            thw = map_thw(
                step.masses, v, arrays["path"][t], float(arrays["lane_width"][t]), grid, s
            )
            rows.append(
                {
                    **common,
                    "method": m,
                    "thw": thw,
                    "left_out": int(N - step.used.sum()),
                    "step_ms": 1000.0 * step.seconds,
                }
            )
    f = pd.DataFrame(rows)
    f["critical"] = f["thw_true"] < s.critical_thw
    f["flagged"] = f["thw"] < s.critical_thw
    return f


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


def lead_times(frame: pd.DataFrame, method: str, fps: float) -> pd.DataFrame:
    """Per sequence with a critical frame: first flag of ``method`` and of ``ego`` within the
    critical episode (s; one frame after the episode's end when never) and ``lead_s`` = ego - method."""
    out = []
    dt = 1.0 / fps
    for seq, g in frame[frame["method"].isin([method, EGO])].groupby("sequence", sort=True):
        crit = g[g["critical"]]
        if crit.empty:
            continue
        end = float(crit["time"].max()) + dt
        first = {}
        for m in (method, EGO):
            hit = crit[(crit["method"] == m) & crit["flagged"]]
            first[m] = float(hit["time"].min()) if len(hit) else end
        out.append(
            {
                "sequence": seq,
                "kind": g["kind"].iloc[0],
                "hazard": g["hazard"].iloc[0],
                "onset_s": float(crit["time"].min()),
                "first_flag_s": first[method],
                "ego_first_flag_s": first[EGO],
                "lead_s": first[EGO] - first[method],
            }
        )
    return pd.DataFrame(out)


def _ci(iv: Interval) -> list[float]:
    return [round(iv.lo, 6), round(iv.hi, 6)]


def summarise(
    frame: pd.DataFrame, methods: list[str], fps: float, s: TwinEvalSettings
) -> dict[str, Any]:
    """Aggregates of one configuration's frame table (see the module docstring): ``{method: {kind: {...}}}``."""
    boot = dict(n_boot=s.n_boot, seed=s.seed, level=s.level)
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
                undefined += ["lead_time_s", "lead_time_s_ci"]
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
            if m != EGO:
                lt = lead_times(f, m, fps)
                if len(lt):
                    iv = mean_ci(lt["lead_s"].to_numpy(), lt["sequence"].to_numpy(), **boot)
                    res["lead_time_s"], res["lead_time_s_ci"] = round(iv.estimate, 6), _ci(iv)
                others = g["vehicles"] - 1
                res["left_out_share"] = round(float(g["left_out"].sum() / max(others.sum(), 1)), 6)
            out[m][kind] = res
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


def targets(summary: dict[str, Any], headline: str, configuration: str) -> dict[str, Any]:
    """The issue's targets at ``configuration`` for the ``headline`` twin (values, CIs, pass/fail):
    occluded recall >= 0.9, occluded recall above the ego's own (CI excluding 0), occluded mean
    lead time > 0.5 s, open false-alarm rate <= 0.05."""
    if configuration not in summary:
        return {"configuration": configuration, "evaluated": False}
    occ = summary[configuration]["methods"].get(headline, {}).get("occluded", {})
    opn = summary[configuration]["methods"].get(headline, {}).get("open", {})
    out: dict[str, Any] = {
        "configuration": configuration,
        "method": headline,
        "evaluated": bool(occ),
    }
    if not occ:
        return out

    def entry(value: Any, ci: Any, ok: bool | None) -> dict[str, Any]:
        return {"value": value, "ci": ci, "pass": ok}

    r = occ.get("recall")
    out["occluded_recall_ge_0.9"] = entry(r, occ.get("recall_ci"), None if r is None else r >= 0.9)
    d = occ.get("recall_vs_ego")
    out["occluded_recall_above_ego"] = entry(
        d,
        occ.get("recall_vs_ego_ci"),
        None if d is None else bool(d > 0 and occ["recall_vs_ego_excludes_zero"]),
    )
    lt = occ.get("lead_time_s")
    out["occluded_lead_time_gt_0.5s"] = entry(
        lt, occ.get("lead_time_s_ci"), None if lt is None else lt > 0.5
    )
    fa = opn.get("false_alarm_rate")
    out["open_false_alarms_le_0.05"] = entry(
        fa, opn.get("false_alarm_rate_ci"), None if fa is None else fa <= 0.05
    )
    return out
