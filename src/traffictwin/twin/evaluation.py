"""Risk from the twin vs from the ego's own map vs the simulator's truth, with sequence-bootstrap CIs.

For every sequence, frame and twin method the ego's corridor time headway is computed from a map
(:func:`traffictwin.risk.metric.occupancy_distance` on ``m_O >= occ_threshold``, the ego's own
footprint ignored) and compared with the truth (``thw_true``: the same metric on the simulator's
boxes). Row ``ego`` is the ego's own map (no cooperation). A frame is *critical* when the true
THW is below ``critical_thw`` (s) and *flagged* (the map warns) when the map's THW is below
``warn_thw`` = ``critical_thw`` + the reaction time ``twin.reaction_s``: a warning that leaves the
driver time to react comes before the episode (at constant speed, ``reaction_s`` before the onset
for a map that sees the hazard); ``reaction_s = 0`` warns at the critical threshold itself.

The aggregation over sequences (recall, lead times, false alarms, with CIs) is
:mod:`traffictwin.twin.summary`; the targets on it are :mod:`traffictwin.twin.targets`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from traffictwin.evidential.noise import apply_pose_noise, scale_noise
from traffictwin.geometry import relative_pose
from traffictwin.grid import GridSpec
from traffictwin.risk.metric import headway, occupancy_distance
from traffictwin.sim.cooperative import HAZARDS, KINDS
from traffictwin.twin.config import TwinEvalSettings
from traffictwin.twin.data import twin_risk_config
from traffictwin.twin.fuse import TWIN_METHODS, Twin, TwinOptions
from traffictwin.twin.predict import MapReading, cell_velocities, map_ttc
from traffictwin.twin.vehicle_view import vehicle_view

__all__ = [
    "TwinEvalSettings",
    "noisy_relative_poses",
    "map_thw",
    "TwinPass",
    "evaluate_sequence",
    "SequenceTables",
    "evaluate_sequence_tables",
    "evaluate_sequences_tables",
    "predictive_frame",
    "classical_registrations",
]

if TYPE_CHECKING:  # the frame tables load pandas where one is built: the twin's targets and
    # settings (check_params) are read without it
    import pandas as pd

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


def map_reading(grid: GridSpec, s: TwinEvalSettings) -> MapReading:
    """How the twin's risk measures read a map: ``s``'s threshold and margins, the ego's footprint
    of the risk label."""
    rc = twin_risk_config(s.corridor_margin)
    return MapReading(
        grid, s.occ_threshold, s.self_margin, rc.subject_length, rc.subject_width, s.corridor_margin
    )


def ttc_reader(grid: GridSpec, s: TwinEvalSettings, fps: float) -> Any:
    """A callable ``(prev_masses | None, masses, ego_prev, ego_now, speed, path, lane_width) ->
    TTC (s)``: the predictive measure (:mod:`traffictwin.twin.predict`) of one map given the
    previous map of the same source, ``1/fps`` s earlier."""
    reading = map_reading(grid, s)

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
        return map_ttc(masses, vel, path, lane_width, speed, reading, s.predict)

    return read


@dataclass(frozen=True)
class TwinPass:
    """One evaluation pass over sequences: the ``grid``, the pose ``noise`` (r m, alpha deg), the
    twin ``methods`` and ``models[method]`` (the models each needs), the evaluation ``settings``,
    the classical ``registration``'s parameters and the ``workers`` processes of the pass (the
    classical registrations, then the sequences)."""

    grid: GridSpec
    noise: tuple[float, float]
    methods: list[str]
    models: dict[str, dict[str, Any]]
    settings: TwinEvalSettings
    registration: Any = None
    workers: int = 1


def _frame_common(arrays: dict[str, np.ndarray], t: int, ttc_true: np.ndarray) -> dict[str, Any]:
    """The columns of frame ``t`` every method's row shares."""
    return {
        "frame": t,
        "time": float(arrays["time"][t]),
        "speed": float(arrays["speeds"][t, 0]),
        "thw_true": float(arrays["thw_true"][t]),
        "ttc_true": float(ttc_true[t]),
        "ego_sees_hazard": bool(arrays["hazard_seen"][t, 0]),
        "others_see_hazard": bool(arrays["hazard_seen"][t, 1:].any()),
    }


@dataclass(frozen=True)
class SequenceTables:
    """One sequence's frame tables: ``frames`` (the ego's risk, :func:`evaluate_sequence`) and
    ``vehicles`` (every other vehicle's, :func:`evaluate_sequence_tables`; empty when not asked
    for or when the data hold no ``vehicle_*`` arrays)."""

    frames: pd.DataFrame
    vehicles: pd.DataFrame


