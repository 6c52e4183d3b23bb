"""Stage stereo_learned: the learned stereo network on every pair of data/risk -> data/stereo_learned,
and the stereo evaluation of SGM and the learned network on the test split.

Usage: ``python -m pipelines.stereo_learned``. Reads ``models/stereo/learned`` and
``models/stereo/holdout`` (sealed, weights-only), ``data/risk``, ``data/disparity`` (SGM, must be made from the same data/risk) and
params.yaml ``evaluation.num_threads`` (torch threads of the inference) and
``evaluation.stereo.n_boot``. Writes, each atomically:

- ``data/stereo_learned`` (kind ``stereo_learned``): shards aligned 1:1 with data/risk (same index,
  split, frame order): ``disp_learned`` (N, H, W) float32 px, -1 where the spread exceeds the
  threshold calibrated on validation (the model meta's ``spread_threshold_px``), and
  ``disp_learned_spread`` (N, H, W) float32 px. A ``base: sgm`` model refines data/disparity's
  ``disp_sgm`` (its input): ``disp_learned`` is -1 exactly where SGM is, and the spread holds the
  |residual| added to SGM (px, 0 where SGM is invalid; the threshold keeps every SGM pixel);
- ``reports/metrics/stereo.json``: the learned stereo's ``targets`` (:mod:`traffictwin.stereo.targets`) and, on the fault-free test frames, for ``sgm`` and ``learned``, on the
  pixels with ground truth that both sources mark valid (``common``) and on each source's own valid
  pixels (``own``, with its ``density`` among the ground-truth pixels): EPE, bad-1, bad-2, the
  relative range error |Z - Z_gt| / Z_gt (median, p90) per distance band (0-10, 10-30, 30-90 m)
  and on the object pixels at the critical distances (12-21 m), each with a sequence-bootstrap
  95 % interval; paired differences learned - SGM (EPE, critical-object median) with intervals;
  ``learned/ms_per_frame`` (batch inference, this CPU) goes to the run record; ``generalisation``:
  the same figures for SGM, the full network and ``models/stereo/holdout`` (trained without its
  meta's ``holdout_templates``) on those templates' fault-free test frames, with the paired
  differences holdout − learned and holdout − SGM (the example figure is drawn by plot_data).
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from traffictwin.acceptance import Threshold, for_problem
from traffictwin.config import ConfigError, get
from traffictwin.io.atomic import write_json_atomic
from traffictwin.io.shards import (
    Dataset,
    DatasetError,
    DatasetWriter,
    derived_dataset,
    shard_name,
    write_npz_deterministic,
)
from traffictwin.risk.stereo_shards import load_stereo_shard
from traffictwin.stereo.evaluation import critical_objects, evaluate, frame_sums
from traffictwin.stereo.targets import stereo_targets

from ._common import params, run_stage, setup_logging, stage_timer
from ._paths import (
    DISPARITY,
    RISK_DATA,
    STEREO_HOLDOUT_MODEL,
    STEREO_LEARNED,
    STEREO_MODEL,
    metrics_file,
)

STAGE = "stereo_learned"
#: zlib level of the shards: the network's float32 disparity and spread barely compress (an 8-frame
#: default-profile shard: 2.21 MB in 0.19 s at level 6, 3.28 MB in 0.02 s stored), and level 6
#: took 85 s of the default run's stage
SHARD_COMPRESSLEVEL = 0


@dataclass
class _Inputs:
    """What :func:`run` reads: the network(s), data/risk, data/disparity (SGM) and the camera."""

    net: Any
    held_net: Any  # the hold-out network, or None
    held: list[str]  # its held-out road templates
    ds: Dataset
    sgm: Dataset
    cam: dict
    fx_b: float  # focal length (px) × baseline (m)
    thr: float  # the network's spread threshold (px)


def _load_inputs(model: Path, src: Path, disparity: Path, holdout_model: Path | None) -> _Inputs:
    """The networks and datasets of :func:`run`, checked (DatasetError when missing/inconsistent)."""
    from traffictwin.risk.stereo_io import load_stereo_model

    if not (Path(src) / "manifest.json").exists():
        raise DatasetError(f"{src}: no manifest.json (run `dvc repro generate_risk` first)")
    net = load_stereo_model(model)
    held_net = load_stereo_model(holdout_model) if holdout_model is not None else None
    held = [str(t) for t in (held_net.meta.get("holdout_templates") or [])] if held_net else []  # type: ignore[attr-defined]
    if held_net is not None and not held:
        raise DatasetError(f"{holdout_model}: model_meta.json names no held-out road templates")
    ds = Dataset(src, kind="risk")  # verifies every shard's SHA-256
    sgm = derived_dataset(disparity, "disparity", ds, "data/risk", "disparity")
    cam = ds.manifest.get("camera") or {}
    if not {"fx", "baseline", "cy", "fy", "mount_height"} <= set(cam):
        raise DatasetError(
            f"{Path(src) / 'manifest.json'}: 'camera' lacks fx/baseline/cy/fy/mount_height"
        )
    fx_b = float(cam["fx"]) * float(cam["baseline"])
    thr = float(net.meta["spread_threshold_px"])  # type: ignore[attr-defined]
    return _Inputs(net, held_net, held, ds, sgm, cam, fx_b, thr)


@dataclass
class _TestSums:
    """Per-frame sums of the fault-free test frames (:func:`frame_sums`) and their sequences;
    ``gen_*``: the same for the held-out templates' frames."""

    acc: list[dict[str, dict[str, Any]]] = field(default_factory=list)
    seqs: list[np.ndarray] = field(default_factory=list)
    gen_acc: list[dict[str, dict[str, Any]]] = field(default_factory=list)
    gen_seqs: list[np.ndarray] = field(default_factory=list)


