"""Stage disparity: OpenCV SGM on every stereo pair of data/risk -> data/disparity (kind "disparity").

Shards are aligned 1:1 with data/risk (same index, split and frame order): ``disp_sgm``
(N, H, W) float32 px, -1 invalid; frames.csv per frame: density, bad-2, D1, EPE and the GT-free
``valid_share`` (read by the stage orb_filter). Accuracy against the GT disparity (density,
bad-2.0, D1, EPE; the relative depth error |Z - Z_gt| / Z_gt per range bin of
``risk_data.check.depth_bins_m``: median, 90th percentile, valid share; per split and per fault
type) and ms/frame -> reports/metrics/disparity.json (the figure like the paper's Fig. 2 is
plot_data's).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path

import numpy as np

from traffictwin.config import ConfigError, typed
from traffictwin.io.atomic import write_json_atomic
from traffictwin.io.shards import (
    Dataset,
    DatasetError,
    DatasetWriter,
    shard_name,
    write_npz_deterministic,
)
from traffictwin.risk.config import RiskDataConfig
from traffictwin.risk.stereo_shards import SPLITS, load_stereo_shard
from traffictwin.sim.driving import FAULTS
from traffictwin.stereo.metrics import (
    accuracy_table,
    add_counts,
    depth_error_counts,
    depth_error_summary,
    disparity_errors,
    grouped_accuracy,
    per_frame_accuracy,
)
from traffictwin.stereo.sgm import SgmParams, disparity_frames, valid_share

from ._common import WORKER_STATE, map_shards, params, run_stage, setup_logging, stage_timer
from ._paths import DISPARITY, RISK_DATA, metrics_file


def _work(i: int):
    st = WORKER_STATE
    ds = Dataset(st["src"], kind="risk", verify=False)
    sh = load_stereo_shard(ds, i, ("left", "right", "disp_gt"))
    sgm: SgmParams = st["sgm"]
    disp, secs = disparity_frames(sh["left"], sh["right"], sgm)
    shares = valid_share(disp, sgm.num_disparities)
    per = [
        {**disparity_errors(d, g), "valid_share": float(v)}
        for d, g, v in zip(disp, sh["disp_gt"], shares)
    ]
    faults = np.asarray(st["faults"][i])
    depth = {  # depth-error histograms of this shard, summed per fault type
        str(f): depth_error_counts(
            disp[faults == f], sh["disp_gt"][faults == f], st["fx_b"], st["bins"]
        )
        for f in np.unique(faults)
    }
    digest = write_npz_deterministic(Path(st["out"]) / shard_name(i), {"disp_sgm": disp})
    return i, digest, len(disp), per, depth, secs


def depth_metrics(
    depth: dict[int, dict[str, dict]], shard_split: dict[int, str], bins: Sequence[float]
) -> dict[str, float]:
    """``<group>/<bin>_relerr_*`` over all frames, per split and per fault type (``fault_<f>``),
    from the per-shard, per-fault :func:`depth_error_counts`."""
    groups: dict[str, dict | None] = {"all": None}
    for i, per_fault in sorted(depth.items()):
        for f, c in per_fault.items():
            for g in ("all", shard_split[i], f"fault_{f}"):
                groups[g] = add_counts(groups.get(g), c)
    order = ["all", *SPLITS, *(f"fault_{f}" for f in FAULTS)]
    out: dict[str, float] = {}
    for g in order:
        if groups.get(g) is not None:
            for k, v in depth_error_summary(groups[g], bins).items():
                out[f"{g}/{k}"] = v
    return out


def run(
    sgm: SgmParams,
    workers: int,
    depth_bins: Sequence[float],
    src: Path = RISK_DATA,
    out: Path = DISPARITY,
    record: dict | None = None,
) -> dict:
    """SGM on every pair of ``src`` into ``out``; returns the accuracy metrics (the same for the
    same data and params). ``record``: the run record, which gets ``ms_per_frame`` (SGM wall time)."""
    log = setup_logging()
    ds = Dataset(src, kind="risk")  # verifies every shard's SHA-256 first
    frames = ds.table("frames.csv")
    cam = ds.manifest.get("camera") or {}
    if not {"fx", "baseline"} <= set(cam):
        raise DatasetError(
            f"{src / 'manifest.json'}: 'camera' lacks fx/baseline (has {sorted(cam)})"
        )
    writer = DatasetWriter(
        out,
        "disparity",
        {"sgm": asdict(sgm), "source": ds.manifest_hash()},
        ds.manifest.get("seed", 0),
    )
    per_frame: dict[int, list[dict]] = {}
    depth: dict[int, dict[str, dict]] = {}
    total_s = 0.0
    faults = {int(i): list(g.sort_values("idx").fault) for i, g in frames.groupby("shard")}
    state = {
        "src": str(src),
        "out": str(out),
        "sgm": sgm,
        "faults": faults,
        "fx_b": float(cam["fx"]) * float(cam["baseline"]),
        "bins": [float(b) for b in depth_bins],
    }
    for i, digest, count, per, dep, secs in map_shards(
        _work, range(len(ds.shards)), workers=workers, state=state, desc="disparity"
    ):
        writer.record_shard(i, shard_name(i), digest, count, ds.shards[i].get("split"))
        per_frame[i] = per
        depth[i] = dep
        total_s += secs
    df = accuracy_table(frames, per_frame)
    metrics: dict = grouped_accuracy(df, SPLITS, FAULTS)
    split_of = {i: str(s.get("split")) for i, s in enumerate(ds.shards)}
    metrics.update(depth_metrics(depth, split_of, state["bins"]))
    metrics = {k: (None if isinstance(v, float) and np.isinf(v) else v) for k, v in metrics.items()}
    metrics["all/frames"] = int(len(df))
    ms_per_frame = 1000.0 * total_s / max(len(df), 1)
    if record is not None:  # timings vary between identical runs: run record only
        record["ms_per_frame"] = round(ms_per_frame, 3)
    writer.add_table("frames.csv", per_frame_accuracy(df))
    writer.finalize(extra={"source_manifest": ds.manifest_hash(), "metrics": metrics})
    log.info(
        "disparity: bad2 %.4f density %.3f %.1f ms/frame",
        metrics["all/bad2"],
        metrics["all/density"],
        ms_per_frame,
    )
    return metrics


def main() -> None:
    rd = typed(params().get("risk_data"), RiskDataConfig, key="risk_data")
    try:  # before data/disparity is touched
        rd.sgm.check_width(rd.camera.width, what="params.yaml: 'risk_data.sgm'")
    except ValueError as exc:
        raise ConfigError(f"{exc} ('risk_data.camera.width')") from None
    with stage_timer("disparity") as record:
        metrics = run(rd.sgm, rd.workers, rd.check.depth_bins_m, record=record)
        write_json_atomic(metrics_file("disparity"), metrics)


if __name__ == "__main__":
    run_stage(main, "disparity")
