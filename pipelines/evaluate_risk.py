"""Stage `evaluate_risk`: every risk network variant and the baselines on the same test frames.

Reads ``evaluation.risk.*``, ``risk_model.label``, ``risk_model.variants`` (names), the data
(``data/risk``, ``data/disparity``, ``data/orb/orb.csv``) and ``models/risk/<variant>/``.
Writes ``reports/metrics/risk.json`` (test MSE/MAE, THW errors in s, Table-1 confusion matrix,
accuracy, balanced accuracy, F1, ROC-AUC at each THW threshold, baselines, the paper-vs-camera_fov
region comparison), ``reports/plots/risk_predictions.csv`` (per-frame predictions),
``reports/plots/risk_confusion.csv`` (actual/predicted class per test frame of the main variant,
for the ``dvc plots`` confusion template), and the figures ``reports/figures/risk_*.png``.
Test metrics are also logged into each variant's MLflow training run when it is in the store.
"""

from __future__ import annotations

import logging

import numpy as np
import pandas as pd

from traffictwin.config import ConfigError, get
from traffictwin.io.atomic import atomic_path, write_json_atomic
from traffictwin.risk import figures as risk_figs
from traffictwin.risk.baselines import GeometricParams
from traffictwin.risk.evaluation import PAPER, confusion_labels, evaluate_suite, risk_threshold
from traffictwin.risk.model_io import load_risk_model
from traffictwin.risk.training import LABELS, RiskSource

from ._common import ROOT, params, run_stage, setup_logging, stage_timer

METRICS = ROOT / "reports" / "metrics" / "risk.json"
PLOTS = ROOT / "reports" / "plots"
FIGS = ROOT / "reports" / "figures"


def _write_csv(df: pd.DataFrame, path) -> None:
    with atomic_path(path, suffix=".csv") as tmp:
        df.to_csv(tmp, index=False, float_format="%.6g", lineterminator="\n")


def _log_to_mlflow(models: dict, metrics: dict, log: logging.Logger) -> None:
    """Add test metrics to each variant's training run (skipped when the run is not in this store)."""
    try:
        from mlflow.tracking import MlflowClient

        from traffictwin.mlops import tracking

        client = MlflowClient(tracking_uri=tracking.tracking_uri())
        for v, m in models.items():
            rid = m.meta.get("mlflow_run_id")
            if not rid:
                continue
            e = metrics["models"][v]
            vals = {
                k: e[k] for k in ("test/mse", "test/mae", "test/thw_mae_s") if e.get(k) is not None
            }
            at = e.get(f"at_{metrics['thresholds_s'][0]:g}s", {})
            for k in ("accuracy", "balanced_accuracy", "f1", "roc_auc"):
                if at.get(k) is not None:
                    vals[f"test/{k}"] = at[k]
            try:
                for k, val in vals.items():
                    client.log_metric(rid, k, float(val))
            except Exception as exc:  # run from another store / deleted: not an error of this stage
                log.warning(
                    "evaluate_risk: could not log test metrics to MLflow run %s (%s)", rid, exc
                )
    except Exception as exc:
        log.warning("evaluate_risk: MLflow unavailable (%s); metrics only in %s", exc, METRICS)


