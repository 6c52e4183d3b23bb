"""Stage orb_filter: the paper's ORB pair check on every stereo pair of data/risk.

Writes data/orb/orb.csv (frame_id, n_matches, n_reliable, mean_dx, mean_dy, outlier, fault)
and reports/metrics/orb.json: detection rate per injected fault type, false-alarm rate on
fault-free pairs, share of frames dropped; a flagged pair -> reports/figures/orb_outlier_example.png.
"""

from __future__ import annotations

import time

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
from traffictwin.io.atomic import atomic_path, write_json_atomic
from traffictwin.io.shards import Dataset
from traffictwin.risk.dataset import load_stereo_shard
from traffictwin.stereo.orb import check_pair

SRC = ROOT / "data" / "risk"
OUT = ROOT / "data" / "orb" / "orb.csv"


def orb_params(cfg) -> dict:
    k = "risk_data.orb"
    return dict(
        n_features=get(cfg, f"{k}.n_features", int, min=10),
        fast_threshold=get(cfg, f"{k}.fast_threshold", int, min=1),
        n_levels=get(cfg, f"{k}.n_levels", int, min=1),
        edge_threshold=get(cfg, f"{k}.edge_threshold", int, min=3),
        max_hamming=get(cfg, f"{k}.max_hamming", float, min=0),
        best_n=get(cfg, f"{k}.best_n", int, min=1),
        min_reliable=get(cfg, f"{k}.min_reliable", int, min=1),
        statistic=get(cfg, f"{k}.statistic", str, choices=("mean", "median")),
        min_dx=get(cfg, f"{k}.min_dx", float, min=0),
        max_dy=get(cfg, f"{k}.max_dy", float, min=0),
    )


def _work(i: int):
    sh = load_stereo_shard(Dataset(WORKER_STATE["src"], kind="risk", verify=False), i)
    rows, secs = [], 0.0
    for k in range(len(sh["left"])):
        t0 = time.perf_counter()
        r = check_pair(sh["left"][k], sh["right"][k], **WORKER_STATE["orb"])
        secs += time.perf_counter() - t0
        rows.append({"shard": i, "idx": k, **r.as_dict()})
    return rows, secs


def run(cfg) -> tuple[pd.DataFrame, dict]:
    log = setup_logging()
    ds = Dataset(SRC, kind="risk")
    frames = ds.table("frames.csv")
    p = orb_params(cfg)
    workers = get(cfg, "risk_data.workers", int, min=1)
    n = len(ds.shards)
    rows, total = [], 0.0
    for r, secs in map_shards(
        _work,
        range(n),
        workers=workers,
        state={"src": str(SRC), "orb": p},
        desc="orb_filter",
        ordered=True,
    ):
        rows.extend(r)
        total += secs
    res = pd.DataFrame(rows)
    df = frames[["frame_id", "shard", "idx", "split", "fault", "speed"]].merge(
        res, on=["shard", "idx"], validate="one_to_one"
    )
    df = df.sort_values("frame_id").reset_index(drop=True)
    out = df[["frame_id", "n_matches", "n_reliable", "mean_dx", "mean_dy", "outlier", "fault"]]
    metrics = orb_metrics(df)
    metrics["all/ms_per_frame"] = 1000.0 * total / max(len(df), 1)
    log.info(
        "orb: dropped %.3f, detection %.3f, false alarms %.3f",
        metrics["all/dropped_share"],
        metrics.get("all/detection_rate", float("nan")),
        metrics["all/false_alarm_rate"],
    )
    return out, metrics


def orb_metrics(df: pd.DataFrame) -> dict:
    """Detection rate (flagged among faulty pairs, per fault type), false-alarm rate (flagged among
    fault-free pairs), dropped share; also split by speed (faults are invisible at standstill)."""
    m: dict = {"all/frames": int(len(df)), "all/dropped_share": float(df.outlier.mean())}
    faulty = df.fault != "none"
    m["all/false_alarm_rate"] = (
        float(df.outlier[~faulty].mean()) if (~faulty).any() else float("nan")
    )
    if faulty.any():
        m["all/detection_rate"] = float(df.outlier[faulty].mean())
    for f in ("delay", "vertical"):
        sel = df.fault == f
        m[f"all/faults_{f}"] = int(sel.sum())
        if sel.any():
            m[f"{f}/detection_rate"] = float(df.outlier[sel].mean())
            mov = sel & (df.speed >= 5.0)
            if mov.any():
                m[f"{f}/detection_rate_speed_ge_5"] = float(df.outlier[mov].mean())
    for s in ("train", "val", "test"):
        part = df[df.split == s]
        if len(part):
            m[f"{s}/dropped_share"] = float(part.outlier.mean())
    # sensitivity of the rule's |dy| threshold (same per-frame statistics, no re-matching)
    for thr in (1.0, 2.0, 3.0, 5.0):
        flag = (df.n_reliable < 1) | (df.mean_dx < 1.0) | (df.mean_dy > thr) | df.mean_dy.isna()
        m[f"sweep/max_dy_{thr:g}_false_alarm_rate"] = (
            float(flag[~faulty].mean()) if (~faulty).any() else float("nan")
        )
        for f in ("delay", "vertical"):
            sel = df.fault == f
            if sel.any():
                m[f"sweep/max_dy_{thr:g}_{f}_detection_rate"] = float(flag[sel].mean())
    m["none/mean_dy_median"] = (
        float(df.mean_dy[~faulty].median()) if (~faulty).any() else float("nan")
    )
    m["none/mean_dx_median"] = (
        float(df.mean_dx[~faulty].median()) if (~faulty).any() else float("nan")
    )
    return m


def main() -> None:
    cfg = params()
    with stage_timer("orb_filter"):
        out, metrics = run(cfg)
        with atomic_path(OUT, suffix=".csv") as tmp:
            out.to_csv(tmp, index=False, float_format="%.6g", lineterminator="\n")
        write_json_atomic(ROOT / "reports" / "metrics" / "orb.json", metrics)
        from traffictwin.risk.data_figures import orb_figure

        ds = Dataset(SRC, kind="risk", verify=False)
        frames = ds.table("frames.csv")
        flagged = out[out.outlier & (out.fault != "none")]
        if not len(flagged):
            flagged = out[out.outlier] if out.outlier.any() else out
        fid = int(flagged.frame_id.iloc[0])
        row = frames[frames.frame_id == fid].iloc[0]
        sh = ds.load_shard(int(row.shard))
        o = out[out.frame_id == fid].iloc[0]
        orb_figure(
            sh["left"][int(row.idx)],
            sh["right"][int(row.idx)],
            ROOT / "reports" / "figures" / "orb_outlier_example.png",
            f"frame {fid}: fault '{row.fault}', mean |dx| {o.mean_dx:.2f} px, mean |dy| {o.mean_dy:.2f} px, "
            f"outlier={bool(o.outlier)}",
            **{
                k: v
                for k, v in orb_params(cfg).items()
                if k in ("n_features", "fast_threshold", "n_levels", "edge_threshold")
            },
        )


if __name__ == "__main__":
    run_stage(main, "orb_filter")
