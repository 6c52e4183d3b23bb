"""What the twin's figures show, computed by evaluate_twin (its outputs ``twin_timeline.csv`` and
``data/figure_inputs/twin_map.npz``): the timeline of a typical occluded sequence and the twin at
its critical onset (:mod:`traffictwin.twin.figures` draws them)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np
import pandas as pd

from traffictwin.evidential.warp import warp_masses
from traffictwin.grid import GridSpec
from traffictwin.twin.evaluation import EGO, TwinEvalSettings, noisy_relative_poses, scalar
from traffictwin.twin.fuse import TwinOptions, build_twin
from traffictwin.twin.summary import lead_times

THW_CAP = 5.0  # s: THW above this (or inf) is drawn at the cap


def pick_timeline_sequence(
    table: pd.DataFrame,
    configuration: str,
    method: str,
    fps: float,
    sequence: int | None = None,
    horizon_s: float = 0.0,
) -> int:
    """``sequence`` if given (must exist), else a typical occluded sequence: the one whose lead time
    of ``method`` over the ego at ``configuration`` (warnings from ``horizon_s`` s before the onset)
    is closest to the median lead (ties: the lowest index)."""
    f = table[table["configuration"] == configuration]
    if sequence is not None:
        if sequence not in set(f["sequence"]):
            raise ValueError(f"twin.figure.sequence: sequence {sequence} is not in data/twin")
        return int(sequence)
    lt = lead_times(f, method, fps, horizon_s)
    occ = lt[lt["kind"] == "occluded"] if len(lt) else lt
    if len(occ) == 0:
        return int(f["sequence"].min())
    off = (occ["lead_s"] - float(occ["lead_s"].median())).abs().round(9)
    return int(occ.assign(off=off).sort_values(["off", "sequence"])["sequence"].iloc[0])


def timeline_table(
    table: pd.DataFrame, configuration: str, method: str, sequence: int
) -> pd.DataFrame:
    """Long table (time s, series, thw s capped at :data:`THW_CAP`) of one sequence: truth, ego,
    twin, and the twin's time to conflict (series ``... TTC``, column ``thw``) where the table has it."""
    f = table[(table["configuration"] == configuration) & (table["sequence"] == sequence)]
    ego, tw = f[f["method"] == EGO], f[f["method"] == method]
    series = {"truth": (ego, "thw_true"), "ego map": (ego, "thw"), f"twin ({method})": (tw, "thw")}
    if "ttc" in tw:  # the predictive measure read from the same twin (time to conflict, s)
        series[f"twin ({method}) TTC"] = (tw, "ttc")
    parts = [
        pd.DataFrame({"time": d["time"], "series": k, "thw": d[c]}) for k, (d, c) in series.items()
    ]
    out = pd.concat(parts, ignore_index=True)
    out["thw"] = np.minimum(out["thw"].to_numpy(float), THW_CAP)
    return out


@dataclass(frozen=True)
class TwinSnapshot:
    """What :func:`twin_map_figure` draws: the ``frame``, every vehicle's noisy and true pose in
    the ego's frame (``rel``, ``true_rel``: N, 3: x m, y m, yaw rad), the twin's ``masses``
    (2, H, W), the pose it ``used`` for each vehicle (``poses`` N, 3; ``used`` N bool) and each
    vehicle's map where the twin put it (``contributions`` N, 2, H, W)."""

    frame: int
    rel: np.ndarray
    true_rel: np.ndarray
    masses: np.ndarray
    poses: np.ndarray
    used: np.ndarray
    contributions: np.ndarray

    def arrays(self) -> dict[str, np.ndarray]:
        """The fields as arrays (``TwinSnapshot.from_arrays`` reads them back, also from an
        ``.npz``, which keeps the frame as a 1-element array)."""
        return {k: np.asarray(v) for k, v in asdict(self).items()}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> TwinSnapshot:
        return cls(
            **{f.name: arrays[f.name] for f in fields(cls)}
            | {"frame": int(np.ravel(arrays["frame"])[0])}
        )


def twin_snapshot(
    arrays: dict[str, np.ndarray],
    grid: GridSpec,
    noise: tuple[float, float],
    method: str,
    models: dict[str, Any] | None,
    s: TwinEvalSettings,
    registration: Any = None,
) -> TwinSnapshot:
    """The twin of ``method`` at the critical onset of one sequence at pose noise ``(r m, alpha
    deg)``, with each vehicle's map warped where the twin put it."""
    t = max(0, scalar(arrays["onset_frame"]))
    maps = arrays["maps"][t]
    rel = noisy_relative_poses(arrays["poses"], arrays["noise_z"], *noise)[t]
    options = TwinOptions(method, strategy=s.strategy, models=models, registration=registration)
    step = build_twin(maps, rel, grid, options)
    true_rel = noisy_relative_poses(arrays["poses"], np.zeros_like(arrays["noise_z"]), 0.0, 0.0)[t]
    contributions = np.stack(
        [maps[0]] + [warp_masses(maps[k], step.poses[k], grid) for k in range(1, len(maps))]
    )
    return TwinSnapshot(t, rel, true_rel, step.masses, step.poses, step.used, contributions)
