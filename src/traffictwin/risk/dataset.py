"""Risk dataset generation: driving sequence -> stereo frames + risk labels (one shard per sequence).

Shard ``i`` is sequence ``i`` (:func:`traffictwin.sim.driving.generate_sequence`), so it depends
only on ``(seed, i)`` and shards can be generated in parallel; its split is assigned per
sequence (= scenario) by :func:`assign_splits`, never per frame.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from traffictwin.grid import GridSpec
from traffictwin.risk.metric import (
    REGIONS,
    RiskCalculator,
    RiskConfig,
    risk_threshold,
)
from traffictwin.risk.stereo_shards import SPLITS
from traffictwin.sim.camera import GroundTexture, StereoCamera
from traffictwin.sim.driving import DrivingConfig, generate_sequence

if TYPE_CHECKING:  # the tables' library loads where a table is built (risk_data is read without it)
    import pandas as pd

#: training labels (``risk_data.label``): THW in a region (metric.REGIONS), or TTC/WTTC in the corridor
LABELS = ("thw_corridor", "thw_paper", "thw_fov", "ttc", "wttc")
#: the region column suffix of each region (frames.csv ``thw_<suffix>``, ``risk_thw_<suffix>``)
REGION_COLUMN = {"corridor": "corridor", "paper": "paper", "camera_fov": "fov"}
#: frames.csv: these columns first, then the per-frame values of :func:`make_shard` in its order
_LEAD = ("frame_id", "shard", "idx", "scenario", "split")


@dataclass(frozen=True)
class RiskDataSpec:
    """Everything a shard needs: driving config, camera, grid, risk config (region set per metric),
    the critical THW (s: a frame is ``critical`` below it; the primary
    ``evaluation.risk.thresholds_s``), which metric is the training label, and the ground-texture
    resolution (m/px)."""

    driving: DrivingConfig
    camera: StereoCamera
    grid: GridSpec
    risk: RiskConfig
    critical_thw_s: float
    label: str = "thw_corridor"
    ground_res: float = 0.1

    def __post_init__(self) -> None:
        if self.label not in LABELS:
            raise ValueError(f"risk label must be one of {LABELS}, got {self.label!r}")


def assign_splits(
    n: int,
    seed: int,
    fractions: tuple[float, float, float] = (0.7, 0.1, 0.2),
    strata: Sequence[str] | None = None,
) -> list[str]:
    """Split name per sequence (train/val/test) by a seeded permutation, stratified by ``strata``
    (e.g. the situation of each sequence; ``None`` = one stratum): every stratum is split in the
    given fractions rounded down, the leftover sequences going to the split furthest below its
    share overall; each split gets at least one sequence when ``n >= 3``."""
    if n < 1:
        raise ValueError(f"need at least one sequence, got {n}")
    if abs(sum(fractions) - 1.0) > 1e-6 or min(fractions) < 0:
        raise ValueError(f"split fractions must be >= 0 and sum to 1, got {fractions}")
    if strata is not None and len(strata) != n:
        raise ValueError(f"need one stratum per sequence: {len(strata)} strata for {n} sequences")
    frac = np.asarray(fractions, float)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 4004]))
    keys = (
        np.zeros(n, int)
        if strata is None
        else np.unique(np.asarray(strata), return_inverse=True)[1]
    )
    perm = rng.permutation(n)
    out = np.empty(n, dtype=object)
    counts = np.zeros(3, int)  # assigned per split so far
    for key in np.unique(keys):
        members = perm[keys[perm] == key]  # this stratum in permuted order
        m = len(members)
        take = np.floor(frac * m).astype(int)
        for _ in range(m - int(take.sum())):  # leftovers: to the split furthest below its share
            deficit = frac * (counts.sum() + m) - (counts + take)
            take[int(np.argmax(deficit))] += 1
        names = np.repeat(np.array(SPLITS, dtype=object), take)
        out[members] = names
        counts += take
    if n >= 3:  # every split non-empty: move one sequence from the largest split
        for j, name in enumerate(SPLITS):
            if counts[j] == 0:
                big = int(np.argmax(counts))
                i = int(np.flatnonzero(out == SPLITS[big])[-1])
                out[i] = name
                counts[big] -= 1
                counts[j] += 1
    return [str(x) for x in out]


def make_shard(
    seed: int, index: int, spec: RiskDataSpec
) -> tuple[dict[str, np.ndarray], list[dict]]:
    """Render sequence ``index``: arrays ``left``, ``right`` (N, H, W, 3) uint8 BGR, ``disp_gt``
    (N, H, W) float32 px, ``speed`` (N,) m/s, ``risk`` (N,) float32; plus one row per frame with
    THW (s) and risk of every region (``thw_<r>``, ``risk_thw_<r>``, r = corridor, paper, fov),
    TTC/WTTC (s) and their risks in the corridor, and the training label's ``thw``/``risk``/
    ``critical``."""
    seq = generate_sequence(seed, index, spec.driving)
    cam = spec.camera
    ground = GroundTexture.from_world(
        seq.world, res=spec.ground_res, seed=int(seq.world.seed) % 100003
    )
    calcs = {r: RiskCalculator(spec.grid, replace(spec.risk, region=r)) for r in REGIONS}
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), int(index), 5005]))
    left, right, disp, rows = [], [], [], []
    for k, fr in enumerate(seq.frames):
        out = cam.render_pair(
            fr.pose, fr.boxes, ground, fr.pose_right, fr.boxes_right, fr.right_cy_offset, rng
        )
        left.append(out["left"])
        right.append(out["right"])
        disp.append(out["disp_gt"])
        res = {
            REGION_COLUMN[r]: calc(fr.pose, fr.speed, fr.boxes, fr.path, fr.lane_width)
            for r, calc in calcs.items()
        }
        rc = res["corridor"]
        values = {f"thw_{c}": r.risk_thw for c, r in res.items()}
        values.update(ttc=rc.risk_ttc, wttc=rc.risk_wttc)
        region = spec.label[4:] if spec.label.startswith("thw_") else "corridor"
        thw = res[region].thw
        rows.append(
            dict(
                idx=k,
                scenario=int(index),
                situation=seq.situation,
                template=seq.world.template,
                t=round(fr.t, 4),
                speed=fr.speed,
                x=fr.pose[0],
                y=fr.pose[1],
                yaw=fr.pose[2],
                thw=thw,
                distance=res[region].distance,
                **{f"thw_{c}": r.thw for c, r in res.items()},
                ttc=rc.ttc,
                wttc=rc.wttc,
                risk=values[spec.label],
                **{f"risk_thw_{c}": r.risk_thw for c, r in res.items()},
                risk_ttc=rc.risk_ttc,
                risk_wttc=rc.risk_wttc,
                critical=bool(thw < spec.critical_thw_s),
                fault=fr.fault,
                vertical_px=fr.right_cy_offset,
            )
        )
    arrays = {
        "left": np.stack(left),
        "right": np.stack(right),
        "disp_gt": np.stack(disp).astype(np.float32),
        "speed": np.array([r["speed"] for r in rows], np.float32),
        "risk": np.array([r["risk"] for r in rows], np.float32),
    }
    return arrays, rows


def frame_table(rows_by_shard: Mapping[int, Sequence[dict]], splits: Sequence[str]) -> pd.DataFrame:
    """The frames table (frames.csv): every row of :func:`make_shard` of shards ``0..n-1`` in order,
    numbered by ``frame_id``, with its shard and the shard's split; lead columns first."""
    import pandas as pd

    table = []
    fid = 0
    for index in range(len(splits)):
        for r in rows_by_shard[index]:
            table.append({"frame_id": fid, "shard": index, "split": splits[index], **r})
            fid += 1
    df = pd.DataFrame(table)
    return df[list(_LEAD) + [c for c in df.columns if c not in _LEAD]]