def _score_shard(
    x: _Inputs,
    i: int,
    sh: dict[str, np.ndarray],
    rows: Any,
    disp: np.ndarray,
    batch_size: int,
    sums: _TestSums,
) -> None:
    """Add shard ``i``'s fault-free test frames (``rows``: its frames.csv rows by ``idx``) to
    ``sums``: SGM and the network's ``disp`` (px), and the hold-out network on its templates."""
    from traffictwin.risk.stereo_io import predict

    sel = ((rows.split == "test") & (rows.fault == "none")).to_numpy()
    if not sel.any():
        return
    d_sgm = x.sgm.load_shard(i)["disp_sgm"][sel]
    gt = sh["disp_gt"][sel]
    obj = critical_objects(gt, x.fx_b, x.cam)
    sums.acc.append(frame_sums({"sgm": d_sgm, "learned": disp[sel]}, gt, x.fx_b, obj))
    sums.seqs.append(rows.scenario.to_numpy()[sel])
    unseen = rows.template.astype(str).isin(x.held).to_numpy()[sel] if x.held else None
    if unseen is not None and unseen.any():
        held_net = x.held_net
        d_h, spread_h = predict(
            held_net,
            sh["left"][sel][unseen],
            sh["right"][sel][unseen],
            batch_size,
            sgm=d_sgm[unseen] if held_net.spec.base == "sgm" else None,
        )
        thr_h = float(held_net.meta["spread_threshold_px"])
        d_h = np.where(spread_h <= thr_h, d_h, -1.0).astype(np.float32)
        sums.gen_acc.append(
            frame_sums(
                {"sgm": d_sgm[unseen], "learned": disp[sel][unseen], "holdout": d_h},
                gt[unseen],
                x.fx_b,
                obj[unseen],
            )
        )
        sums.gen_seqs.append(rows.scenario.to_numpy()[sel][unseen])


def _test_metrics(
    x: _Inputs,
    sums: _TestSums,
    src: Path,
    n_boot: int,
    thresholds: Mapping[str, Threshold] | None,
) -> dict[str, Any]:
    """stereo.json's metrics from the test sums: SGM vs the network, its targets and the
    hold-out network's ``generalisation``."""
    if not sums.acc:
        raise DatasetError(f"{src}: no fault-free test frames to evaluate on")
    metrics: dict[str, Any] = _finite(evaluate(_stack(sums.acc), np.concatenate(sums.seqs), n_boot))
    metrics["learned/spread_threshold_px"] = x.thr
    if thresholds is None:
        thresholds = for_problem(params(), "stereo")
    metrics["targets"] = stereo_targets(metrics, thresholds)
    if x.held_net is not None:
        metrics["generalisation"] = generalisation(x.held, sums.gen_acc, sums.gen_seqs, n_boot)
    return metrics


