"""Stage generate_risk: driving sequences -> stereo frames + risk labels -> data/risk (kind "risk").

One shard per driving sequence (= scenario), rendered in parallel worker processes
(``risk_data.workers``); splits 70/10/20 by sequence. Also writes
reports/metrics/risk_data.json and reports/figures/risk_metric_example.png.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import pandas as pd

from pipelines._common import (
    ROOT,
    WORKER_STATE,
    map_shards,
    params,
    run_stage,
    setup_logging,
    stage_timer,
)
from traffictwin.config import get
from traffictwin.grid import GridSpec
from traffictwin.io.atomic import write_json_atomic
from traffictwin.io.shards import DatasetWriter, shard_name, write_npz_deterministic
from traffictwin.risk.dataset import LABELS, RiskDataSpec, assign_splits, make_shard
from traffictwin.risk.metric import RiskConfig
from traffictwin.sim.camera import StereoCamera
from traffictwin.sim.driving import DrivingConfig

OUT = ROOT / "data" / "risk"


def data_seed(cfg) -> int:
    """Dataset seed from the global seed and ``risk_data.seed``."""
    return int(get(cfg, "seed", int, min=0)) + 1_000_003 * int(
        get(cfg, "risk_data.seed", int, min=0)
    )


def spec_from_params(cfg) -> RiskDataSpec:
    """Build the generation spec from params.yaml (checked access)."""
    k = "risk_data"
    cam = StereoCamera(
        width=get(cfg, f"{k}.camera.width", int, min=16),
        height=get(cfg, f"{k}.camera.height", int, min=16),
        hfov_deg=get(cfg, f"{k}.camera.hfov_deg", float, min=5, max=150),
        baseline=get(cfg, f"{k}.camera.baseline", float, min=0.01),
        mount_x=get(cfg, f"{k}.camera.mount_x", float),
        mount_height=get(cfg, f"{k}.camera.mount_height", float, min=0.1),
        max_range=get(cfg, f"{k}.camera.max_range", float, min=1),
        noise_std=get(cfg, f"{k}.camera.noise_std", float, min=0),
    )
    vpx = get(cfg, f"{k}.faults.vertical_px", list)
    drv = DrivingConfig(
        fps=get(cfg, f"{k}.fps", float, min=0.1),
        frames=get(cfg, f"{k}.frames_per_sequence", int, min=1),
        warmup=get(cfg, f"{k}.warmup", float, min=0),
        max_speed=get(cfg, f"{k}.max_speed", float, min=1),
        critical_share=get(cfg, f"{k}.critical_share", float, min=0, max=1),
        templates=tuple(get(cfg, f"{k}.templates", list)),
        fault_delay=get(cfg, f"{k}.faults.delay_share", float, min=0, max=1),
        fault_vertical=get(cfg, f"{k}.faults.vertical_share", float, min=0, max=1),
        delay=get(cfg, f"{k}.faults.delay_s", float, min=0),
        vertical_px=(float(vpx[0]), float(vpx[1])),
    )
    risk = RiskConfig(
        subject_length=get(cfg, f"{k}.metric.subject_length", float, min=0.5),
        subject_width=get(cfg, f"{k}.metric.subject_width", float, min=0.3),
        hfov_deg=cam.hfov_deg,
        mount_x=cam.mount_x,
        fill=get(cfg, f"{k}.metric.fill", str, choices=("border", "filled")),
        include_pedestrians=get(cfg, f"{k}.metric.include_pedestrians", bool),
    )
    grid = GridSpec(
        get(cfg, "grid.rows", int, min=8),
        get(cfg, "grid.cols", int, min=8),
        get(cfg, "grid.cell", float, min=0.01),
    )
    return RiskDataSpec(
        drv,
        cam,
        grid,
        risk,
        label=get(cfg, f"{k}.label", str, choices=LABELS),
        ground_res=get(cfg, f"{k}.ground_res", float, min=0.02, max=1.0),
    )


def _work(index: int) -> tuple[int, str, int, list[dict]]:
    arrays, rows = make_shard(WORKER_STATE["seed"], index, WORKER_STATE["spec"])
    digest = write_npz_deterministic(WORKER_STATE["root"] / shard_name(index), arrays)
    return index, digest, len(rows), rows


def generate(cfg, out: Path = OUT) -> dict:
    """Generate the dataset into ``out``; returns the summary metrics."""
    log = setup_logging()
    spec = spec_from_params(cfg)
    seed = data_seed(cfg)
    n = get(cfg, "risk_data.sequences", int, min=1)
    fr = get(cfg, "risk_data.splits", list)
    if len(fr) != 3:
        raise ValueError(
            f"params.yaml: 'risk_data.splits' must be 3 fractions (train, val, test), got {fr}"
        )
    splits = assign_splits(n, seed, tuple(float(x) for x in fr))
    workers = get(cfg, "risk_data.workers", int, min=1)
    recorded = {k: v for k, v in dict(get(cfg, "risk_data", dict)).items() if k != "workers"}
    recorded["grid"] = dict(get(cfg, "grid", dict))
    writer = DatasetWriter(out, "risk", recorded, seed)
    rows_by: dict[int, list[dict]] = {}
    state = {"spec": spec, "seed": seed, "root": Path(out)}
    for index, digest, count, rows in map_shards(
        _work, range(n), workers=workers, state=state, desc="generate_risk", unit="seq"
    ):
        writer.record_shard(index, shard_name(index), digest, count, splits[index])
        rows_by[index] = rows
    table = []
    fid = 0
    for index in range(n):
        for r in rows_by[index]:
            table.append({"frame_id": fid, "shard": index, "split": splits[index], **r})
            fid += 1
    df = pd.DataFrame(table)
    cols = ["frame_id", "shard", "idx", "scenario", "split"] + [
        c for c in df.columns if c not in ("frame_id", "shard", "idx", "scenario", "split")
    ]
    df = df[cols]
    writer.add_table("frames.csv", df)
    summary = summarise(df)
    writer.finalize(
        extra={"camera": spec.camera.intrinsics(), "label": spec.label, "summary": summary}
    )
    log.info("data/risk: %d frames, critical share %.3f", len(df), summary["all/critical_share"])
    return summary


def summarise(df: pd.DataFrame) -> dict:
    """Frame counts, critical share (THW < 1.5 s), fault and situation shares, per split."""
    out: dict = {}
    for name, part in [("all", df)] + [(s, df[df.split == s]) for s in ("train", "val", "test")]:
        if len(part) == 0:
            continue
        out[f"{name}/frames"] = int(len(part))
        out[f"{name}/sequences"] = int(part.scenario.nunique())
        out[f"{name}/critical_share"] = float(part.critical.mean())
        out[f"{name}/risk_mean"] = float(part.risk.mean())
    out["all/speed_mean"] = float(df.speed.mean())
    out["all/speed_max"] = float(df.speed.max())
    out["all/standstill_share"] = float((df.speed < 0.5).mean())
    for f, c in Counter(df.fault).items():
        out[f"all/fault_share_{f}"] = float(c / len(df))
    for s, c in Counter(df.groupby("scenario").situation.first()).items():
        out[f"all/sequences_{s}"] = int(c)
    for m in ("risk_thw_paper", "risk_thw_fov", "risk_ttc", "risk_wttc"):
        out[f"all/{m}_mean"] = float(df[m].mean())
        out[f"all/{m}_nonzero"] = float((df[m] > 0).mean())
    out["all/critical_share_fov"] = float((df.risk_thw_fov > 1 / 30).mean())
    return out


def main() -> None:
    cfg = params()
    with stage_timer("generate_risk"):
        summary = generate(cfg)
        write_json_atomic(ROOT / "reports" / "metrics" / "risk_data.json", summary)
        from traffictwin.risk.data_figures import risk_metric_figure

        spec = spec_from_params(cfg)
        risk_metric_figure(
            data_seed(cfg), spec, ROOT / "reports" / "figures" / "risk_metric_example.png"
        )


if __name__ == "__main__":
    run_stage(main, "generate_risk")
