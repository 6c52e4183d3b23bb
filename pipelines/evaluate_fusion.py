"""Stage `evaluate_fusion`: every fusion method on every configuration's test set (paper V-A, Figs. 4–7).

Reads ``data/prealigned/<cfg>`` (test split: inputs, labels and the noise drawn, the same draws
for every method), ``data/fusion`` (raw map 2 for the `registered` baseline and Fig. 4) and
``models/fusion/<cfg>/model.ckpt`` for every configuration of ``configurations``. Writes:

- ``reports/metrics/fusion.json`` — aggregated metrics (DVC metrics): ``test.<cfg>.<method>.<metric>``,
  ``cross.dnn-<net>.<cfg>.<metric>``, ``bins.{translation,rotation}.<method>.<bin>.<metric>``;
- ``reports/fusion_eval_samples.csv`` — one row per (test config, method, pair);
- ``reports/plots/fusion_kld.csv``, ``fusion_scores.csv``, ``fusion_pose_bins.csv`` — DVC plot data;
- ``reports/figures/fusion_{kld_boxplot,scores_occupied,scores_free,qualitative}.png``;
- ``reports/fusion_findings.md`` — findings computed from fusion.json;
and logs the numbers to each network's MLflow run (``mlflow_run_id`` of its model_meta.json).
Library: :mod:`traffictwin.fusion.evaluation` (methods: :mod:`traffictwin.fusion.methods`).
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any

import pandas as pd

from traffictwin.fusion.config import fusion_eval_config, grid_config, pose_configurations
from traffictwin.io.atomic import atomic_path, write_json_atomic, write_text_atomic

from ._common import params, run_stage, setup_logging, stage_timer
from ._paths import (
    FUSION_DATA,
    REPORTS,
    figure_file,
    fusion_model_dir,
    metrics_file,
    plot_file,
    prealigned,
)

STAGE = "evaluate_fusion"
METRICS = metrics_file("fusion")
SAMPLES = REPORTS / "fusion_eval_samples.csv"
FINDINGS = REPORTS / "fusion_findings.md"

log = logging.getLogger("traffictwin.evaluate_fusion")


def _csv(frame: pd.DataFrame, path: Path) -> None:
    with atomic_path(path, suffix=".csv") as tmp:
        frame.to_csv(tmp, index=False, float_format="%.6g", lineterminator="\n")


def log_to_mlflow(metrics: dict[str, Any], configs: list[str]) -> None:
    """Log every number to each network's own MLflow run (``mlflow_run_id`` in model_meta.json)."""
    from mlflow.entities import Metric, RunTag
    from mlflow.exceptions import MlflowException
    from mlflow.tracking import MlflowClient

    from traffictwin.fusion.evaluation import mlflow_metrics
    from traffictwin.mlops.tracking import setup

    client = MlflowClient(tracking_uri=setup())
    stamp = int(time.time() * 1000)
    for c in configs:
        meta_path = fusion_model_dir(c) / "model_meta.json"
        meta = json.loads(meta_path.read_text()) if meta_path.exists() else {}
        run_id = meta.get("mlflow_run_id")
        if not run_id:
            log.warning(
                "%s: no mlflow_run_id; fusion evaluation of %s not logged to MLflow", meta_path, c
            )
            continue
        flat = mlflow_metrics(metrics, c)
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
    from traffictwin.fusion import evaluation as ev
    from traffictwin.fusion.figures import save_figure
    from traffictwin.fusion.findings import fusion_findings
    from traffictwin.fusion.model_io import load_fusion_model

    setup_logging()
    cfg = params()
    grid = grid_config(cfg)
    noise = pose_configurations(cfg)
    fc = fusion_eval_config(cfg)
    configs = list(noise)
    with stage_timer(STAGE):
        data, pair_ids = ev.load_test_sets(
            {c: prealigned(c) for c in configs}, fc.split, fc.max_pairs
        )
        raw = ev.load_raw_pairs(FUSION_DATA, pair_ids, fc.split)
        models = {
            c: load_fusion_model(
                fusion_model_dir(c) / "model.ckpt",
                expected_cfg=c,
                expected_grid=grid,
                device=fc.device,
            )
            for c in configs
        }
        res = ev.evaluate(data, raw, models, grid, fc)
        metrics = ev.json_clean(res.metrics)
        for name, frame in ev.plot_tables(res, noise).items():
            _csv(frame, plot_file(name))
        _csv(res.samples, SAMPLES)
        figs = ev.figures(res, noise, grid, fc.qualitative_pair, fc.qualitative_fraction)
        for name, fig in figs.items():
            save_figure(fig, figure_file(name))
        write_text_atomic(FINDINGS, fusion_findings(metrics))
        write_json_atomic(METRICS, metrics)
        log_to_mlflow(metrics, configs)


if __name__ == "__main__":
    run_stage(main, "evaluate_fusion")
