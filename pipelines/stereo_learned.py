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
  differences holdout − learned and holdout − SGM;
- ``reports/figures/stereo_learned_example.png``: left | exact | SGM | learned | error for test frames.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from traffictwin.config import ConfigError, get
from traffictwin.io.atomic import save_figure, write_json_atomic
from traffictwin.io.shards import (
    Dataset,
    DatasetError,
    DatasetWriter,
    shard_name,
    write_npz_deterministic,
)
from traffictwin.risk.dataset import load_stereo_shard
from traffictwin.stereo.metrics import (
    CRITICAL_M,
    RANGE_EDGES_M,
    depth_error_counts,
    histogram_quantile,
    object_mask,
    range_bin_names,
)
from traffictwin.stereo.targets import stereo_targets

from ._common import params, run_stage, setup_logging, stage_timer
from ._paths import (
    DISPARITY,
    RISK_DATA,
    STEREO_HOLDOUT_MODEL,
    STEREO_LEARNED,
    STEREO_MODEL,
    figure_file,
    metrics_file,
)

STAGE = "stereo_learned"
SOURCES = ("sgm", "learned")
MASKS = ("common", "own")
SUM_KEYS = ("n_gt", "n", "abs", "bad1", "bad2")


def frame_sums(
    disp: dict[str, np.ndarray], gt: np.ndarray, fx_b: float, obj: np.ndarray
) -> dict[str, dict[str, Any]]:
    """Per frame (N first), per ``<source>/<mask>``: pixel counts ``n_gt`` (GT pixels), ``n``
    (evaluated), ``abs`` (sum |d - d_gt| px), ``bad1``, ``bad2`` and the relative-range-error
    histograms ``bands`` (N, 3, E) on :data:`RANGE_EDGES_M` and ``crit`` (N, E) on the object
    pixels ``obj`` at :data:`CRITICAL_M` (:func:`depth_error_counts`)."""
    has = gt > 0
    both = has & np.logical_and.reduce([d >= 0 for d in disp.values()])
    out: dict[str, dict[str, Any]] = {}
    n = len(gt)
    for src, d in disp.items():
        for mask in MASKS:
            m = both if mask == "common" else has & (d >= 0)
            err = np.where(m, np.abs(d - gt), 0.0)
            dm = np.where(m, d, -1.0)  # pixels outside the mask: "no estimate"
            bands = [depth_error_counts(dm[i], gt[i], fx_b, RANGE_EDGES_M) for i in range(n)]
            crit = [
                depth_error_counts(dm[i][obj[i]], gt[i][obj[i]], fx_b, CRITICAL_M) for i in range(n)
            ]
            out[f"{src}/{mask}"] = {
                "n_gt": has.sum((1, 2)).astype(np.int64),
                "n": m.sum((1, 2)).astype(np.int64),
                "abs": err.sum((1, 2), dtype=np.float64),
                "bad1": ((err > 1.0) & m).sum((1, 2)).astype(np.int64),
                "bad2": ((err > 2.0) & m).sum((1, 2)).astype(np.int64),
                "bands": np.stack([b["hist"] for b in bands]),
                "crit": np.stack([c["hist"][0] for c in crit]),
            }
    return out


def _stats(s: dict[str, np.ndarray], w: np.ndarray) -> dict[str, float]:
    """The metrics of per-sequence sums ``s`` weighted by ``w`` (resample counts per sequence)."""
    n = float(w @ s["n"])
    out = {
        "epe": float(w @ s["abs"]) / n if n else float("nan"),
        "bad1": float(w @ s["bad1"]) / n if n else float("nan"),
        "bad2": float(w @ s["bad2"]) / n if n else float("nan"),
        "density": n / float(w @ s["n_gt"]) if float(w @ s["n_gt"]) else float("nan"),
    }
    crit = np.tensordot(w, s["crit"], 1)
    out["crit_obj_relerr_median"] = histogram_quantile(crit, 0.5)
    out["crit_obj_relerr_p90"] = histogram_quantile(crit, 0.9)
    bands = np.tensordot(w, s["bands"], 1)
    for b, name in enumerate(range_bin_names(RANGE_EDGES_M)):
        out[f"{name}_relerr_median"] = histogram_quantile(bands[b], 0.5)
        out[f"{name}_relerr_p90"] = histogram_quantile(bands[b], 0.9)
    return out


