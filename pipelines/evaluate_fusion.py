"""Stage `evaluate_fusion`: every fusion method on every configuration's test set (paper V-A, Figs. 4–7).

Reads ``data/prealigned/<cfg>`` (test split: inputs, labels and the noise drawn, the same draws
for every method), ``data/fusion`` (raw maps for the registration methods and Fig. 4),
``models/fusion/network/model.ckpt`` (row ``dnn``: the one network, at every configuration),
``models/fusion/<variant>/model.ckpt`` for every entry of ``fusion_variants`` (its row
:func:`~traffictwin.fusion.config.variant_row`: ``registered+network``, ``dnn[<loss>]`` at every
configuration, ``dnn[per-config]`` at its own; ``fusion_model.loss.name`` names the default loss,
read only when there are variants) and ``models/registration/learned`` (rows ``learned``,
``learned+network``, ``learned-refined``, ``learned-refined+network``), and the ``val`` split of
``data/prealigned/<cfg>`` / ``data/fusion`` (``evaluation.fusion.validation``). Writes:

- ``reports/metrics/summary_fusion.json`` — the DVC metrics file (:func:`summary`): the one
  network's best-epoch validation and headline test figures, flat ``split/name`` keys as in MLflow;
- ``reports/metrics/fusion.json`` — aggregated metrics (an output, not a DVC metrics file), layout in
  :mod:`traffictwin.fusion.evaluation`: ``test.<cfg>.<row>.<metric>`` (+ ``<metric>_ci``),
  ``validation`` (the registration and refinement settings chosen on validation pairs before the
  test pass: :func:`choose_on_validation`),
  ``diff.<cfg>.<row>.vs_{naive,registered}.<metric>``, ``label.<cfg>``, ``targets``,
  ``cross.dnn-<net>.<cfg>.<metric>``, ``bins.{translation,rotation}.<row>.<bin>.<metric>``;
- ``reports/fusion_eval_samples.csv`` — one row per (test config, method, pair);
- ``reports/plots/fusion_kld.csv``, ``fusion_scores.csv``, ``fusion_pose_bins.csv`` — DVC plot data;
- ``data/figure_inputs/fusion.npz`` — Fig. 4's maps of one pair (label, naive, network per
  configuration) and the figures' metadata: plot_data draws
  ``reports/figures/fusion_{kld_boxplot,scores_occupied,scores_free,qualitative}.png`` from it,
  fusion.json and ``fusion_kld.csv``;
- ``reports/fusion_findings.md`` — findings computed from fusion.json;
- its run record ``reports/timings/evaluate_fusion.json`` (outside DVC) — the wall times
  ``ms_per_pair.<cfg>.<row>``, ``runtime_ms_per_pair.<row>`` and the runtime target;
and logs the network's own numbers to its MLflow run (``run_id`` in its training stage's run record,
``reports/timings/<stage>.json``), with every method's numbers at its configuration as the table
artifact ``evaluation/test_methods.json``.
Bootstrap intervals: ``evaluation.fusion_ci`` (n_boot, seed, level).
Library: :mod:`traffictwin.fusion.evaluation` (methods: :mod:`traffictwin.fusion.methods`).
"""

from __future__ import annotations

import json
import logging
import math
import time
from pathlib import Path
from typing import Any

import pandas as pd

from traffictwin.acceptance import for_problem
from traffictwin.fusion.config import fusion_eval_config, grid_config, pose_configurations
from traffictwin.io.atomic import (
    write_csv_atomic,
    write_json_atomic,
    write_text_atomic,
)
from traffictwin.io.jsonio import json_clean
from traffictwin.trainer.settings import check_device

from ._common import params, read_run_record, run_stage, setup_logging, stage_timer
from ._figure_inputs import figure_input
from ._inference import pin_torch_threads
from ._paths import (
    FUSION_DATA,
    REPORTS,
    fusion_model_dir,
    metrics_file,
    plot_file,
    prealigned,
    registration_model_dir,
)

STAGE = "evaluate_fusion"
METRICS = metrics_file("fusion")
SUMMARY = metrics_file("summary_fusion")  # the DVC metrics file: what `dvc exp show` compares
SAMPLES = REPORTS / "fusion_eval_samples.csv"
FINDINGS = REPORTS / "fusion_findings.md"
FIGURE_INPUTS = figure_input("fusion")
TRAINING = metrics_file("train_fusion_network")  # the one network's training record (train_fusion)
METHODS_TABLE = "evaluation/test_methods_{cfg}.json"  # MLflow table artifact of a network's run

