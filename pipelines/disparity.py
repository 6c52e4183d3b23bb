"""Stage disparity: OpenCV SGM on every stereo pair of data/risk -> data/disparity (kind "disparity").

Shards are aligned 1:1 with data/risk (same index, split and frame order): ``disp_sgm``
(N, H, W) float32 px, -1 invalid. Accuracy against the GT disparity (density, bad-2.0, D1,
EPE; per split and per fault type) and ms/frame -> reports/metrics/disparity.json; a
figure like the paper's Fig. 2 -> reports/figures/stereo_example.png.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
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
from traffictwin.io.atomic import write_json_atomic
from traffictwin.io.shards import Dataset, DatasetWriter, shard_name, write_npz_deterministic
from traffictwin.risk.dataset import load_stereo_shard
from traffictwin.stereo.metrics import disparity_errors, summarise
from traffictwin.stereo.sgm import compute_disparity, make_matcher

SRC = ROOT / "data" / "risk"
OUT = ROOT / "data" / "disparity"


def sgm_params(cfg) -> dict:
    k = "risk_data.sgm"
    return dict(
        num_disparities=get(cfg, f"{k}.num_disparities", int, min=16),
        block_size=get(cfg, f"{k}.block_size", int, min=1),
        uniqueness_ratio=get(cfg, f"{k}.uniqueness_ratio", int, min=0),
        speckle_window=get(cfg, f"{k}.speckle_window", int, min=0),
        speckle_range=get(cfg, f"{k}.speckle_range", int, min=0),
        gray=get(cfg, f"{k}.gray", bool),
    )


def _work(i: int):
    ds = Dataset(WORKER_STATE["src"], kind="risk", verify=False)
    sh = load_stereo_shard(ds, i, ("left", "right", "disp_gt"))
    p = WORKER_STATE["sgm"]
    m = make_matcher(
        p["num_disparities"],
        p["block_size"],
        1 if p["gray"] else 3,
        p["uniqueness_ratio"],
        p["speckle_window"],
        p["speckle_range"],
    )
    out, per, secs = [], [], 0.0
    for k in range(len(sh["left"])):
        t0 = time.perf_counter()
        d = compute_disparity(sh["left"][k], sh["right"][k], gray=p["gray"], matcher=m)
        secs += time.perf_counter() - t0
        out.append(d)
        per.append(disparity_errors(d, sh["disp_gt"][k]))
    digest = write_npz_deterministic(
        Path(WORKER_STATE["out"]) / shard_name(i), {"disp_sgm": np.stack(out)}
    )
    return i, digest, len(out), per, secs


def run(cfg, src: Path = SRC, out: Path = OUT) -> dict:
    log = setup_logging()
    ds = Dataset(src, kind="risk")  # verifies every shard's SHA-256 first
    frames = ds.table("frames.csv")
    p = sgm_params(cfg)
    workers = get(cfg, "risk_data.workers", int, min=1)
    writer = DatasetWriter(
        out, "disparity", {"sgm": p, "source": ds.manifest_hash()}, ds.manifest.get("seed", 0)
    )
    n = len(ds.shards)
    per_frame: dict[int, list[dict]] = {}
    total_s = 0.0
    state = {"src": str(src), "out": str(out), "sgm": p}
    for i, digest, count, per, secs in map_shards(
        _work, range(n), workers=workers, state=state, desc="disparity"
    ):
        writer.record_shard(i, shard_name(i), digest, count, ds.shards[i].get("split"))
        per_frame[i] = per
        total_s += secs
    rows = []
    for i in range(n):
        for k, e in enumerate(per_frame[i]):
            rows.append({"shard": i, "idx": k, **e})
    err = pd.DataFrame(rows)
    df = frames.merge(err, on=["shard", "idx"], how="left", validate="one_to_one")
    metrics: dict = {}
    groups = [("all", df)] + [(s, df[df.split == s]) for s in ("train", "val", "test")]
    groups += [(f"fault_{f}", df[df.fault == f]) for f in ("none", "delay", "vertical")]
    keys = ["n_gt", "n_valid", "n_bad2", "n_d1", "sum_abs"]
    for name, part in groups:
        if len(part) == 0:
            continue
        sums = {k: float(part[k].sum()) for k in keys}
        for m, v in summarise(sums).items():
            metrics[f"{name}/{m}"] = v
    metrics["all/ms_per_frame"] = 1000.0 * total_s / max(len(df), 1)
    metrics["all/frames"] = int(len(df))
    per_tab = df[["frame_id"]].copy()
    per_tab["density"] = df.n_valid / df.n_gt.where(df.n_gt > 0)
    per_tab["bad2"] = df.n_bad2 / df.n_valid.where(df.n_valid > 0)
    per_tab["d1"] = df.n_d1 / df.n_valid.where(df.n_valid > 0)
    per_tab["epe"] = df.sum_abs / df.n_valid.where(df.n_valid > 0)
    writer.add_table("frames.csv", per_tab)
    # the manifest keeps only what the same params reproduce exactly (timings vary: metrics file only)
    accuracy = {k: v for k, v in metrics.items() if not k.endswith("ms_per_frame")}
    writer.finalize(extra={"source_manifest": ds.manifest_hash(), "metrics": accuracy})
    log.info(
        "disparity: bad2 %.4f density %.3f %.1f ms/frame",
        metrics["all/bad2"],
        metrics["all/density"],
        metrics["all/ms_per_frame"],
    )
    return metrics


def main() -> None:
    cfg = params()
    with stage_timer("disparity"):
        metrics = run(cfg)
        write_json_atomic(ROOT / "reports" / "metrics" / "disparity.json", metrics)
        from traffictwin.risk.data_figures import stereo_figure

        ds = Dataset(SRC, kind="risk", verify=False)
        dd = Dataset(OUT, kind="disparity", verify=False)
        frames = ds.table("frames.csv")
        clean = frames[(frames.fault == "none") & (frames.speed > 3)]
        row = (clean if len(clean) else frames).iloc[0]
        sh, sd = ds.load_shard(int(row.shard)), dd.load_shard(int(row.shard))
        k = int(row.idx)
        stereo_figure(
            sh["left"][k],
            sh["right"][k],
            sh["disp_gt"][k],
            sd["disp_sgm"][k],
            ROOT / "reports" / "figures" / "stereo_example.png",
            f"frame {int(row.frame_id)} ({row.template}, {row.situation}), v = {row.speed:.1f} m/s",
        )


if __name__ == "__main__":
    run_stage(main, "disparity")
