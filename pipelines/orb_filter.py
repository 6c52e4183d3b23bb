"""Stage orb_filter: the stereo pair checks on every pair of data/risk -> data/orb/orb.csv.

Runs the ORB pair check (paper Sec. 3.3) on every pair and reads the SGM valid share of each
pair from data/disparity/frames.csv (stage disparity). Writes data/orb/orb.csv (columns
:data:`traffictwin.stereo.orb.TABLE_COLUMNS`: the ORB statistics, ``valid_share``, one flag per
rule -- ``flag_orb_paper``, ``flag_orb``, ``flag_valid_share`` -- and ``outlier`` = the configured
``risk_data.check.rule``, the "drop this pair" column the risk training reads) and
reports/metrics/orb.json: for ``outlier`` the detection rate per injected fault type, the
false-alarm rate on fault-free pairs and the share dropped; for every rule the detection /
false-alarm table with scenario-cluster bootstrap 95 % intervals (delay faults also per subject
speed); the |dy| and valid-share threshold sweeps (the figure of an ORB-flagged pair is
plot_data's).
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from traffictwin.config import typed
from traffictwin.io.atomic import write_csv_atomic, write_json_atomic
from traffictwin.io.shards import Dataset, DatasetError, derived_dataset
from traffictwin.risk.config import RiskDataConfig
from traffictwin.risk.stereo_shards import SPLITS, load_stereo_shard
from traffictwin.sim.driving import FAULTS
from traffictwin.stereo.check import (
    RULES,
    StereoCheckParams,
    add_flags,
    choose_min_valid_share,
    key_fragment,
    valid_share_sweep,
)
from traffictwin.stereo.detection import detection_table
from traffictwin.stereo.orb import TABLE_COLUMNS, OrbParams, check_pairs, orb_frames, orb_metrics

from ._common import WORKER_STATE, map_shards, params, run_stage, setup_logging, stage_timer
from ._paths import DISPARITY, ORB_CSV, RISK_DATA, metrics_file


def _work(i: int):
    sh = load_stereo_shard(Dataset(WORKER_STATE["src"], kind="risk", verify=False), i)
    rows, secs = check_pairs(sh["left"], sh["right"], WORKER_STATE["orb"])
    return [{"shard": i, **r} for r in rows], secs


def valid_shares(risk: Dataset, disparity: Path = DISPARITY) -> pd.DataFrame:
    """``frame_id``, ``valid_share`` of every frame of ``risk`` from the disparity stage's
    frames.csv; a clear error when data/disparity is missing, stale or lacks the column."""
    disp = derived_dataset(disparity, "disparity", risk, "data/risk", "disparity")
    table = disp.table("frames.csv")
    if "valid_share" not in table.columns:
        raise DatasetError(
            f"{disparity / 'frames.csv'}: column 'valid_share' missing (has {list(table.columns)}): "
            "rerun the disparity stage"
        )
    return table[["frame_id", "valid_share"]]


def run(
    orb: OrbParams,
    check: StereoCheckParams,
    workers: int,
    src: Path = RISK_DATA,
    disparity: Path = DISPARITY,
    record: dict | None = None,
) -> tuple[pd.DataFrame, dict]:
    """The pair-check table and metrics (the same for the same data and params); ``record``: the
    run record, which gets ``ms_per_frame`` (ORB wall time)."""
    log = setup_logging()
    ds = Dataset(src, kind="risk")
    shares = valid_shares(
        ds, disparity
    )  # before the slow ORB pass: a stale data/disparity fails first
    rows, total = [], 0.0
    for r, secs in map_shards(
        _work,
        range(len(ds.shards)),
        workers=workers,
        state={"src": str(src), "orb": orb},
        desc="orb_filter",
        ordered=True,
    ):
        rows.extend(r)
        total += secs
    df = orb_frames(
        ds.table("frames.csv"), pd.DataFrame(rows).rename(columns={"outlier": "flag_orb"})
    )
    df = df.merge(shares, on="frame_id", how="left", validate="one_to_one")
    if df.valid_share.isna().any():
        missing = df.frame_id[df.valid_share.isna()].tolist()[:5]
        raise DatasetError(f"{disparity / 'frames.csv'}: no valid_share for frames {missing}...")
    chosen = None
    min_valid_share = check.min_valid_share
    if min_valid_share is None:  # chosen on the validation split (none on test)
        min_valid_share, chosen = choose_min_valid_share(
            df[df["split"] == "val"], check.max_false_alarm
        )
    df = add_flags(
        df,
        min_dx=orb.min_dx,
        max_dy=orb.max_dy,
        min_valid_share=min_valid_share,
        rule=check.rule,
    )
    metrics = orb_metrics(df, SPLITS, FAULTS, orb.min_reliable, orb.min_dx)
    metrics.update(detection_table(df, FAULTS))
    metrics.update(valid_share_sweep(df, FAULTS))
    metrics["check/min_valid_share"] = float(min_valid_share)
    metrics["check/min_valid_share_chosen_on"] = "val" if chosen else "config"
    for r in chosen or []:
        pre = f"check/val_min_valid_share_{key_fragment(r['min_valid_share'])}"
        metrics[f"{pre}_detection_rate"] = r["detection_rate"]
        metrics[f"{pre}_false_alarm_rate"] = r["false_alarm_rate"]
    metrics.update({f"rule_{r}/configured": int(r == check.rule) for r in RULES})
    if record is not None:  # timings vary between identical runs: run record only
        record["ms_per_frame"] = round(1000.0 * total / max(len(df), 1), 3)
    log.info(
        "pair check (%s): dropped %.3f, detection %.3f, false alarms %.3f",
        check.rule,
        metrics["all/dropped_share"],
        metrics.get("all/detection_rate", float("nan")),
        metrics["all/false_alarm_rate"],
    )
    return df[list(TABLE_COLUMNS)], metrics


def main() -> None:
    rd = typed(params().get("risk_data"), RiskDataConfig, key="risk_data")
    with stage_timer("orb_filter") as record:
        out, metrics = run(rd.orb, rd.check, rd.workers, record=record)
        write_csv_atomic(ORB_CSV, out, float_format="%.6g", lineterminator="\n")
        write_json_atomic(metrics_file("orb"), metrics)


if __name__ == "__main__":
    run_stage(main, "orb_filter")