log = logging.getLogger("traffictwin.evaluate_fusion")


def _csv(frame: pd.DataFrame, path: Path) -> None:
    write_csv_atomic(path, frame, float_format="%.6g", lineterminator="\n")


def log_to_mlflow(metrics: dict[str, Any], runs: list[tuple[Path, str, str, str]]) -> None:
    """Log each network's numbers to its own MLflow run (``run_id`` in the run record of the stage
    that trained it) as ``test/<cfg>/<metric>`` for every configuration it was evaluated at
    (``test/<cfg>/registered_network/<metric>`` for a network's row on registered pairs: MLflow
    names allow no ``+``), and
    every method's numbers there as the table :data:`METHODS_TABLE`; ``runs``: ``(model folder,
    configuration, evaluation row, training stage)`` per network and configuration."""
    from mlflow.entities import Metric, RunTag
    from mlflow.exceptions import MlflowException
    from mlflow.tracking import MlflowClient

    from traffictwin.fusion.evaluation import methods_table, mlflow_metrics
    from traffictwin.mlops.tracking import setup

    client = MlflowClient(tracking_uri=setup())
    stamp = int(time.time() * 1000)
    logged: dict[str, int] = {}  # metrics logged per network (one summary line at the end)
    for folder, c, row, stage in runs:
        name = folder.name
        run_id = read_run_record(stage).get("run_id")
        if not run_id:
            log.warning(
                "%s: no MLflow run id in the run record of %s; fusion evaluation of %s not logged",
                name,
                stage,
                c,
            )
            continue
        # the one network's run holds two rows per configuration: dnn (prealigned pairs) under
        # test/<cfg>/, registered+network (the same network on registered pairs) under
        # test/<cfg>/registered_network/ (MLflow metric names allow no "+")
        prefix = f"test/{c}/" if not row.startswith("registered+network") else f"test/{c}/{row}/"
        flat = mlflow_metrics(metrics, c, row, prefix)
        try:
            # log_batch on the training run: same run as mlflow.start_run(run_id=…) but leaves its status alone
            client.log_batch(
                run_id,
                metrics=[Metric(k, v, stamp, 0) for k, v in sorted(flat.items())],
                tags=[RunTag("evaluated_by", STAGE)],
            )
            # the baselines and the other rows: one table artifact, not metrics of this run
            client.log_table(run_id, methods_table(metrics, c), METHODS_TABLE.format(cfg=c))
            logged[f"{name} {run_id[:8]}"] = logged.get(f"{name} {run_id[:8]}", 0) + len(flat)
        except MlflowException as exc:
            log.warning(
                "MLflow run %s of %s not reachable (%s); metrics are in %s",
                run_id,
                name,
                exc,
                METRICS,
            )
    if logged:
        per_run = ", ".join(f"{n} metrics to {run}" for run, n in logged.items())
        log.info("logged the fusion evaluation to MLflow: %s", per_run)