def main() -> None:
    log = setup_logging()
    p = params()
    k = "evaluation.risk"
    thresholds = [float(t) for t in get(p, f"{k}.thresholds_s", list)]
    if not thresholds or any(t <= 0 for t in thresholds):
        raise ConfigError(
            f"params.yaml: '{k}.thresholds_s' must be a non-empty list of positive seconds, got {thresholds}"
        )
    thw_cap = get(p, f"{k}.thw_cap_s", float, min=0.1)
    batch = get(p, f"{k}.batch_size", int, min=1)
    defined = get(p, "risk_model.variants", dict)
    variants = list(get(p, "risk_model.run_variants", list))
    unknown = [v for v in variants if v not in defined]
    if not variants or unknown:
        raise ConfigError(
            f"params.yaml: 'risk_model.run_variants' must name variants of 'risk_model.variants' {sorted(defined)}, got {variants}"
        )
    main_v = get(p, f"{k}.main_variant", str, choices=variants)
    primary = get(p, "risk_model.label", str, choices=LABELS)
    g = f"{k}.geometric"
    try:
        geo = GeometricParams(
            corridor_half_width=get(p, f"{g}.corridor_half_width", float),
            min_height=get(p, f"{g}.min_height", float),
            max_height=get(p, f"{g}.max_height", float),
            min_pixels=get(p, f"{g}.min_pixels", int),
            max_range=get(p, f"{g}.max_range", float),
            subject_length=get(p, "risk_data.metric.subject_length", float),
            subject_width=get(p, "risk_data.metric.subject_width", float),
        )
    except ValueError as exc:
        if isinstance(exc, ConfigError):
            raise
        raise ConfigError(f"params.yaml: '{g}': {exc}") from None

    with stage_timer("evaluate_risk"):
        orb = ROOT / "data" / "orb" / "orb.csv" if get(p, "risk_model.orb_filter", bool) else None
        source = RiskSource(ROOT / "data" / "risk", ROOT / "data" / "disparity", orb)
        models = {v: load_risk_model(ROOT / "models" / "risk" / v) for v in variants}
        metrics, pred = evaluate_suite(
            source,
            models,
            primary_label=primary,
            thresholds_s=thresholds,
            thw_cap=thw_cap,
            geometric=geo,
            batch_size=batch,
        )
        t0 = thresholds[0]
        main_label = metrics["models"][main_v]["label"]
        y, yhat = pred[main_label].to_numpy(), pred[f"pred_{main_v}"].to_numpy()

        # figures
        histories = {v: pd.read_csv(ROOT / "models" / "risk" / v / "history.csv") for v in variants}
        risk_figs.plot_training_curves(
            histories, FIGS / "risk_training_curves.png", paper_test_mse=PAPER["test/mse"]
        )
        risk_figs.plot_scatter(
            y,
            {main_v: yhat, "geometric": pred["pred_geometric"].to_numpy()},
            FIGS / "risk_scatter.png",
            risk_threshold(t0),
            title=f"test frames, label {main_label}",
        )
        cm = metrics["models"][main_v][f"at_{t0:g}s"]["confusion"]
        risk_figs.plot_confusion(
            cm,
            FIGS / "risk_confusion.png",
            title=f"{main_v}: THW {t0:g} s (accuracy {metrics['models'][main_v][f'at_{t0:g}s']['accuracy']:.1%})",
        )
        # Fig. 7: a well predicted high-risk frame and the worst prediction
        err = np.abs(yhat - y)
        crit = np.flatnonzero(y > risk_threshold(t0))
        good = int(crit[np.argmin(err[crit])]) if len(crit) else int(np.argmin(err))
        bad = (
            int(np.argsort(err)[-2])
            if int(np.argmax(err)) == good and len(err) > 1
            else int(np.argmax(err))
        )
        wanted = {str(pred.at[i, "frame_id"]): i for i in (good, bad)}
        sel = source.frames[source.frames["frame_id"].astype(str).isin(wanted)]
        raw = {}
        for rows, arr in source.iter_arrays(sel, ["left", "disp_sgm"]):
            for j, fid in enumerate(rows["frame_id"].astype(str)):
                raw[fid] = (arr["left"][j], arr["disp_sgm"][j])
        examples = [
            {
                "left": raw[f][0],
                "disp": raw[f][1],
                "true": float(y[i]),
                "pred": float(yhat[i]),
                "title": ("well predicted" if i == good else "worst prediction") + f" (frame {f})",
            }
            for f, i in sorted(wanted.items(), key=lambda kv: kv[1] != good)
        ]
        risk_figs.plot_examples(examples, FIGS / "risk_examples.png")

        # plot data + metrics
        actual, predicted = confusion_labels(y, yhat, t0)
        _write_csv(
            pd.DataFrame({"frame_id": pred["frame_id"], "actual": actual, "predicted": predicted}),
            PLOTS / "risk_confusion.csv",
        )
        _write_csv(pred, PLOTS / "risk_predictions.csv")
        metrics["main_variant"] = main_v
        write_json_atomic(METRICS, metrics)
        _log_to_mlflow(models, metrics, log)
        m = metrics["models"][main_v]
        log.info(
            "evaluate_risk: %s test MSE %.5f (paper %.5f), accuracy %.2f %% (paper %.2f %%) on %d frames",
            main_v,
            m["test/mse"],
            PAPER["test/mse"],
            100 * m[f"at_{t0:g}s"]["accuracy"],
            100 * PAPER["accuracy"],
            m["test/n"],
        )


if __name__ == "__main__":
    run_stage(main, "evaluate_risk")