def _resample_weights(g: int, n_boot: int, seed: int) -> np.ndarray:
    """(n_boot, g) how often each sequence is drawn in each resample: the resamples
    :func:`traffictwin.stats.statistic_ci` draws for ``g`` clusters from ``seed``."""
    rng = np.random.default_rng(seed)
    return np.stack([np.bincount(rng.integers(0, g, size=g), minlength=g) for _ in range(n_boot)])


def _interval(est: float, boot: np.ndarray, level: float = 0.95) -> tuple[float, float, float]:
    """``(estimate, lo, hi)``: the percentile interval of the finite resample values (NaN without
    any), as :func:`traffictwin.stats.statistic_ci` computes it."""
    boot = boot[np.isfinite(boot)]
    if boot.size == 0:
        return est, float("nan"), float("nan")
    a = (1.0 - level) / 2.0
    lo, hi = np.quantile(boot, [a, 1.0 - a])
    return est, float(lo), float(hi)


def evaluate(
    sums: dict[str, dict[str, np.ndarray]],
    sequences: np.ndarray,
    n_boot: int,
    seed: int = 0,
    pairs: tuple[tuple[str, str], ...] = (("learned", "sgm"),),
) -> dict[str, float]:
    """``<source>/<mask>/<metric>`` with ``_lo`` / ``_hi`` (sequence-bootstrap 95 % interval) and,
    for each ``(a, b)`` of ``pairs``, the paired ``diff_<a>_minus_<b>/<mask>/{epe,
    crit_obj_relerr_median}``; ``sums`` per frame (:func:`frame_sums`), ``sequences`` the frame's
    sequence (the bootstrap cluster). Every metric and difference reads the same resamples, each
    computed once (:func:`_stats` of all metrics per resample)."""
    codes, inv = np.unique(sequences, return_inverse=True)
    g = len(codes)
    per_seq = {  # frames summed per sequence: a resample weights the sequences by their counts
        k: {f: np.stack([v[f][inv == j].sum(0) for j in range(g)]) for f in v}
        for k, v in sums.items()
    }
    weights = _resample_weights(g, n_boot, seed).astype(np.float64)
    full = {k: _stats(s, np.ones(g)) for k, s in per_seq.items()}
    boot = {  # key -> metric -> (n_boot,) values
        k: {m: np.array(v) for m, v in _columns([_stats(s, w) for w in weights]).items()}
        for k, s in per_seq.items()
    }
    out: dict[str, float] = {"test/frames": int(len(sequences)), "test/sequences": g}
    for key in per_seq:
        for metric, est in full[key].items():
            _, lo, hi = _interval(est, boot[key][metric])
            out[f"{key}/{metric}"] = est
            out[f"{key}/{metric}_lo"], out[f"{key}/{metric}_hi"] = lo, hi
    for (first, second), mask in ((p, m) for p in pairs for m in MASKS):
        a, b = f"{first}/{mask}", f"{second}/{mask}"
        for metric in ("epe", "crit_obj_relerr_median"):
            key = f"diff_{first}_minus_{second}/{mask}/{metric}"
            out[key], out[key + "_lo"], out[key + "_hi"] = _interval(
                full[a][metric] - full[b][metric], boot[a][metric] - boot[b][metric]
            )
    return out


def _columns(rows: list[dict[str, float]]) -> dict[str, list[float]]:
    """A list of equal-keyed dicts as one list per key."""
    return {k: [r[k] for r in rows] for k in rows[0]}


def check_disparity(risk: Dataset, disparity: Path) -> Dataset:
    """data/disparity, checked to be made from ``risk`` (the SGM source of the comparison)."""
    if not (Path(disparity) / "manifest.json").exists():
        raise DatasetError(f"{disparity}: no manifest.json (run `dvc repro disparity` first)")
    disp = Dataset(disparity, kind="disparity", verify=False)
    src = disp.params.get("source")
    if src != risk.manifest_hash():
        raise DatasetError(
            f"{Path(disparity) / 'manifest.json'}: made from another data/risk (source {src}, "
            f"data/risk is {risk.manifest_hash()}): run the disparity stage first"
        )
    return disp


