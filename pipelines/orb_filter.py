"""Stage orb_filter: the paper's ORB pair check on every stereo pair of data/risk.

Writes data/orb/orb.csv (frame_id, n_matches, n_reliable, mean_dx, mean_dy, outlier, fault)
and reports/metrics/orb.json: detection rate per injected fault type, false-alarm rate on
fault-free pairs, share of frames dropped; a flagged pair -> reports/figures/orb_outlier_example.png.
"""

from __future__ import annotations

import pandas as pd

from traffictwin.config import typed
from traffictwin.io.atomic import atomic_path, write_json_atomic
from traffictwin.io.shards import Dataset
from traffictwin.risk.config import RiskDataConfig
from traffictwin.risk.data_figures import orb_example_figure
from traffictwin.risk.dataset import SPLITS, load_stereo_shard
from traffictwin.sim.driving import FAULTS
from traffictwin.stereo.orb import TABLE_COLUMNS, OrbParams, check_pairs, orb_frames, orb_metrics

from ._common import WORKER_STATE, map_shards, params, run_stage, setup_logging, stage_timer
from ._paths import ORB_CSV, RISK_DATA, figure_file, metrics_file


def _work(i: int):
    sh = load_stereo_shard(Dataset(WORKER_STATE["src"], kind="risk", verify=False), i)
    rows, secs = check_pairs(sh["left"], sh["right"], WORKER_STATE["orb"])
    return [{"shard": i, **r} for r in rows], secs


def run(orb: OrbParams, workers: int) -> tuple[pd.DataFrame, dict]:
    log = setup_logging()
    ds = Dataset(RISK_DATA, kind="risk")
    rows, total = [], 0.0
    for r, secs in map_shards(
        _work,
        range(len(ds.shards)),
        workers=workers,
        state={"src": str(RISK_DATA), "orb": orb},
        desc="orb_filter",
        ordered=True,
    ):
        rows.extend(r)
        total += secs
    df = orb_frames(ds.table("frames.csv"), pd.DataFrame(rows))
    metrics = orb_metrics(df, SPLITS, FAULTS, orb.min_reliable, orb.min_dx)
    metrics["all/ms_per_frame"] = 1000.0 * total / max(len(df), 1)
    log.info(
        "orb: dropped %.3f, detection %.3f, false alarms %.3f",
        metrics["all/dropped_share"],
        metrics.get("all/detection_rate", float("nan")),
        metrics["all/false_alarm_rate"],
    )
    return df[list(TABLE_COLUMNS)], metrics


def main() -> None:
    rd = typed(params().get("risk_data"), RiskDataConfig, key="risk_data")
    with stage_timer("orb_filter"):
        out, metrics = run(rd.orb, rd.workers)
        with atomic_path(ORB_CSV, suffix=".csv") as tmp:
            out.to_csv(tmp, index=False, float_format="%.6g", lineterminator="\n")
        write_json_atomic(metrics_file("orb"), metrics)
        orb_example_figure(
            Dataset(RISK_DATA, kind="risk", verify=False),
            out,
            rd.orb,
            figure_file("orb_outlier_example"),
        )


if __name__ == "__main__":
    run_stage(main, "orb_filter")
