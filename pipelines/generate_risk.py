"""Stage generate_risk: driving sequences -> stereo frames + risk labels -> data/risk (kind "risk").

One shard per driving sequence (= scenario), rendered in parallel worker processes
(``risk_data.workers``); splits 70/10/20 by sequence, stratified by the sequence's situation. A
frame is ``critical`` when its THW is below the primary ``evaluation.risk.thresholds_s``. Also writes
reports/metrics/risk_data.json (the risk-metric example figure is plot_data's).
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf

from traffictwin.config import get, typed
from traffictwin.grid import GridSpec
from traffictwin.io.atomic import write_json_atomic
from traffictwin.io.shards import DatasetWriter, shard_name, write_npz_deterministic
from traffictwin.risk.config import RiskDataConfig
from traffictwin.risk.dataset import (
    RiskDataSpec,
    assign_splits,
    frame_table,
    make_shard,
    summarise_frames,
)
from traffictwin.risk.metric import primary
from traffictwin.sim.driving import draw_situation

from ._common import WORKER_STATE, map_shards, params, run_stage, setup_logging, stage_timer
from ._paths import RISK_DATA, metrics_file


def read_config(cfg) -> tuple[RiskDataConfig, RiskDataSpec, int]:
    """``risk_data`` validated, the generation spec on the configured grid (frames critical below
    the primary ``evaluation.risk.thresholds_s``), and the data seed."""
    rd = typed(cfg.get("risk_data"), RiskDataConfig, key="risk_data")
    grid = GridSpec(
        get(cfg, "grid.rows", int, min=8),
        get(cfg, "grid.cols", int, min=8),
        get(cfg, "grid.cell", float, min=0.01),
    )
    critical_thw_s = primary(get(cfg, "evaluation.risk.thresholds_s", list))
    return rd, rd.data_spec(grid, critical_thw_s), rd.data_seed(get(cfg, "seed", int, min=0))


def _work(index: int) -> tuple[int, str, int, list[dict]]:
    arrays, rows = make_shard(WORKER_STATE["seed"], index, WORKER_STATE["spec"])
    digest = write_npz_deterministic(
        WORKER_STATE["root"] / shard_name(index), arrays, compresslevel=WORKER_STATE["level"]
    )
    return index, digest, len(rows), rows


def recorded_params(cfg) -> dict:
    """What the data version records: ``risk_data`` as in params.yaml (less ``workers`` and
    ``compresslevel``, which do not change the data) and ``grid``."""
    rec = {
        k: v
        for k, v in OmegaConf.to_container(cfg.risk_data, resolve=True).items()
        if k not in ("workers", "compresslevel")
    }
    rec["grid"] = OmegaConf.to_container(cfg.grid, resolve=True)
    return rec


def generate(
    rd: RiskDataConfig, spec: RiskDataSpec, seed: int, recorded: dict, out: Path = RISK_DATA
) -> dict:
    """Generate the dataset into ``out``; returns the summary metrics."""
    log = setup_logging()
    situations = [draw_situation(seed, i, spec.driving.situations) for i in range(rd.sequences)]
    splits = assign_splits(rd.sequences, seed, rd.split_fractions(), strata=situations)
    writer = DatasetWriter(out, "risk", recorded, seed)
    rows_by: dict[int, list[dict]] = {}
    state = {"spec": spec, "seed": seed, "root": Path(out), "level": rd.compresslevel}
    for index, digest, count, rows in map_shards(
        _work,
        range(rd.sequences),
        workers=rd.workers,
        state=state,
        desc="generate_risk",
        unit="seq",
    ):
        writer.record_shard(index, shard_name(index), digest, count, splits[index])
        rows_by[index] = rows
    df = frame_table(rows_by, splits)
    writer.add_table("frames.csv", df)
    summary = summarise_frames(df, spec.critical_thw_s)
    writer.finalize(
        extra={"camera": spec.camera.intrinsics(), "label": spec.label, "summary": summary}
    )
    log.info("data/risk: %d frames, critical share %.3f", len(df), summary["all/critical_share"])
    return summary


def main() -> None:
    cfg = params()
    rd, spec, seed = read_config(cfg)
    with stage_timer("generate_risk"):
        summary = generate(rd, spec, seed, recorded_params(cfg))
        write_json_atomic(metrics_file("risk_data"), summary)


if __name__ == "__main__":
    run_stage(main, "generate_risk")
