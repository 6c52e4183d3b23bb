"""Fusion training data: scenarios -> two evidential maps per encounter -> two input-label pairs.

For scenario ``j`` (template ``templates[j % len(templates)]``, so templates are balanced) a
world and traffic are drawn from ``SeedSequence([seed, j])``. At each of the scenario's
encounter times both subject vehicles scan the world (each sees the other one, not itself),
the inverse sensor model turns each scan into a mass grid in that vehicle's sensor frame, and
(paper III-B) the fusion is done from both perspectives with the exact poses:

* pair ``(map1 = A, map2 = B)``: label = ``dempster(A, warp(B, pose of B in A's frame))``
* pair ``(map1 = B, map2 = A)``: the mirror.

Shard ``i`` holds scenarios ``[i * S, (i + 1) * S)`` and depends only on ``(seed, i)`` and the
parameters; its split (train/val/test) comes from :func:`shard_splits` (by scenario, never by
pair). ``pair_id = scenario * 1000 + 2 * encounter + perspective`` identifies a pair.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from traffictwin.evidential.dempster import dempster
from traffictwin.evidential.ism import IsmParams, inverse_sensor_model
from traffictwin.evidential.warp import warp_masses
from traffictwin.geometry import relative_pose
from traffictwin.grid import GridSpec
from traffictwin.sim.lidar import LidarSpec, scan
from traffictwin.sim.scene import Boxes
from traffictwin.sim.traffic import sample_scenario
from traffictwin.sim.world import TEMPLATES, build_world

SPLITS = ("train", "val", "test")


@dataclass(frozen=True)
class FusionDataParams:
    """Everything one shard depends on besides ``(seed, index)``.

    ``scenarios_per_shard``; ``encounters_per_scenario`` (each gives 2 pairs) spaced
    ``encounter_spacing`` s around ``t_meet`` (s); ``meet_distance`` (m) between the subjects;
    ``density``: traffic density overrides (see :data:`traffictwin.sim.traffic.DEFAULT_DENSITY`).
    """

    grid: GridSpec = GridSpec()
    lidar: LidarSpec = LidarSpec()
    ism: IsmParams = IsmParams()
    scenarios_per_shard: int = 4
    encounters_per_scenario: int = 4
    encounter_spacing: float = 0.5
    t_meet: float = 10.0
    meet_distance: tuple[float, float] = (6.0, 40.0)
    density: dict = field(default_factory=dict)
    templates: tuple[str, ...] = TEMPLATES

    def __post_init__(self) -> None:
        bad = [t for t in self.templates if t not in TEMPLATES]
        if bad or not self.templates:
            raise ValueError(
                f"templates: unknown road template(s) {bad or '(empty list)'}; expected names from {list(TEMPLATES)}"
            )
        if self.scenarios_per_shard < 1:
            raise ValueError(f"scenarios_per_shard must be >= 1, got {self.scenarios_per_shard}")
        if self.encounters_per_scenario < 1:
            raise ValueError(
                f"encounters_per_scenario must be >= 1, got {self.encounters_per_scenario}"
            )
        if not 0 <= self.meet_distance[0] < self.meet_distance[1]:
            raise ValueError(
                f"meet_distance must be (min, max) m with 0 <= min < max, got {self.meet_distance}"
            )

    @property
    def pairs_per_shard(self) -> int:
        return 2 * self.encounters_per_scenario * self.scenarios_per_shard


def template_of(scenario: int, templates: tuple[str, ...] = TEMPLATES) -> str:
    """Road template of scenario ``scenario`` (round robin over ``templates``)."""
    return templates[int(scenario) % len(templates)]


def shard_splits(
    n_shards: int, seed: int, fractions: tuple[float, float, float] = (0.8, 0.1, 0.1)
) -> list[str]:
    """Split name of every shard: a seeded permutation, ``round(f * n)`` val and test shards
    (at least one each when ``n_shards >= 3``), the rest train."""
    if n_shards < 1:
        raise ValueError(f"number of shards must be >= 1, got {n_shards}")
    if any(f < 0 for f in fractions) or abs(sum(fractions) - 1.0) > 1e-6:
        raise ValueError(f"split fractions must be >= 0 and sum to 1, got {fractions}")
    n_val = int(round(fractions[1] * n_shards))
    n_test = int(round(fractions[2] * n_shards))
    if n_shards >= 3:
        n_val, n_test = (
            max(n_val, 1 if fractions[1] > 0 else 0),
            max(n_test, 1 if fractions[2] > 0 else 0),
        )
    perm = np.random.default_rng(np.random.SeedSequence([int(seed), 7004])).permutation(n_shards)
    out = ["train"] * n_shards
    for i in perm[:n_val]:
        out[int(i)] = "val"
    for i in perm[n_val : n_val + n_test]:
        out[int(i)] = "test"
    return out


def scenario_maps(seed: int, scenario: int, p: FusionDataParams) -> dict[str, np.ndarray]:
    """Both subjects' mass grids and exact world poses at every encounter of one scenario.

    Returns ``maps (E, 2, 2, H, W)`` float32 (encounter, subject, m_F/m_O, H, W), ``poses (E, 2, 3)``,
    ``times (E,)`` (s).
    """
    ss = np.random.SeedSequence([int(seed), int(scenario)])
    world_seed, traffic_seed, lidar_seed = (int(x) for x in ss.generate_state(3, dtype=np.uint32))
    world = build_world(template_of(scenario, p.templates), world_seed)
    sc = sample_scenario(
        world,
        traffic_seed,
        t_meet=p.t_meet,
        n_encounters=p.encounters_per_scenario,
        encounter_spacing=p.encounter_spacing,
        meet_distance=tuple(p.meet_distance),
        **p.density,
    )
    rng = np.random.default_rng(lidar_seed)
    E = p.encounters_per_scenario
    maps = np.zeros((E, 2, 2, p.grid.rows, p.grid.cols), np.float32)
    poses = np.zeros((E, 2, 3))
    for e, t in enumerate(sc.encounter_times):
        agents = sc.agents_at(float(t))
        for k, sid in enumerate(sc.subject_ids):
            boxes = Boxes.concat([world.static, agents.subset(agents.ids != sid)])
            pose = sc.subject_pose(k, float(t))
            maps[e, k] = inverse_sensor_model(scan(p.lidar, pose, boxes, rng), p.grid, p.ism)
            poses[e, k] = pose
    return {"maps": maps, "poses": poses, "times": np.asarray(sc.encounter_times, dtype=np.float64)}


def make_pairs(maps: np.ndarray, poses: np.ndarray, grid: GridSpec) -> dict[str, np.ndarray]:
    """Input-label pairs from ``maps (E, 2, 2, H, W)`` and ``poses (E, 2, 3)``: for every
    encounter, perspective 0 = (subject 0, subject 1) and perspective 1 = the mirror."""
    out: dict[str, list] = {"map1": [], "map2": [], "label": [], "pose1": [], "pose2": []}
    for e in range(len(maps)):
        for a, b in ((0, 1), (1, 0)):
            warped, _ = prealign(maps[e, b], poses[e, a], poses[e, b], grid)
            out["map1"].append(maps[e, a])
            out["map2"].append(maps[e, b])
            out["label"].append(dempster(maps[e, a], warped))
            out["pose1"].append(poses[e, a])
            out["pose2"].append(poses[e, b])
    return {
        "map1": np.stack(out["map1"]).astype(np.float32),
        "map2": np.stack(out["map2"]).astype(np.float32),
        "label": np.stack(out["label"]).astype(np.float32),
        "pose1": np.stack(out["pose1"]).astype(np.float64),
        "pose2": np.stack(out["pose2"]).astype(np.float64),
    }


def generate_shard(seed: int, index: int, p: FusionDataParams) -> dict[str, np.ndarray]:
    """Arrays of shard ``index`` (see the module docstring and the ``data/fusion`` interface)."""
    if index < 0:
        raise ValueError(f"shard index must be >= 0, got {index}")
    parts = []
    for j in range(index * p.scenarios_per_shard, (index + 1) * p.scenarios_per_shard):
        sm = scenario_maps(seed, j, p)
        pairs = make_pairs(sm["maps"], sm["poses"], p.grid)
        E = len(sm["maps"])
        enc = np.repeat(np.arange(E), 2)
        persp = np.tile([0, 1], E)
        pairs["scenario"] = np.full(2 * E, j, dtype=np.int64)
        pairs["pair_id"] = (j * 1000 + 2 * enc + persp).astype(np.int64)
        pairs["template"] = np.full(
            2 * E, TEMPLATES.index(template_of(j, p.templates)), dtype=np.int64
        )
        pairs["time"] = np.repeat(sm["times"], 2)
        parts.append(pairs)
    return {k: np.concatenate([q[k] for q in parts]) for k in parts[0]}


def write_shard(
    seed: int, index: int, p: FusionDataParams, path: str, compresslevel: int = 1
) -> tuple[int, str, int]:
    """Generate shard ``index`` and write it to ``path`` (atomic, deterministic bytes).

    Returns ``(index, sha256, pair count)``; a top-level function so worker processes can run it.
    """
    import cv2

    from traffictwin.io.shards import write_npz_deterministic

    cv2.setNumThreads(1)
    arrays = generate_shard(seed, index, p)
    digest = write_npz_deterministic(path, arrays, compresslevel=compresslevel)
    return index, digest, len(arrays["map1"])


# ---------------------------------------------------------------------------------------------
# prealignment (paper III-C)
def prealign(
    map2: np.ndarray,
    pose1: np.ndarray,
    pose2: np.ndarray,
    grid: GridSpec,
    noise: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Map 2 warped into map 1's frame: *the* prealignment of the project.

    ``map2 (2, H, W)`` in its sensor frame; ``pose1``, ``pose2``: world poses (x m, y m, yaw rad)
    of the two sensors; ``noise`` (dx m, dy m, dyaw rad), if given, is added to ``pose2`` first
    (:func:`~traffictwin.evidential.noise.apply_pose_noise`). Returns ``(warped (2, H, W)
    float32, rel_pose (3,))`` with ``rel_pose`` the (noisy) pose of map 2's sensor in map 1's
    frame. Used for the labels (exact poses), the prealigned data and Fig. 4 (noisy poses) and
    by ``traffictwin fuse``.
    """
    from traffictwin.evidential.noise import apply_pose_noise

    if noise is not None:
        pose2 = apply_pose_noise(pose2, noise)
    rel = relative_pose(pose1, pose2)
    return warp_masses(map2, rel, grid), rel


