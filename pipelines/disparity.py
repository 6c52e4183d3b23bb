"""Stage disparity: OpenCV SGM on every stereo pair of data/risk -> data/disparity (kind "disparity").

Shards are aligned 1:1 with data/risk (same index, split and frame order): ``disp_sgm``
(N, H, W) float32 px, -1 invalid. Accuracy against the GT disparity (density, bad-2.0, D1,
EPE; per split and per fault type) and ms/frame -> reports/metrics/disparity.json; a
figure like the paper's Fig. 2 -> reports/figures/stereo_example.png.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

from traffictwin.config import typed
from traffictwin.io.atomic import write_json_atomic
from traffictwin.io.shards import Dataset, DatasetWriter, shard_name, write_npz_deterministic
from traffictwin.risk.config import RiskDataConfig
from traffictwin.risk.data_figures import stereo_example_figure
from traffictwin.risk.dataset import SPLITS, load_stereo_shard
from traffictwin.sim.driving import FAULTS
from traffictwin.stereo.metrics import (
    accuracy_table,
    disparity_errors,
    grouped_accuracy,
    per_frame_accuracy,
)
from traffictwin.stereo.sgm import SgmParams, disparity_frames

from ._common import WORKER_STATE, map_shards, params, run_stage, setup_logging, stage_timer
from ._paths import DISPARITY, RISK_DATA, figure_file, metrics_file


def _work(i: int):
    ds = Dataset(WORKER_STATE["src"], kind="risk", verify=False)
    sh = load_stereo_shard(ds, i, ("left", "right", "disp_gt"))
    disp, secs = disparity_frames(sh["left"], sh["right"], WORKER_STATE["sgm"])
    per = [disparity_errors(d, g) for d, g in zip(disp, sh["disp_gt"])]
    digest = write_npz_deterministic(Path(WORKER_STATE["out"]) / shard_name(i), {"disp_sgm": disp})
    return i, digest, len(disp), per, secs


def run(sgm: SgmParams, workers: int, src: Path = RISK_DATA, out: Path = DISPARITY) -> dict:
    log = setup_logging()
    ds = Dataset(src, kind="risk")  # verifies every shard's SHA-256 first
    frames = ds.table("frames.csv")
    writer = DatasetWriter(
        out,
        "disparity",
        {"sgm": asdict(sgm), "source": ds.manifest_hash()},
        ds.manifest.get("seed", 0),
    )
    per_frame: dict[int, list[dict]] = {}
    total_s = 0.0
    state = {"src": str(src), "out": str(out), "sgm": sgm}
    for i, digest, count, per, secs in map_shards(
        _work, range(len(ds.shards)), workers=workers, state=state, desc="disparity"
    ):
        writer.record_shard(i, shard_name(i), digest, count, ds.shards[i].get("split"))
        per_frame[i] = per
        total_s += secs
    df = accuracy_table(frames, per_frame)
    metrics: dict = grouped_accuracy(df, SPLITS, FAULTS)
    metrics["all/ms_per_frame"] = 1000.0 * total_s / max(len(df), 1)
    metrics["all/frames"] = int(len(df))
    writer.add_table("frames.csv", per_frame_accuracy(df))
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
    rd = typed(params().get("risk_data"), RiskDataConfig, key="risk_data")
    with stage_timer("disparity"):
        metrics = run(rd.sgm, rd.workers)
        write_json_atomic(metrics_file("disparity"), metrics)
        stereo_example_figure(
            Dataset(RISK_DATA, kind="risk", verify=False),
            Dataset(DISPARITY, kind="disparity", verify=False),
            figure_file("stereo_example"),
        )


if __name__ == "__main__":
    run_stage(main, "disparity")