class _VehicleRisk:
    """The other vehicles' rows of one sequence (:func:`evaluate_sequence_tables`, ``vehicles``):
    each vehicle's THW from its own map and from its view of each twin, along its own path."""

    def __init__(
        self, arrays: dict[str, np.ndarray], run: TwinPass, base: dict[str, Any], on: bool
    ) -> None:
        self.a, self.run, self.base = arrays, run, base
        n = arrays["maps"].shape[1]
        self.others = range(1, n) if on and "vehicle_thw_true" in arrays else range(0)
        self.rows: list[dict[str, Any]] = []

    def _add(self, t: int, k: int, method: str, masses: np.ndarray, left_out: int) -> None:
        a = self.a
        v, lw = float(a["speeds"][t, k]), float(a["vehicle_lane_width"][t, k])
        thw = map_thw(masses, v, a["vehicle_path"][t, k], lw, self.run.grid, self.run.settings)
        self.rows.append(
            {
                **self.base,
                "vehicle": k,
                "frame": t,
                "time": float(a["time"][t]),
                "speed": v,
                "thw_true": float(a["vehicle_thw_true"][t, k]),
                "sees_hazard": bool(a["hazard_seen"][t, k]),
                "method": method,
                "thw": thw,
                "left_out": left_out,
            }
        )

    def own_maps(self, t: int) -> None:
        for k in self.others:
            self._add(t, k, EGO, self.a["maps"][t, k], 0)

    def twin(self, t: int, method: str, step: Any) -> None:
        maps, n = self.a["maps"][t], self.a["maps"].shape[1]
        for k in self.others:
            view = vehicle_view(maps, step.poses, step.used, k, self.run.grid)
            self._add(t, k, method, view, int(n - step.used.sum()))

    def table(self) -> pd.DataFrame:
        import pandas as pd

        v = pd.DataFrame(self.rows)
        if len(v):
            v["critical"] = v["thw_true"] < self.run.settings.critical_thw
            v["flagged"] = v["thw"] < self.run.settings.warn_thw
        return v


def _registrations(
    arrays: dict[str, np.ndarray], run: TwinPass, registered: dict[int, list[Any]] | None
) -> dict[int, list[Any]]:
    """The classical registrations of every frame of one sequence, where a method uses them:
    ``registered`` when given, else computed here."""
    if not uses_classical(run.methods, run.settings):
        return {}
    if registered is not None:
        return registered
    return classical_registrations([arrays], run.grid, run.noise, run.registration, run.workers)[0]


def evaluate_sequence(
    arrays: dict[str, np.ndarray],
    run: TwinPass,
    registered: dict[int, list[Any]] | None = None,
    include_ego: bool = True,
) -> pd.DataFrame:
    """The ego's frame table of one sequence (:func:`evaluate_sequence_tables`, ``frames``)."""
    return evaluate_sequence_tables(arrays, run, registered, include_ego).frames


def evaluate_sequence_tables(
    arrays: dict[str, np.ndarray],
    run: TwinPass,
    registered: dict[int, list[Any]] | None = None,
    include_ego: bool = True,
    vehicles: bool = False,
) -> SequenceTables:
    """One row per (method incl. ``ego``, frame) of one sequence's arrays (:mod:`traffictwin.twin.data`)
    in the pass ``run``. Columns ``thw`` and ``ttc`` (s): the map's time headway and its time to
    conflict with the motion predicted from the previous frame's map of the same method
    (:func:`ttc_reader`; at the first frame: no motion), ``ttc_true`` the simulator's.
    ``include_ego=False``: no ``ego`` rows (they do not depend on the pose noise: a second noise
    model reuses the first one's). With the ``reference`` strategy the classical registrations of
    every frame are computed once (``registered``: given, from :func:`classical_registrations`;
    else here) and shared by the methods that use them.

    ``vehicles=True`` (and ``vehicle_*`` arrays in the data): also the table ``vehicles``, one row
    per (other vehicle ``k``, method incl. ``ego`` = the vehicle's own map, frame): ``thw`` read
    from :func:`traffictwin.twin.vehicle_view.vehicle_view` of the method's twin along ``k``'s
    path, ``thw_true`` ``k``'s truth, ``critical`` / ``flagged`` as for the ego (THW only)."""
    s, grid, methods = run.settings, run.grid, run.methods
    maps = arrays["maps"]
    T, N = maps.shape[:2]
    rel = noisy_relative_poses(arrays["poses"], arrays["noise_z"], *run.noise)
    base = {
        "sequence": scalar(arrays["sequence"]),
        "kind": KINDS[scalar(arrays["kind"])],
        "hazard": HAZARDS[scalar(arrays["hazard"])],
        "vehicles": N,
    }
    twins = {
        m: Twin(
            grid,
            TwinOptions(
                m, strategy=s.strategy, models=run.models.get(m), registration=run.registration
            ),
        )
        for m in methods
    }
    pre = _registrations(arrays, run, registered)
    fps = 1.0 / float(np.median(np.diff(arrays["time"]))) if T > 1 else 1.0
    read_ttc = ttc_reader(grid, s, fps)
    ego_pose = arrays["poses"][:, 0]
    ttc_true = arrays["ttc_true"] if "ttc_true" in arrays else np.full(T, np.nan)
    prev: dict[str, np.ndarray | None] = dict.fromkeys([EGO, *methods])
    rows = []
    others = _VehicleRisk(arrays, run, base, vehicles)

    def risk_row(m: str, masses: np.ndarray, t: int, common: dict[str, Any], **extra: Any) -> dict:
        v, path, lw = common["speed"], arrays["path"][t], float(arrays["lane_width"][t])
        thw = map_thw(masses, v, path, lw, grid, s)
        ttc = read_ttc(prev[m], masses, ego_pose[max(t - 1, 0)], ego_pose[t], v, path, lw)
        prev[m] = masses
        return {**common, "method": m, "thw": thw, "ttc": ttc, **extra}

    for t in range(T):
        common = {**base, **_frame_common(arrays, t, ttc_true)}
        if include_ego:
            rows.append(risk_row(EGO, maps[t, 0], t, common, left_out=0, step_ms=0.0))
        others.own_maps(t)
        # each registration of this frame once, for every method using it
        shared: dict = {"registered_results": pre[t]} if t in pre else {}
        for m in methods:
            step = twins[m].update(float(arrays["time"][t]), maps[t], rel[t], shared)
            others.twin(t, m, step)
            left_out, ms = int(N - step.used.sum()), 1000.0 * step.seconds
            rows.append(risk_row(m, step.masses, t, common, left_out=left_out, step_ms=ms))
    import pandas as pd

    f = pd.DataFrame(rows)
    f["critical"] = f["thw_true"] < s.critical_thw
    f["flagged"] = f["thw"] < s.warn_thw
    f["flagged_ttc"] = f["ttc"] < s.predict.warn_s
    return SequenceTables(f, others.table())