def summarise_frames(df: pd.DataFrame, critical_thw_s: float) -> dict:
    """Frame counts, critical share (THW < ``critical_thw_s`` s) of the label and of every region,
    fault and situation shares, per split."""
    out: dict = {}
    thr = risk_threshold(critical_thw_s)
    for name, part in [("all", df)] + [(s, df[df.split == s]) for s in SPLITS]:
        if len(part) == 0:
            continue
        out[f"{name}/frames"] = int(len(part))
        out[f"{name}/sequences"] = int(part.scenario.nunique())
        out[f"{name}/critical_share"] = float(part.critical.mean())
        out[f"{name}/risk_mean"] = float(part.risk.mean())
        for region in REGION_COLUMN.values():
            col = f"risk_thw_{region}"
            if col in part.columns:
                out[f"{name}/critical_share_{region}"] = float((part[col] > thr).mean())
    out["all/speed_mean"] = float(df.speed.mean())
    out["all/speed_max"] = float(df.speed.max())
    out["all/standstill_share"] = float((df.speed < 0.5).mean())
    for f, c in Counter(df.fault).items():
        out[f"all/fault_share_{f}"] = float(c / len(df))
    for s, c in Counter(df.groupby("scenario").situation.first()).items():
        out[f"all/sequences_{s}"] = int(c)
    for m in ("risk_thw_corridor", "risk_thw_paper", "risk_thw_fov", "risk_ttc", "risk_wttc"):
        if m in df.columns:
            out[f"all/{m}_mean"] = float(df[m].mean())
            out[f"all/{m}_nonzero"] = float((df[m] > 0).mean())
    if "situation" in df.columns:
        for sit, part in df.groupby("situation"):
            out[f"situation/{sit}/critical_share"] = float(part.critical.mean())
    return out