def run(
    model: Path = STEREO_MODEL,
    src: Path = RISK_DATA,
    disparity: Path = DISPARITY,
    out: Path = STEREO_LEARNED,
    *,
    num_threads: int = 0,
    n_boot: int = 1000,
    batch_size: int = 8,
    figure: Path | None = None,
    record: dict | None = None,
    holdout_model: Path | None = None,
) -> dict[str, Any]:
    """The network on every pair of ``src`` into ``out``; returns the test metrics. Nothing is
    written when an input is missing or inconsistent. ``holdout_model``: the network trained
    without some road templates (its meta's ``holdout_templates``), scored with the full one and
    SGM on those templates' fault-free test frames (``generalisation``)."""
    from traffictwin.risk.stereo_training import load_stereo_model, predict
    from traffictwin.threads import pin_threads

    log = setup_logging()
    if not (Path(src) / "manifest.json").exists():
        raise DatasetError(f"{src}: no manifest.json (run `dvc repro generate_risk` first)")
    net = load_stereo_model(model)
    held_net = load_stereo_model(holdout_model) if holdout_model is not None else None
    held = [str(t) for t in (held_net.meta.get("holdout_templates") or [])] if held_net else []  # type: ignore[attr-defined]
    if held_net is not None and not held:
        raise DatasetError(f"{holdout_model}: model_meta.json names no held-out road templates")
    ds = Dataset(src, kind="risk")  # verifies every shard's SHA-256
    sgm = check_disparity(ds, disparity)
    cam = ds.manifest.get("camera") or {}
    if not {"fx", "baseline", "cy", "fy", "mount_height"} <= set(cam):
        raise DatasetError(
            f"{Path(src) / 'manifest.json'}: 'camera' lacks fx/baseline/cy/fy/mount_height"
        )
    fx_b = float(cam["fx"]) * float(cam["baseline"])
    thr = float(net.meta["spread_threshold_px"])  # type: ignore[attr-defined]
    pin_threads(num_threads)
    frames = ds.table("frames.csv")
    writer = DatasetWriter(
        out,
        "stereo_learned",
        {"source": ds.manifest_hash(), "model_sha256": _sha(model), "spread_threshold_px": thr},
        ds.manifest.get("seed", 0),
    )
    seconds, n_frames = 0.0, 0
    acc: list[dict[str, dict[str, Any]]] = []
    seqs: list[np.ndarray] = []
    keep: list[tuple[int, np.ndarray]] = []
    gen_acc: list[dict[str, dict[str, Any]]] = []  # the held-out templates' test frames
    gen_seqs: list[np.ndarray] = []
    for i, info in enumerate(ds.shards):
        sh = load_stereo_shard(ds, i, ("left", "right", "disp_gt"))
        d_in = sgm.load_shard(i)["disp_sgm"] if net.spec.base == "sgm" else None
        t0 = time.perf_counter()
        disp, spread = predict(net, sh["left"], sh["right"], batch_size, sgm=d_in)
        seconds += time.perf_counter() - t0
        n_frames += len(disp)
        disp = np.where(spread <= thr, disp, -1.0).astype(np.float32)
        digest = write_npz_deterministic(
            Path(out) / shard_name(i), {"disp_learned": disp, "disp_learned_spread": spread}
        )
        writer.record_shard(i, shard_name(i), digest, len(disp), info.get("split"))
        rows = frames[frames.shard == i].sort_values("idx")
        sel = ((rows.split == "test") & (rows.fault == "none")).to_numpy()
        if sel.any():
            d_sgm = sgm.load_shard(i)["disp_sgm"][sel]
            gt = sh["disp_gt"][sel]
            with np.errstate(divide="ignore"):
                depth = np.where(gt > 0, fx_b / np.maximum(gt, 1e-12), np.inf)
            obj = object_mask(depth, float(cam["cy"]), float(cam["fy"]), float(cam["mount_height"]))
            acc.append(frame_sums({"sgm": d_sgm, "learned": disp[sel]}, gt, fx_b, obj))
            seqs.append(rows.scenario.to_numpy()[sel])
            keep.append((i, np.flatnonzero(sel)))
            unseen = rows.template.astype(str).isin(held).to_numpy()[sel] if held else None
            if unseen is not None and unseen.any():
                d_h, spread_h = predict(
                    held_net,
                    sh["left"][sel][unseen],
                    sh["right"][sel][unseen],
                    batch_size,
                    sgm=d_sgm[unseen] if held_net.spec.base == "sgm" else None,  # type: ignore[union-attr]
                )
                thr_h = float(held_net.meta["spread_threshold_px"])  # type: ignore[union-attr]
                d_h = np.where(spread_h <= thr_h, d_h, -1.0).astype(np.float32)
                gen_acc.append(
                    frame_sums(
                        {"sgm": d_sgm[unseen], "learned": disp[sel][unseen], "holdout": d_h},
                        gt[unseen],
                        fx_b,
                        obj[unseen],
                    )
                )
                gen_seqs.append(rows.scenario.to_numpy()[sel][unseen])
    if not acc:
        raise DatasetError(f"{src}: no fault-free test frames to evaluate on")
    metrics: dict[str, Any] = _finite(evaluate(_stack(acc), np.concatenate(seqs), n_boot))
    metrics["learned/spread_threshold_px"] = thr
    metrics["targets"] = stereo_targets(metrics)
    if held_net is not None:
        metrics["generalisation"] = generalisation(held, gen_acc, gen_seqs, n_boot)
    ms = 1000.0 * seconds / max(n_frames, 1)
    if record is not None:  # timings vary between identical runs: run record only
        record["ms_per_frame"] = round(ms, 3)
        record["torch_threads"] = num_threads
    writer.finalize(extra={"source_manifest": ds.manifest_hash(), "metrics": metrics})
    if figure is not None:
        _figure(ds, sgm, Dataset(out, kind="stereo_learned", verify=False), keep, figure)
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