_WORKER: dict[str, Any] = {}  # the pass of :func:`evaluate_sequences_tables`' worker processes


def _sequence_worker_init(run: TwinPass, threads: int) -> None:
    from traffictwin.threads import pin_threads

    if threads:
        pin_threads(threads)
    _WORKER["run"] = run


def _sequence_task(task: tuple[int, dict[str, np.ndarray], Any, bool, bool]) -> tuple[int, Any]:
    j, arrays, registered, include_ego, vehicles = task
    return j, evaluate_sequence_tables(arrays, _WORKER["run"], registered, include_ego, vehicles)


def evaluate_sequences_tables(
    sequences: list[dict[str, np.ndarray]],
    run: TwinPass,
    registered: list[dict[int, list[Any]] | None],
    include_ego: bool = True,
    vehicles: bool = False,
) -> list[SequenceTables]:
    """:func:`evaluate_sequence_tables` of every sequence (``registered[j]``: sequence ``j``'s
    classical registrations, or None), in ``run.workers`` processes when there are several.

    The sequences are independent, so the tables are the same for any number of workers: each
    worker runs torch on this process's intra-op thread count (:mod:`traffictwin.threads`: the
    networks' float sums follow it). Only ``step_ms``, a wall time, differs. The workers are
    spawned (a fork of this process could inherit a lock held by one of its threads)."""
    import sys

    from traffictwin.processes import map_indexed
    from traffictwin.threads import passive_omp_wait

    n = len(sequences)
    if len(registered) != n:
        raise ValueError(
            f"evaluate_sequences_tables: {len(registered)} registrations for {n} sequences"
        )
    if run.workers <= 1 or n <= 1:
        return [
            evaluate_sequence_tables(a, run, r, include_ego, vehicles)
            for a, r in zip(sequences, registered)
        ]
    torch = sys.modules.get("torch")  # not imported: no network in this pass
    threads = torch.get_num_threads() if torch is not None else 0
    tasks = (
        (j, a, r, include_ego, vehicles) for j, (a, r) in enumerate(zip(sequences, registered))
    )
    # spawned workers inherit this environment: their torch threads share the cores, and
    # spinning OpenMP threads starve the other worker (a user's own policy is kept)
    passive_omp_wait()
    return map_indexed(
        _sequence_task,
        tasks,
        n,
        run.workers,
        method="spawn",
        initializer=_sequence_worker_init,
        initargs=(run, threads),
    )


def predictive_frame(frame: pd.DataFrame) -> pd.DataFrame:
    """``frame`` with, for every method ``m``, rows ``m + TTC`` (``"+ttc"``): the same frames with
    ``flagged`` = the predictive warning (``flagged_ttc``), so warnings of both measures on the
    same maps are compared by :func:`warning_metrics` (baseline ``m``)."""
    import pandas as pd

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
    2, ...]}``. All in one :func:`~traffictwin.fusion.registration_batches.register_many` call (one pool of
    ``workers`` processes); the results do not depend on ``workers``."""
    from traffictwin.fusion.registration_batches import register_many

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