def prealign_arrays(
    shard: dict[str, np.ndarray], noise: np.ndarray, grid: GridSpec, draw: np.ndarray | None = None
) -> dict[str, np.ndarray]:
    """Prealigned arrays for the pairs of a fusion ``shard`` with pose noise ``noise (N, 3)``
    (dx m, dy m, dyaw rad, added to map 2's world pose): map 2 warped into map 1's frame by the
    *noisy* relative pose. ``noise`` rows may repeat pairs (several draws): ``draw (N,)`` then
    says which draw, and the pairs are taken as ``shard[...][pair_index]`` where
    ``pair_index = np.repeat(arange(n_pairs), N // n_pairs)``.
    """
    n = len(shard["map1"])
    reps = len(noise) // max(n, 1)
    if len(noise) != reps * n or reps < 1:
        raise ValueError(
            f"prealign: noise has {len(noise)} rows, expected a multiple of the {n} pairs"
        )
    take = np.repeat(np.arange(n), reps)
    pose1, pose2 = shard["pose1"][take], shard["pose2"][take]
    rel_true = np.stack([relative_pose(a, b) for a, b in zip(pose1, pose2)])
    done = [
        prealign(shard["map2"][i], pose1[k], pose2[k], grid, noise[k]) for k, i in enumerate(take)
    ]
    warped = np.stack([w for w, _ in done])
    rel_noisy = np.stack([r for _, r in done])
    inputs = np.concatenate([shard["map1"][take], warped], axis=1).astype(np.float32)
    return {
        "inputs": inputs,
        "label": shard["label"][take].astype(np.float32),
        "noise": np.asarray(noise, dtype=np.float64),
        "rel_pose_true": rel_true,
        "rel_pose_noisy": rel_noisy,
        "scenario": shard["scenario"][take],
        "pair_id": shard["pair_id"][take],
        "draw": (
            np.zeros(len(take), np.int64) if draw is None else np.asarray(draw, dtype=np.int64)
        ),
    }