def _figure(risk: Dataset, sgm: Dataset, learned: Dataset, keep, path: Path, rows: int = 3) -> None:
    """A few evenly spaced fault-free test frames (:func:`traffictwin.stereo.figures.example_figure`)."""
    from traffictwin.stereo.figures import example_figure

    picks = [(i, int(k)) for i, ks in keep for k in ks]
    picks = [picks[j] for j in np.unique(np.linspace(0, len(picks) - 1, rows).round().astype(int))]
    parts: dict[str, list[np.ndarray]] = {"left": [], "gt": [], "sgm": [], "learned": []}
    for i, k in picks:
        sh = risk.load_shard(i)
        parts["left"].append(sh["left"][k])
        parts["gt"].append(sh["disp_gt"][k])
        parts["sgm"].append(sgm.load_shard(i)["disp_sgm"][k])
        parts["learned"].append(learned.load_shard(i)["disp_learned"][k])
    a = {k: np.stack(v) for k, v in parts.items()}
    vmax = float(max(np.percentile(a["gt"][a["gt"] > 0], 99), 1.0)) if (a["gt"] > 0).any() else 1.0
    save_figure(example_figure(a["left"], a["gt"], a["sgm"], a["learned"], vmax), path)


def main() -> None:
    p = params()
    threads = get(p, "evaluation.num_threads", int, min=0)
    n_boot = get(p, "evaluation.stereo.n_boot", int, min=1)
    if n_boot < 10:
        raise ConfigError(f"params.yaml: 'evaluation.stereo.n_boot' must be >= 10, got {n_boot}")
    with stage_timer(STAGE) as record:
        metrics = run(
            num_threads=threads,
            n_boot=n_boot,
            figure=figure_file("stereo_learned_example"),
            record=record,
            holdout_model=STEREO_HOLDOUT_MODEL,
        )
        write_json_atomic(metrics_file("stereo"), metrics)


if __name__ == "__main__":
    run_stage(main, STAGE)