def load_networks(
    cfg: Any, configs: list[str], grid: Any, device: str
) -> tuple[dict[str, dict[str, Any]], list[tuple[Path, str, str, str]]]:
    """``{row: {configuration: network}}`` and the ``(model folder, configuration, row, training
    stage)`` list of every network's MLflow run.

    Row ``dnn``: the one network (models/fusion/network) at every configuration, and the same
    network on classically registered pairs as row ``registered+network`` (one fusion network for
    every input); one row per ``fusion_variants`` entry (:func:`~traffictwin.fusion.config.variant_row`):
    a variant trained on the mixed noise at every configuration, a per-configuration variant at
    its configuration only (row ``dnn[per-config]``); row ``learned``: the one learned
    registration (models/registration/learned, when params.yaml has a ``registration_model``
    group) at every configuration; row ``learned+network``: (learned, the one network)."""
    from traffictwin.config import ConfigError, get
    from traffictwin.fusion.config import MIXED, fusion_variants, variant_row
    from traffictwin.fusion.model_io import load_fusion_model

    one = load_fusion_model(
        fusion_model_dir() / "model.ckpt", expected_cfg=MIXED, expected_grid=grid, device=device
    )
    from traffictwin.fusion.evaluation import (
        HYBRID,
        LEARNED,
        LEARNED_NETWORK,
        LEARNED_REFINED,
        LEARNED_REFINED_NETWORK,
    )

    networks: dict[str, dict[str, Any]] = {
        "dnn": dict.fromkeys(configs, one),
        HYBRID: dict.fromkeys(configs, one),  # the one network on registered pairs
    }
    runs = [
        (fusion_model_dir(), c, row, "train_fusion") for row in ("dnn", HYBRID) for c in configs
    ]
    variants = fusion_variants(cfg)
    default_loss = get(cfg, "fusion_model.loss.name", str) if variants else None
    for name, v in variants.items():
        row = variant_row(v.method, v.loss, default_loss, per_config=v.config != MIXED)
        net = load_fusion_model(
            fusion_model_dir(name) / "model.ckpt",
            expected_cfg=v.config,  # a variant's checkpoint records its training set as cfg
            expected_grid=grid,
            device=device,
        )
        for c in configs if v.config == MIXED else [v.config]:
            if c in networks.setdefault(row, {}):
                raise ConfigError(
                    f"params.yaml: 'fusion_variants.{name}' is row {row!r} at configuration {c}, "
                    f"which another variant already fills"
                )
            networks[row][c] = net
            runs.append((fusion_model_dir(name), c, row, f"train_fusion_variant@{name}"))
    from traffictwin.fusion.registration_io import load_registration_model

    if "registration_model" in cfg:
        folder = registration_model_dir()
        reg = load_registration_model(folder / "model.ckpt", expected_grid=grid, expected_cfg=MIXED)
        for c in configs:
            networks.setdefault(LEARNED, {})[c] = reg
            runs.append((folder, c, LEARNED, "train_registration"))
            networks.setdefault(LEARNED_NETWORK, {})[c] = (reg, one)
            networks.setdefault(LEARNED_REFINED, {})[c] = reg
            networks.setdefault(LEARNED_REFINED_NETWORK, {})[c] = (reg, one)
    return networks, runs


def choose_on_validation(
    fc: Any, configs: list[str], grid: Any, networks: dict[str, dict[str, Any]]
) -> tuple[Any, dict[str, Any]]:
    """Choose the classical registration's and the learned pose refinement's settings on the
    validation pairs (``evaluation.fusion.validation``: ``max_pairs`` per configuration of
    ``split``, never the evaluated one): every candidate of each grid
    (:func:`~traffictwin.fusion.registration_tuning.parameter_grid`) scored by its registration success rate
    pooled over the configurations, the highest wins (ties: the earlier candidate). Returns ``fc``
    with the chosen ``registration`` / ``refinement`` and the record for fusion.json's
    ``validation`` block. The refinement is chosen only where the learned registration is
    evaluated; without validation pairs the configured settings stay (recorded as skipped)."""
    from dataclasses import asdict, replace

    import numpy as np

    from traffictwin.fusion import evaluation as ev
    from traffictwin.fusion.methods import FusionInput
    from traffictwin.fusion.registration_tuning import parameter_grid, validation_success
    from traffictwin.io.npz import DatasetError

    v = fc.validation
    record: dict[str, Any] = {"split": v["split"], "rule": "highest success rate; ties: earlier"}
    try:
        data, pair_ids = ev.load_test_sets(
            {c: prealigned(c) for c in configs}, v["split"], v["max_pairs"], grid
        )
        raw = ev.load_raw_pairs(FUSION_DATA, pair_ids, v["split"], grid)
    except DatasetError as exc:
        log.warning("no validation pairs (%s): the configured registration settings stay", exc)
        record["skipped"] = str(exc)
        return fc, record
    record["n_pairs_per_config"] = int(len(pair_ids))
    inputs = [
        FusionInput(
            inputs=data[c]["inputs"],
            map1=raw["map1"],
            map2=raw["map2"],
            rel_pose_noisy=data[c]["rel_pose_noisy"],
            rel_pose_true=data[c]["rel_pose_true"],
            grid=grid,
            batch_size=fc.batch_size,
            pair_key=np.arange(len(pair_ids)),
            memo={},
        )
        for c in configs
    ]
    reg_model = next(iter(networks.get(ev.LEARNED, {}).values()), None)
    searches = [("registration", "registered", fc.registration_params, None)]
    if reg_model is not None:
        searches.append(("refinement", "learned-refined", fc.refinement_params, reg_model))
    chosen: dict[str, dict[str, Any]] = {}
    for key, kind, base, model in searches:
        grid_spec = dict(v[f"{key}_grid"] or {})
        cands = parameter_grid(base, grid_spec)
        rates = validation_success(
            kind,
            inputs,
            cands,
            fc.success_trans_m,
            fc.success_rot_deg,
            registration=model,
            workers=fc.registration_workers,
        )
        best = int(np.argmax(rates))  # the first of equal maxima
        chosen[key] = asdict(cands[best])
        record[key] = {
            "candidates": [{f: getattr(p, f) for f in grid_spec} for p in cands],
            "success_rate": [float(r) for r in rates],
            "chosen": {f: getattr(cands[best], f) for f in grid_spec},
        }
        log.info(
            "validation (%d pairs x %d configurations): %s %s, success %.3f (candidates %s)",
            len(pair_ids),
            len(configs),
            key,
            record[key]["chosen"],
            rates[best],
            np.round(rates, 3).tolist(),
        )
    return replace(fc, **chosen), record


