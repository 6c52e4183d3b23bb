"""Twin data: cooperative sequences -> every vehicle's evidential grid per frame + the ego's ground truth.

Sequence ``i`` (:func:`traffictwin.sim.cooperative.generate_cooperative_sequence`, deterministic
for ``(seed, i)``) is simulated at ``fps``; at every frame every vehicle scans the world (its own
box excluded) and the inverse sensor model turns the scan into a mass grid in its sensor frame —
the same lidar, ISM and grid as the fusion data, so the fusion models apply unchanged. Per
sequence one ``.npz`` with (T frames, N vehicles):

- ``maps (T, N, 2, H, W)`` float32 — m_F, m_O of each vehicle (sensor frame);
- ``poses (T, N, 3)`` exact world poses (x m, y m, yaw rad), ``speeds (T, N)`` m/s;
- ``noise_z (T, N, 3)`` standard-normal pose-noise draws of vehicle k at frame t (row 0 = ego:
  zeros), from ``(seed, sequence, k, t)``; a configuration scales them
  (:func:`traffictwin.evidential.noise.scale_noise`) and adds them to the vehicle's world pose;
- ``bias_z (N, 3)`` standard-normal draws of vehicle k's persistent (per-sequence, GNSS-like)
  pose bias (row 0 = ego: zeros), from ``(seed, sequence, k)``; the evaluation's ``bias`` noise
  model mixes them with ``noise_z`` (:func:`traffictwin.twin.noise.pose_noise_z`);
- ``path (T, K, 2)`` the ego's path ahead in its own frame (m), ``lane_width (T,)`` m;
- ``thw_true (T,)`` ego's time headway (s) on the simulator's boxes (corridor region, vehicles
  and pedestrians; :class:`traffictwin.risk.metric.RiskCalculator`), ``distance_true (T,)`` m;
- ``vehicle_path (T, N, K, 2)`` every vehicle's path ahead in its own frame (m; row 0 = ``path``),
  ``vehicle_lane_width (T, N)`` m, ``vehicle_thw_true (T, N)`` every vehicle's time headway (s)
  on the simulator's boxes, the same metric as the ego's (row 0 = ``thw_true``);
- ``ttc_true (T,)`` the ego's time to conflict (s, inf: none within the horizon) on the
  simulator's boxes with their true velocities (:mod:`traffictwin.twin.predict`);
- ``hazard_seen (T, N)`` bool — whether vehicle k's lidar returned from the hazard at frame t;
- ``time (T,)`` s; scalars ``sequence``, ``kind`` (index into :data:`KINDS`), ``hazard`` (index
  into :data:`HAZARDS`), ``template`` (index into the world templates), ``onset_frame``,
  ``hidden_at_onset``, ``hidden_window`` (the occluded sequence's hazard hidden from the ego
  over ``scenario.hidden_s`` before the onset and seen by another vehicle, noiseless scans),
  ``attempts``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from traffictwin.evidential.ism import IsmParams, inverse_sensor_model
from traffictwin.evidential.noise import standard_normal_draws
from traffictwin.grid import GridSpec
from traffictwin.risk.metric import RiskCalculator, RiskConfig, path_to_subject_frame
from traffictwin.sim.cooperative import (
    HAZARD_ID,
    HAZARDS,
    KINDS,
    CooperativeConfig,
    generate_cooperative_sequence,
)
from traffictwin.sim.lidar import LidarSpec, scan
from traffictwin.sim.traffic import SUBJECT_SIZE
from traffictwin.sim.world import TEMPLATES
from traffictwin.twin.predict import PredictSettings, box_points, time_to_conflict

__all__ = [
    "TwinDataParams",
    "twin_risk_config",
    "sequence_arrays",
    "write_sequence",
    "noise_draws",
    "bias_draws",
    "TEST_SPLIT",
    "VALIDATION_SPLIT",
]

TEST_SPLIT, VALIDATION_SPLIT = (
    "test",
    "validation",
)  # evaluated / only to choose the predictive rule
BIAS_DRAW = 1_000_000  # draw index of the persistent bias (frame draws use 0..T-1)


@dataclass(frozen=True)
class TwinDataParams:
    """Everything a sequence depends on besides ``(seed, index)``: the fusion data's grid, lidar
    and ISM; the cooperative scenario settings; the corridor margin (m) of the ego's risk label."""

    grid: GridSpec = GridSpec()
    lidar: LidarSpec = LidarSpec()
    ism: IsmParams = IsmParams()
    scenario: CooperativeConfig = field(kw_only=True)
    corridor_margin: float = 0.0
    predict: PredictSettings = field(kw_only=True)  # TTC settings (the stage passes twin.predict())


def twin_risk_config(corridor_margin: float = 0.0) -> RiskConfig:
    """The ego's risk metric: corridor region, the simulator's subject footprint, pedestrians count."""
    return RiskConfig(
        subject_length=SUBJECT_SIZE[0],
        subject_width=SUBJECT_SIZE[1],
        region="corridor",
        include_pedestrians=True,
        corridor_margin=corridor_margin,
    )


def noise_draws(seed: int, sequence: int, frames: int, vehicles: int) -> np.ndarray:
    """Standard-normal pose-noise draws ``(frames, vehicles, 3)`` of one sequence (ego row zero):
    vehicle k's draw at frame t depends only on ``(seed, sequence, k, t)``."""
    z = np.zeros((frames, vehicles, 3))
    for k in range(1, vehicles):
        pid = np.full(frames, int(sequence) * 100 + k, dtype=np.int64)
        z[:, k] = standard_normal_draws(seed, pid, np.arange(frames))
    return z


