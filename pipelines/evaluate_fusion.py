"""Stage `evaluate_fusion`: every fusion method on every configuration's test set (paper V-A, Figs. 4–7).

Reads ``data/prealigned/<cfg>`` (test split: inputs, labels and the noise drawn, the same draws
for every method), ``data/fusion`` (raw map 2 for the `registered` baseline and Fig. 4) and
``models/fusion/<cfg>/model.ckpt``. Writes:

- ``reports/metrics/fusion.json`` — aggregated metrics (DVC metrics): ``test.<cfg>.<method>.<metric>``,
  ``cross.dnn-<net>.<cfg>.<metric>``, ``bins.{translation,rotation}.<method>.<bin>.<metric>``;
- ``reports/fusion_eval_samples.csv`` — one row per (test config, method, pair);
- ``reports/plots/fusion_kld.csv``, ``fusion_scores.csv``, ``fusion_pose_bins.csv`` — DVC plot data;
- ``reports/figures/fusion_{kld_boxplot,scores_occupied,scores_free,qualitative}.png``;
- ``reports/fusion_findings.md`` — findings computed from fusion.json;
and logs the numbers to each network's MLflow run (``mlflow_run_id`` of its model_meta.json).
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from traffictwin.config import ConfigError, get
from traffictwin.grid import GridSpec
from traffictwin.io.atomic import atomic_path, write_json_atomic, write_text_atomic
from traffictwin.io.shards import Dataset, DatasetError

from ._common import ROOT, params, run_stage, setup_logging, stage_timer

STAGE = "evaluate_fusion"
METRICS = Path("reports/metrics/fusion.json")
SAMPLES = Path("reports/fusion_eval_samples.csv")
PLOT_KLD = Path("reports/plots/fusion_kld.csv")
PLOT_SCORES = Path("reports/plots/fusion_scores.csv")
PLOT_BINS = Path("reports/plots/fusion_pose_bins.csv")
FIG_BOX = Path("reports/figures/fusion_kld_boxplot.png")
FIG_OCC = Path("reports/figures/fusion_scores_occupied.png")
FIG_FREE = Path("reports/figures/fusion_scores_free.png")
FIG_QUAL = Path("reports/figures/fusion_qualitative.png")
FINDINGS = Path("reports/fusion_findings.md")

BASELINES = ("ego", "naive", "naive-yager", "naive-cautious")
SUMMARY_KEYS = (
    "n",
    "kld_fo_mean",
    "kld_fo_median",
    "kld_fo_q25",
    "kld_fo_q75",
    "kld_fou_mean",
    "kld_fou_median",
    "precision_occ",
    "recall_occ",
    "dice_occ",
    "precision_free",
    "recall_free",
    "dice_free",
    "dice_occ_sample_mean",
    "dice_free_sample_mean",
    "u_mean",
    "u_mean_known",
)
CROSS_KEYS = (
    "n",
    "kld_fo_mean",
    "kld_fou_mean",
    "dice_occ",
    "dice_free",
    "precision_occ",
    "recall_occ",
)
BIN_KEYS = ("n", "kld_fo_mean", "kld_fo_median", "dice_occ", "dice_free")

log = logging.getLogger("traffictwin.evaluate_fusion")


# -- settings ------------------------------------------------------------------------------------
def settings(cfg: Any) -> dict[str, Any]:
    """Checked evaluation settings from params.yaml (``evaluation.fusion`` + grid + configurations)."""
    from traffictwin.fusion.registration import RegistrationParams

    k = "evaluation.fusion"
    all_cfgs = get(cfg, "configurations", dict)
    configs = get(cfg, f"{k}.configs", list)
    for c in configs:
        if c not in all_cfgs:
            raise ConfigError(
                f"params.yaml: '{k}.configs' names '{c}', not one of configurations {sorted(all_cfgs)}"
            )
    if not configs:
        raise ConfigError(f"params.yaml: '{k}.configs' must list at least one configuration")
    opt_int = lambda key: get(cfg, f"{k}.{key}", (int, type(None)), min=None)  # noqa: E731
    s = {
        "configs": [str(c) for c in configs],
        "noise": {
            c: (
                get(cfg, f"configurations.{c}.r", float, min=0.0),
                get(cfg, f"configurations.{c}.alpha", float, min=0.0),
            )
            for c in configs
        },
        "split": get(cfg, f"{k}.split", str, choices=("train", "val", "test")),
        "max_pairs": opt_int("max_pairs"),
        "registered_max_pairs": opt_int("registered_max_pairs"),
        "cross_max_pairs": opt_int("cross_max_pairs"),
        "batch_size": get(cfg, f"{k}.batch_size", int, min=1),
        "device": get(cfg, f"{k}.device", str),
        "kld_eps": get(cfg, f"{k}.kld_eps", float, min=0.0, max=0.1),
        "auroc_bins": get(cfg, f"{k}.auroc_bins", int, min=2),
        "trans_bins_m": get(cfg, f"{k}.trans_bins_m", list),
        "rot_bins_deg": get(cfg, f"{k}.rot_bins_deg", list),
        "success_trans_m": get(cfg, f"{k}.success_trans_m", float, min=0.0),
        "success_rot_deg": get(cfg, f"{k}.success_rot_deg", float, min=0.0),
        "qualitative_fraction": get(cfg, f"{k}.qualitative_fraction", float, min=0.0, max=1.0),
        "qualitative_pair": get(cfg, f"{k}.qualitative_pair", int, min=0),
        "grid": GridSpec(
            get(cfg, "grid.rows", int, min=1),
            get(cfg, "grid.cols", int, min=1),
            get(cfg, "grid.cell", float, min=1e-6),
        ),
        "profile": get(cfg, "profile.name", str),
    }
    for key in ("max_pairs", "registered_max_pairs", "cross_max_pairs"):
        if s[key] is not None and s[key] < 1:
            raise ConfigError(f"params.yaml: '{k}.{key}' must be null or >= 1, got {s[key]}")
    reg = get(cfg, f"{k}.registration", dict)
    try:
        s["registration"] = RegistrationParams(**reg)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"params.yaml: '{k}.registration': {exc}") from None
    return s


# -- data ----------------------------------------------------------------------------------------
def evenly_spaced(n: int, k: int | None) -> np.ndarray:
    """``k`` indices spread evenly over ``range(n)`` (all when ``k`` is None or ≥ n)."""
    if k is None or k >= n:
        return np.arange(n)
    return np.unique(np.round(np.linspace(0, n - 1, k)).astype(np.int64))


def load_test_sets(
    configs: list[str], split: str, max_pairs: int | None
) -> tuple[dict[str, dict[str, np.ndarray]], np.ndarray]:
    """Each configuration's ``split`` arrays restricted to the same pair ids: ``max_pairs`` of the
    pair ids common to all configurations, spread evenly over them (so over scenarios/templates)."""
    raw = {}
    for c in configs:
        ds = Dataset(ROOT / "data" / "prealigned" / c, kind="prealigned")
        raw[c] = ds.load_all(split)
        for key in ("inputs", "label", "noise", "rel_pose_true", "rel_pose_noisy", "pair_id"):
            if key not in raw[c]:
                raise DatasetError(f"{ds.root}: array '{key}' missing in split '{split}'")
    common = np.array(
        sorted(set.intersection(*(set(raw[c]["pair_id"].tolist()) for c in configs))),
        dtype=np.int64,
    )
    if not len(common):
        raise DatasetError(
            f"data/prealigned/{{{','.join(configs)}}}: no pair id common to all '{split}' splits"
        )
    chosen = common[evenly_spaced(len(common), max_pairs)]
    out = {}
    for c in configs:
        pid = raw[c]["pair_id"]
        index = {
            int(pid[i]): i for i in range(len(pid) - 1, -1, -1)
        }  # the first draw of each pair wins
        idx = np.array([index[int(p)] for p in chosen], dtype=np.int64)
        out[c] = {k: v[idx] for k, v in raw[c].items()}
    return out, chosen


def load_raw_pairs(pair_ids: np.ndarray, split: str) -> dict[str, np.ndarray]:
    """``map1``, ``map2``, ``label``, ``pose1``, ``pose2`` of data/fusion for ``pair_ids`` (in that order)."""
    ds = Dataset(ROOT / "data" / "fusion", kind="fusion")
    keys = ("map1", "map2", "label", "pose1", "pose2", "pair_id")
    arrays = ds.load_all(split, keys=keys)
    index = {int(p): i for i, p in enumerate(arrays["pair_id"])}
    missing = [int(p) for p in pair_ids if int(p) not in index]
    if missing:
        raise DatasetError(
            f"{ds.root}: pair ids {missing[:5]} of data/prealigned missing in split '{split}' (stale data?)"
        )
    idx = np.array([index[int(p)] for p in pair_ids], dtype=np.int64)
    return {k: arrays[k][idx] for k in keys}


# -- evaluation ----------------------------------------------------------------------------------
def _bins(frame: pd.DataFrame, s: dict[str, Any]) -> tuple[dict[str, Any], pd.DataFrame]:
    from traffictwin.fusion.metrics import aggregate, pose_error_bins

    noise = frame[["noise_dx", "noise_dy", "noise_dyaw"]].to_numpy()
    tb, rb, tl, rl = pose_error_bins(noise, s["trans_bins_m"], s["rot_bins_deg"])
    frame = frame.assign(trans_bin=[tl[i] for i in tb], rot_bin=[rl[i] for i in rb])
    out: dict[str, Any] = {"translation": {}, "rotation": {}}
    rows = []
    for axis, col, labels in (("translation", "trans_bin", tl), ("rotation", "rot_bin", rl)):
        for meth, g in frame.groupby("method", sort=False):
            out[axis][meth] = {}
            for lab in labels:
                sub = g[g[col] == lab]
                if len(sub):
                    agg = aggregate({k: sub[k].to_numpy() for k in sub.columns})
                    out[axis][meth][lab] = {k: agg[k] for k in BIN_KEYS if k in agg}
                    rows.append({"axis": axis, "bin": lab, "method": meth, **out[axis][meth][lab]})
    return out, pd.DataFrame(rows)


def evaluate(s: dict[str, Any]) -> dict[str, Any]:
    """Run every method; returns the metrics dict and the frames/arrays the outputs need."""
    from traffictwin.fusion.methods import (
        EvalSettings,
        evaluate_prealigned,
        evaluate_predictions,
        evaluate_registered,
    )
    from traffictwin.fusion.metrics import aggregate
    from traffictwin.fusion.model_io import load_fusion_model, predict_masses

    configs, grid = s["configs"], s["grid"]
    es = EvalSettings(
        s["batch_size"], s["kld_eps"], s["auroc_bins"], s["success_trans_m"], s["success_rot_deg"]
    )
    data, pair_ids = load_test_sets(configs, s["split"], s["max_pairs"])
    n = len(pair_ids)
    reg_idx = evenly_spaced(n, s["registered_max_pairs"])
    cross_idx = evenly_spaced(n, s["cross_max_pairs"])
    raw = load_raw_pairs(pair_ids, s["split"])
    log.info(
        "evaluating %d pairs per configuration (%d registered, %d cross) on %s",
        n,
        len(reg_idx),
        len(cross_idx),
        configs,
    )

    models = {}
    for c in configs:
        path = ROOT / "models" / "fusion" / c / "model.ckpt"
        models[c] = load_fusion_model(path, expected_cfg=c, expected_grid=grid, device=s["device"])

    frames: list[pd.DataFrame] = []
    metrics: dict[str, Any] = {"test": {}, "cross": {f"dnn-{c}": {} for c in configs}}

    def tag(
        frame: pd.DataFrame,
        cfg: str,
        method: str,
        d: dict[str, np.ndarray],
        idx: np.ndarray,
        network: str = "",
    ) -> pd.DataFrame:
        frame = frame.copy()
        nz = d["noise"][idx]
        frame.insert(0, "pair_id", d["pair_id"][idx])
        frame.insert(0, "network", network)
        frame.insert(0, "method", method)
        frame.insert(0, "config", cfg)
        frame["noise_dx"], frame["noise_dy"], frame["noise_dyaw"] = nz[:, 0], nz[:, 1], nz[:, 2]
        frame["trans_err_m"] = np.hypot(nz[:, 0], nz[:, 1])
        frame["rot_err_deg"] = np.degrees(np.abs(nz[:, 2]))
        return frame

    all_idx = np.arange(n)
    for c in configs:
        d = data[c]
        metrics["test"][c] = {}
        for meth in BASELINES:
            f, au = evaluate_prealigned(d["inputs"], d["label"], meth, es)
            frames.append(tag(f, c, meth, d, all_idx))
            metrics["test"][c][meth] = {**_summary(f), "u_auroc": au.value()}
        f, au = evaluate_registered(
            raw["map1"][reg_idx],
            raw["map2"][reg_idx],
            d["rel_pose_noisy"][reg_idx],
            d["rel_pose_true"][reg_idx],
            d["label"][reg_idx],
            grid,
            s["registration"],
            es,
        )
        frames.append(tag(f, c, "registered", d, reg_idx))
        metrics["test"][c]["registered"] = {
            **_summary(f),
            "u_auroc": au.value(),
            "success_rate": float(f["reg_success"].mean()),
            "accepted_rate": float(f["reg_accepted"].mean()),
            "estimate_success_rate": float(
                (
                    (f["est_trans_err_m"] <= s["success_trans_m"])
                    & (f["est_rot_err_deg"] <= s["success_rot_deg"])
                ).mean()
            ),
            "residual_trans_m_median": float(f["reg_trans_err_m"].median()),
            "residual_trans_m_mean": float(f["reg_trans_err_m"].mean()),
            "residual_rot_deg_median": float(f["reg_rot_err_deg"].median()),
            "noisy_trans_m_median": float(f["noisy_trans_err_m"].median()),
            "noisy_rot_deg_median": float(f["noisy_rot_err_deg"].median()),
        }
        for net in configs:
            idx = all_idx if net == c else cross_idx
            inputs, label = d["inputs"][idx], d["label"][idx]
            predict = lambda sl, net=net, inputs=inputs: predict_masses(
                models[net], inputs[sl], s["batch_size"]
            )[0]  # noqa: E731
            f, au = evaluate_predictions(label, predict, es)
            frames.append(tag(f, c, "dnn" if net == c else f"dnn-{net}", d, idx, network=net))
            agg = aggregate({k: f[k].to_numpy() for k in f.columns})
            metrics["cross"][f"dnn-{net}"][c] = {k: agg[k] for k in CROSS_KEYS} | {
                "u_auroc": au.value()
            }
            if net == c:
                metrics["test"][c]["dnn"] = {**_summary(f), "u_auroc": au.value()}
        log.info(
            "config %s: KLD naive %.4f, network %.4f, registered %.4f (success %.0f %%)",
            c,
            metrics["test"][c]["naive"]["kld_fo_mean"],
            metrics["test"][c]["dnn"]["kld_fo_mean"],
            metrics["test"][c]["registered"]["kld_fo_mean"],
            100 * metrics["test"][c]["registered"]["success_rate"],
        )
    samples = pd.concat(frames, ignore_index=True)
    main = samples[~samples["method"].str.startswith("dnn-")]
    metrics["bins"], bins_table = _bins(main, s)
    metrics["runtime_ms_per_pair"] = {
        m: float(g["ms"].mean()) for m, g in main.groupby("method", sort=False)
    }
    metrics["n_pairs"] = {
        "per_config": int(n),
        "registered": int(len(reg_idx)),
        "cross": int(len(cross_idx)),
    }
    return {
        "metrics": metrics,
        "samples": samples,
        "bins": bins_table,
        "data": data,
        "raw": raw,
        "models": models,
    }


def _summary(frame: pd.DataFrame) -> dict[str, float]:
    from traffictwin.fusion.metrics import aggregate

    agg = aggregate({k: frame[k].to_numpy() for k in frame.columns})
    out = {k: agg[k] for k in SUMMARY_KEYS if k in agg}
    out["ms_per_pair"] = float(frame["ms"].mean())
    return out


# -- outputs -------------------------------------------------------------------------------------
def _csv(frame: pd.DataFrame, path: Path) -> None:
    with atomic_path(ROOT / path, suffix=".csv") as tmp:
        frame.to_csv(tmp, index=False, float_format="%.6g", lineterminator="\n")


def _clean(obj: Any) -> Any:
    """JSON-safe: NaN/inf → None (DVC and json both choke on NaN)."""
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        return f if math.isfinite(f) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


def qualitative(res: dict[str, Any], s: dict[str, Any]) -> dict[str, list[np.ndarray]]:
    """Fig. 4 panels: one test pair, map 2 warped with a pose error of fraction·(r, r, α) per configuration."""
    from traffictwin.evidential.dempster import dempster
    from traffictwin.evidential.noise import apply_pose_noise
    from traffictwin.evidential.warp import warp_masses
    from traffictwin.fusion.model_io import predict_masses
    from traffictwin.sim.scene import relative_pose

    i = s["qualitative_pair"]
    if i >= len(res["raw"]["map1"]):
        raise ConfigError(
            f"params.yaml: 'evaluation.fusion.qualitative_pair' = {i} but only {len(res['raw']['map1'])} pairs are evaluated"
        )
    m1, m2 = res["raw"]["map1"][i], res["raw"]["map2"][i]
    pose1, pose2 = res["raw"]["pose1"][i], res["raw"]["pose2"][i]
    k = s["qualitative_fraction"]
    rows: dict[str, list[np.ndarray]] = {"label": [], "naive": [], "network": []}
    for c in s["configs"]:
        r, alpha = s["noise"][c]
        noisy2 = apply_pose_noise(
            pose2, np.array([k * r, k * r, np.radians(k * alpha)])
        )  # as prealign does
        warped = warp_masses(m2, relative_pose(pose1, noisy2), s["grid"])
        inputs = np.concatenate([m1, warped])[None].astype(np.float32)
        rows["label"].append(res["raw"]["label"][i])
        rows["naive"].append(np.asarray(dempster(m1, warped)))
        rows["network"].append(predict_masses(res["models"][c], inputs, 1)[0][0])
    return rows


def write_outputs(res: dict[str, Any], s: dict[str, Any]) -> None:
    from traffictwin.fusion.figures import kld_boxplot, qualitative_grid, scores_plot
    from traffictwin.fusion.findings import fusion_findings

    metrics = _clean(res["metrics"])
    samples: pd.DataFrame = res["samples"]
    configs = s["configs"]
    methods = ["dnn", "naive", "registered", "naive-yager", "naive-cautious", "ego"]
    # plot data
    main = samples[~samples["method"].str.startswith("dnn-")]
    _csv(
        main[["config", "method", "pair_id", "kld_fo", "kld_fou", "trans_err_m", "rot_err_deg"]],
        PLOT_KLD,
    )
    score_rows = []
    for c in configs:
        row: dict[str, Any] = {
            "config": c,
            "noise_r_m": s["noise"][c][0],
            "noise_alpha_deg": s["noise"][c][1],
        }
        for m in methods:
            for key in (
                "precision_occ",
                "recall_occ",
                "dice_occ",
                "precision_free",
                "recall_free",
                "dice_free",
                "kld_fo_mean",
            ):
                row[f"{m}_{key}"] = res["metrics"]["test"][c][m].get(key)
        score_rows.append(row)
    _csv(pd.DataFrame(score_rows), PLOT_SCORES)
    _csv(res["bins"], PLOT_BINS)
    _csv(samples, SAMPLES)
    # figures
    kvals = {
        m: {c: main[(main.method == m) & (main.config == c)]["kld_fo"].to_numpy() for c in configs}
        for m in ("naive", "registered", "dnn")
    }
    kld_boxplot(
        kvals,
        configs,
        ["naive", "registered", "dnn"],
        ROOT / FIG_BOX,
        title=f"KLD per configuration (test set, {metrics['n_pairs']['per_config']} pairs; registered on "
        f"{metrics['n_pairs']['registered']})",
    )
    scores = {m: {c: res["metrics"]["test"][c][m] for c in configs} for m in methods}
    scores_plot(scores, configs, methods, "occ", ROOT / FIG_OCC)
    scores_plot(scores, configs, methods, "free", ROOT / FIG_FREE)
    qualitative_grid(
        qualitative(res, s),
        configs,
        ROOT / FIG_QUAL,
        title=f"pair {int(res['data'][configs[0]]['pair_id'][s['qualitative_pair']])}: pose error = "
        f"{s['qualitative_fraction']:.0%} of (r, r, α); red = m_O, green = m_F, black = unknown",
    )
    write_text_atomic(ROOT / FINDINGS, fusion_findings(metrics))
    write_json_atomic(ROOT / METRICS, metrics)


def log_to_mlflow(metrics: dict[str, Any], s: dict[str, Any]) -> None:
    """Log every number to each network's own MLflow run (``mlflow_run_id`` in model_meta.json)."""
    import time

    from mlflow.entities import Metric, RunTag
    from mlflow.exceptions import MlflowException
    from mlflow.tracking import MlflowClient

    from traffictwin.mlops.tracking import setup

    client = MlflowClient(tracking_uri=setup())
    stamp = int(time.time() * 1000)
    for c in s["configs"]:
        meta_path = ROOT / "models" / "fusion" / c / "model_meta.json"
        meta = json.loads(meta_path.read_text()) if meta_path.exists() else {}
        run_id = meta.get("mlflow_run_id")
        if not run_id:
            log.warning(
                "%s: no mlflow_run_id; fusion evaluation of %s not logged to MLflow", meta_path, c
            )
            continue
        flat: dict[str, float] = {}
        for meth, vals in metrics["test"][c].items():
            prefix = "test" if meth == "dnn" else f"test_{meth}"
            flat.update({f"{prefix}/{k}": v for k, v in vals.items()})
        for other, vals in metrics["cross"][f"dnn-{c}"].items():
            flat.update({f"cross_{other}/{k}": v for k, v in vals.items()})
        flat = {k: float(v) for k, v in flat.items() if v is not None and math.isfinite(float(v))}
        try:
            # log_batch on the training run: same run as mlflow.start_run(run_id=…) but leaves its status alone
            client.log_batch(
                run_id,
                metrics=[Metric(k, v, stamp, 0) for k, v in sorted(flat.items())],
                tags=[RunTag("evaluated_by", STAGE)],
            )
            log.info(
                "logged %d fusion evaluation metrics to MLflow run %s (%s)", len(flat), run_id, c
            )
        except MlflowException as exc:
            log.warning(
                "MLflow run %s of %s not reachable (%s); metrics are in %s", run_id, c, exc, METRICS
            )


def main() -> None:
    setup_logging()
    cfg = params()
    s = settings(cfg)
    with stage_timer(STAGE):
        res = evaluate(s)
        write_outputs(res, s)
        log_to_mlflow(_clean(res["metrics"]), s)


if __name__ == "__main__":
    run_stage(main, "evaluate_fusion")