#: the summary's best-epoch validation figures: key -> the network meta's field (train_fusion);
#: not val/loss: under the default loss it is val/kld_full again (train_fusion_network.json has it)
SUMMARY_VAL = {
    "val/kld_full": "best_val_kld_full",
    "val/dice_occ": "best_val_dice_occ",
}
#: the summary's test figures of the one network (row ``dnn``), at the hardest configuration
SUMMARY_TEST = ("kld_fou_mean", "dice_occ")


def summary(metrics: dict[str, Any], meta: dict[str, Any], configs: list[str]) -> dict[str, float]:
    """The handful of numbers a person compares between experiments, flat ``split/name`` keys
    with MLflow's names for the same numbers: the one network's best-epoch validation figures
    (its model meta: ``val/kld_full``, ``val/dice_occ``) and its test KLD(b)
    (nats per cell) and occupied Dice at the last (noisiest) configuration
    (``test/D/kld_fou_mean``, ``test/D/dice_occ``). A number that is missing or not finite is
    left out."""
    out: dict[str, Any] = {k: meta.get(field) for k, field in SUMMARY_VAL.items()}
    if configs:
        c = configs[-1]
        row = metrics.get("test", {}).get(c, {}).get("dnn", {})
        out.update({f"test/{c}/{name}": row.get(name) for name in SUMMARY_TEST})
    return {
        k: float(v)
        for k, v in out.items()
        if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
    }


def main() -> None:
    from traffictwin.fusion import evaluation as ev
    from traffictwin.fusion.findings import fusion_findings
    from traffictwin.io.figure_inputs import write_arrays_with_meta

    setup_logging()
    cfg = params()
    grid = grid_config(cfg)
    noise = pose_configurations(cfg)
    fc = fusion_eval_config(cfg)
    check_device(fc.device, "params.yaml", "evaluation.fusion.device")
    ci = ev.fusion_ci_config(cfg)
    thresholds = for_problem(cfg, "fusion", ev.JUDGES)
    configs = list(noise)
    with stage_timer(STAGE) as record:
        record["torch_threads"] = pin_torch_threads(cfg)
        networks, runs = load_networks(cfg, configs, grid, fc.device)
        fc, chosen = choose_on_validation(fc, configs, grid, networks)
        data, pair_ids = ev.load_test_sets(
            {c: prealigned(c) for c in configs}, fc.split, fc.max_pairs, grid
        )
        raw = ev.load_raw_pairs(FUSION_DATA, pair_ids, fc.split, grid)
        # the training target reads it; a tree without it (no train_fusion) leaves that one unjudged
        training = json.loads(TRAINING.read_text(encoding="utf-8")) if TRAINING.is_file() else None
        res = ev.evaluate(data, raw, networks, grid, fc, ci, thresholds, training)
        metrics = json_clean({**res.metrics, "validation": chosen})
        record.update(json_clean(res.timings))  # wall times: run record only
        for name, frame in ev.plot_tables(res, noise).items():
            _csv(frame, plot_file(name))
        _csv(res.samples, SAMPLES)
        panels, meta = ev.figure_inputs(
            res, noise, grid, fc.qualitative_pair, fc.qualitative_fraction
        )
        write_arrays_with_meta(FIGURE_INPUTS, panels, meta)
        write_text_atomic(FINDINGS, fusion_findings(metrics))
        write_json_atomic(METRICS, metrics)
        meta = json.loads((fusion_model_dir() / "model_meta.json").read_text(encoding="utf-8"))
        write_json_atomic(SUMMARY, summary(metrics, meta, configs))
        log_to_mlflow(metrics, runs)


if __name__ == "__main__":
    run_stage(main, "evaluate_fusion")