@dataclass(frozen=True)
class ShardNoise:
    """The pose noise a prealigned shard draws: ``draws`` draws per pair from ``seed`` (draw ``d``
    of pair ``pid``: :func:`~traffictwin.evidential.noise.standard_normal_draws` with ``(seed,
    pid, d)``), scaled by ``(r m, alpha_deg)`` or, with ``mixture = (sigmas (K, 3), kind)``, by
    :func:`~traffictwin.evidential.noise.noise_scales` (``r`` and ``alpha_deg`` then ignored)."""

    seed: int
    draws: int
    r: float = 0.0
    alpha_deg: float = 0.0
    mixture: tuple[np.ndarray, str] | None = None


def prealign_shard(
    src: str, dst: str, noise: ShardNoise, grid: GridSpec, compresslevel: int = 1
) -> tuple[str, int]:
    """Read fusion shard ``src`` (already verified by the caller), prealign it with ``noise``'s
    draws (:class:`ShardNoise`), write ``dst``; returns ``(sha256, count)``. With a mixture, the
    shard also stores each row's ``noise_sigma (N, 3)``."""
    import cv2

    from traffictwin.evidential.noise import noise_scales, scale_noise, standard_normal_draws
    from traffictwin.io.shards import read_npz, write_npz_deterministic

    cv2.setNumThreads(1)
    shard = read_npz(src)
    if shard["map1"].shape[-2:] != grid.shape:
        raise ValueError(
            f"{src}: maps are {shard['map1'].shape[-2:]}, the grid parameter says {grid.shape}"
        )
    pid = np.repeat(shard["pair_id"], noise.draws)
    draw = np.tile(np.arange(noise.draws), len(shard["pair_id"]))
    z = standard_normal_draws(noise.seed, pid, draw)
    if noise.mixture is None:
        arrays = prealign_arrays(shard, scale_noise(z, noise.r, noise.alpha_deg), grid, draw)
    else:
        sig = noise_scales(noise.seed, pid, draw, noise.mixture[0], noise.mixture[1])
        arrays = prealign_arrays(shard, z * sig, grid, draw)
        arrays["noise_sigma"] = sig
    digest = write_npz_deterministic(dst, arrays, compresslevel=compresslevel)
    return digest, len(arrays["inputs"])


def evenly_spaced(n: int, k: int | None) -> np.ndarray:
    """``k`` indices spread evenly over ``range(n)`` (all when ``k`` is None, <= 0 or >= n)."""
    if k is None or k <= 0 or k >= n:
        return np.arange(n)
    return np.unique(np.round(np.linspace(0, n - 1, k)).astype(np.int64))