def run(
    model: Path = STEREO_MODEL,
    src: Path = RISK_DATA,
    disparity: Path = DISPARITY,
    out: Path = STEREO_LEARNED,
    *,
    num_threads: int = 0,
    n_boot: int = 1000,
    batch_size: int = 8,
    record: dict | None = None,
    holdout_model: Path | None = None,
    thresholds: Mapping[str, Threshold] | None = None,
) -> dict[str, Any]:
    """The network on every pair of ``src`` into ``out``; returns the test metrics. Nothing is
    written when an input is missing or inconsistent. ``holdout_model``: the network trained
    without some road templates (its meta's ``holdout_templates``), scored with the full one and
    SGM on those templates' fault-free test frames (``generalisation``). ``thresholds``: the
    targets' acceptance thresholds (``acceptance.stereo``; default: read from params.yaml)."""
    from traffictwin.risk.stereo_io import predict
    from traffictwin.threads import pin_threads

    log = setup_logging()
    x = _load_inputs(model, src, disparity, holdout_model)
    ds, net, thr = x.ds, x.net, x.thr
    pin_threads(num_threads)
    frames = ds.table("frames.csv")
    writer = DatasetWriter(
        out,
        "stereo_learned",
        {"source": ds.manifest_hash(), "model_sha256": _sha(model), "spread_threshold_px": thr},
        ds.manifest.get("seed", 0),
    )
    seconds, n_frames = 0.0, 0
    sums = _TestSums()
    for i, info in enumerate(ds.shards):
        sh = load_stereo_shard(ds, i, ("left", "right", "disp_gt"))
        d_in = x.sgm.load_shard(i)["disp_sgm"] if net.spec.base == "sgm" else None
        t0 = time.perf_counter()
        disp, spread = predict(net, sh["left"], sh["right"], batch_size, sgm=d_in)
        seconds += time.perf_counter() - t0
        n_frames += len(disp)
        disp = np.where(spread <= thr, disp, -1.0).astype(np.float32)
        digest = write_npz_deterministic(
            Path(out) / shard_name(i),
            {"disp_learned": disp, "disp_learned_spread": spread},
            compresslevel=SHARD_COMPRESSLEVEL,
        )
        writer.record_shard(i, shard_name(i), digest, len(disp), info.get("split"))
        rows = frames[frames.shard == i].sort_values("idx")
        _score_shard(x, i, sh, rows, disp, batch_size, sums)
    metrics = _test_metrics(x, sums, src, n_boot, thresholds)
    ms = 1000.0 * seconds / max(n_frames, 1)
    if record is not None:  # timings vary between identical runs: run record only
        record["ms_per_frame"] = round(ms, 3)
        record["torch_threads"] = num_threads
    writer.finalize(extra={"source_manifest": ds.manifest_hash(), "metrics": metrics})
    log.info(
        "%s: test EPE learned %.3f / SGM %.3f px (common pixels), critical objects median "
        "%.1f %% / %.1f %% (own pixels), %.1f ms/frame",
        STAGE,
        metrics["learned/common/epe"],
        metrics["sgm/common/epe"],
        100 * (metrics["learned/own/crit_obj_relerr_median"] or float("nan")),
        100 * (metrics["sgm/own/crit_obj_relerr_median"] or float("nan")),
        ms,
    )
    return metrics


def _stack(acc: list[dict[str, dict[str, Any]]]) -> dict[str, dict[str, np.ndarray]]:
    """Per-shard :func:`frame_sums` joined frame-wise."""
    return {k: {f: np.concatenate([a[k][f] for a in acc]) for f in acc[0][k]} for k in acc[0]}


def _finite(metrics: dict[str, Any]) -> dict[str, Any]:
    """NaN / inf -> ``None`` (JSON null)."""
    return {
        k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in metrics.items()
    }


def generalisation(
    templates: list[str],
    acc: list[dict[str, dict[str, Any]]],
    sequences: list[np.ndarray],
    n_boot: int,
) -> dict[str, Any]:
    """SGM, the full network (``learned``) and the one trained without ``templates``
    (``holdout``) on those templates' fault-free test frames (:func:`evaluate`, with the paired
    differences holdout − learned and holdout − SGM); ``why`` instead when there are none."""
    out: dict[str, Any] = {"templates": list(templates)}
    if not acc:
        return {**out, "why": "no fault-free test frame of the held-out road templates"}
    pairs = (("holdout", "learned"), ("holdout", "sgm"))
    return {**out, **_finite(evaluate(_stack(acc), np.concatenate(sequences), n_boot, pairs=pairs))}


def _sha(model: Path) -> str:
    from traffictwin.io.shards import sha256_file

    p = Path(model)
    return sha256_file(p / "model.ckpt" if p.is_dir() else p)


def main() -> None:
    p = params()
    threads = get(p, "evaluation.num_threads", int, min=0)
    n_boot = get(p, "evaluation.stereo.n_boot", int, min=1)
    if n_boot < 10:
        raise ConfigError(f"params.yaml: 'evaluation.stereo.n_boot' must be >= 10, got {n_boot}")
    thresholds = for_problem(p, "stereo")
    with stage_timer(STAGE) as record:
        metrics = run(
            thresholds=thresholds,
            num_threads=threads,
            n_boot=n_boot,
            record=record,
            holdout_model=STEREO_HOLDOUT_MODEL,
        )
        write_json_atomic(metrics_file("stereo"), metrics)


if __name__ == "__main__":
    run_stage(main, STAGE)