def bias_draws(seed: int, sequence: int, vehicles: int) -> np.ndarray:
    """Standard-normal persistent pose-bias draws ``(vehicles, 3)`` of one sequence (ego row zero):
    vehicle k's depends only on ``(seed, sequence, k)`` and differs from every frame draw."""
    z = np.zeros((vehicles, 3))
    if vehicles > 1:
        pid = int(sequence) * 100 + np.arange(1, vehicles, dtype=np.int64)
        z[1:] = standard_normal_draws(seed, pid, BIAS_DRAW)
    return z


def sequence_arrays(seed: int, index: int, p: TwinDataParams) -> dict[str, np.ndarray]:
    """Arrays of sequence ``index`` (see the module docstring)."""
    if index < 0:
        raise ValueError(f"sequence index must be >= 0, got {index}")
    seq = generate_cooperative_sequence(seed, index, p.scenario, p.lidar)
    T, N = len(seq.frames), len(seq.roles)
    g = p.grid
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), int(index), 5006]))
    calc = RiskCalculator(g, twin_risk_config(p.corridor_margin))
    maps = np.zeros((T, N, 2, g.rows, g.cols), np.float32)
    seen = np.zeros((T, N), bool)
    thw = np.zeros(T)
    ttc = np.zeros(T)
    dist = np.zeros(T)
    paths = np.zeros((T, len(seq.frames[0].path), 2))
    v_paths = np.zeros((T, N, len(seq.frames[0].path), 2))
    v_thw = np.zeros((T, N))
    for t, f in enumerate(seq.frames):
        for k in range(N):
            others = f.boxes.subset(f.boxes.ids != seq.vehicle_ids[k])
            s = scan(p.lidar, f.poses[k], others, rng)
            maps[t, k] = inverse_sensor_model(s, g, p.ism)
            seen[t, k] = bool(np.any(s.hit == int(np.flatnonzero(others.ids == HAZARD_ID)[0])))
        ego_others = f.boxes.subset(f.boxes.ids != seq.vehicle_ids[0])
        r = calc(f.poses[0], float(f.speeds[0]), ego_others, path=f.path, lane_width=f.lane_width)
        thw[t], dist[t] = r.thw, r.distance
        paths[t] = path_to_subject_frame(f.path, f.poses[0])
        v_thw[t, 0], v_paths[t, 0] = r.thw, paths[t]
        for k in range(1, N):
            others = f.boxes.subset(f.boxes.ids != seq.vehicle_ids[k])
            path_k, lw_k = f.vehicle_paths[k], float(f.vehicle_lane_widths[k])
            v_thw[t, k] = calc(
                f.poses[k], float(f.speeds[k]), others, path=path_k, lane_width=lw_k
            ).thw
            v_paths[t, k] = path_to_subject_frame(path_k, f.poses[k])
        xy, vel = box_points(ego_others.corners(), ego_others.velocity, f.poses[0])
        ttc[t] = time_to_conflict(
            xy,
            vel,
            paths[t],
            f.lane_width,
            float(f.speeds[0]),
            SUBJECT_SIZE[0],
            p.predict,
            p.corridor_margin,
        )
    return {
        "maps": maps,
        "poses": np.stack([f.poses for f in seq.frames]).astype(np.float64),
        "speeds": np.stack([f.speeds for f in seq.frames]).astype(np.float64),
        "noise_z": noise_draws(seed, index, T, N),
        "bias_z": bias_draws(seed, index, N),
        "path": paths,
        "lane_width": np.array([f.lane_width for f in seq.frames], dtype=np.float64),
        "thw_true": thw,
        "distance_true": dist,
        "vehicle_path": v_paths,
        "vehicle_lane_width": np.stack([f.vehicle_lane_widths for f in seq.frames]),
        "vehicle_thw_true": v_thw,
        "ttc_true": ttc,
        "hazard_seen": seen,
        "time": np.array([f.t for f in seq.frames], dtype=np.float64),
        "sequence": np.array(index, dtype=np.int64),
        "kind": np.array(KINDS.index(seq.kind), dtype=np.int64),
        "hazard": np.array(HAZARDS.index(seq.hazard), dtype=np.int64),
        "template": np.array(TEMPLATES.index(seq.world.template), dtype=np.int64),
        "onset_frame": np.array(seq.onset_frame, dtype=np.int64),
        "hidden_at_onset": np.array(seq.hidden_at_onset, dtype=bool),
        "hidden_window": np.array(seq.hidden_window, dtype=bool),
        "attempts": np.array(seq.attempts, dtype=np.int64),
    }


# arrays where +inf is a value ("nothing ahead" / speed 0); every other float array is finite
INF_ARRAYS = ("thw_true", "distance_true", "ttc_true", "vehicle_thw_true")


def write_sequence(
    seed: int, index: int, p: TwinDataParams, path: str, compresslevel: int = 1
) -> tuple[int, str, int]:
    """Generate sequence ``index`` and write it to ``path`` (atomic, deterministic bytes).

    Returns ``(index, sha256, frame count)``; a top-level function so worker processes can run it."""
    import cv2

    from traffictwin.io.shards import write_npz_deterministic

    cv2.setNumThreads(1)
    arrays = sequence_arrays(seed, index, p)
    digest = write_npz_deterministic(
        path, arrays, compresslevel=compresslevel, allow_inf=INF_ARRAYS
    )
    return index, digest, len(arrays["time"])
