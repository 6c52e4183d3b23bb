"""Publishing a trained model: where the files go (:class:`ModelOutputs`), the best epoch's
metrics (:func:`fit_metrics`), the MLflow model (:func:`log_fitted_model`), the files
(:func:`publish`) and what the stage gets back (:class:`FitResult`)."""

from __future__ import annotations

import tempfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from traffictwin.io.atomic import write_json_atomic
from traffictwin.model_format import save_model_files
from traffictwin.trainer.fit import Fitted
from traffictwin.trainer.tracking import log_checkpoint, log_final_metrics, log_model


@dataclass(frozen=True)
class ModelOutputs:
    """Where a run publishes (rank zero, each atomically, only after training succeeded): the
    slim checkpoint ``ckpt``, its ``meta`` JSON, the best epoch's ``metrics`` JSON and the
    ``curves`` CSV (None: not written)."""

    ckpt: str | Path
    meta: str | Path | None = None
    metrics: str | Path | None = None
    curves: str | Path | None = None


@dataclass
class FitResult:
    """What a training run produced (paths written, best metrics, timing)."""

    checkpoint: Path
    meta: dict[str, Any]
    metrics: dict[str, Any]
    history: list[dict[str, float]]
    run_id: str | None = None
    model_uri: str | None = None
    train_seconds: float = 0.0  # wall time of trainer.fit (s): for the stage's run record only
    samples_per_s: float | None = None  # training pairs (all ranks) per second of train_seconds
    precision: str | None = None  # the trainer's resolved precision: run record only


def stopped_early(epochs_run: int, max_epochs: int) -> bool:
    """Whether early stopping ended the run before ``max_epochs`` (the run converged on its
    validation metric instead of running out of epochs)."""
    return int(epochs_run) < int(max_epochs)


def fit_metrics(fitted: Fitted, max_epochs: int, **facts: Any) -> dict[str, Any]:
    """The best epoch's ``split/name`` metrics, ``best_epoch`` (0-based), ``epochs`` run,
    ``max_epochs``, ``stopped_early`` and the problem's ``facts`` (``samples_seen``, ...)."""
    row = fitted.best_row()
    epochs_run = len(fitted.history.rows)
    metrics: dict[str, Any] = {key: row[key] for key in sorted(row) if "/" in key}
    metrics.update(
        {
            "best_epoch": fitted.best_epoch,
            "epochs": epochs_run,
            "max_epochs": max_epochs,
            "stopped_early": stopped_early(epochs_run, max_epochs),
            **facts,
        }
    )
    return metrics


def last_step(fitted: Fitted) -> int:
    """The MLflow step of the history's last row (its ``step``, else its ``epoch``; 0 without rows)."""
    rows = fitted.history.rows
    if not rows:
        return 0
    return int(rows[-1].get("step", rows[-1].get("epoch", 0)))


def log_summary_metrics(fitted: Fitted, metrics: Mapping[str, Any]) -> None:
    """The best epoch's ``metrics`` (:func:`fit_metrics`, what the DVC metrics file holds) as the
    run's values under the same names: each ``split/name`` logged once more at the history's
    :func:`last_step`, so MLflow's value of ``val/kld_full`` (its latest) is the best epoch's, as
    in ``dvc exp show``, while the per-epoch history before it stays; the facts (``best_epoch``,
    ``epochs``, ...) at step 0."""
    split = {k: v for k, v in metrics.items() if "/" in k}
    log_final_metrics(fitted.logger, split, step=last_step(fitted))
    log_final_metrics(fitted.logger, {k: v for k, v in metrics.items() if k not in split})


def log_fitted_model(
    fitted: Fitted,
    slim: Mapping[str, Any],
    meta: Mapping[str, Any],
    metrics: Mapping[str, Any],
    net: torch.nn.Module,
    example: np.ndarray,
    metadata: Mapping[str, Any],
) -> str:
    """Into the fitted run's MLflow run: ``metrics`` (:func:`log_summary_metrics`), the slim
    checkpoint as an artifact and ``net`` as an MLflow model (:func:`log_model`); returns the
    model URI."""
    log_summary_metrics(fitted, metrics)
    problem = str(slim["traffictwin"].get("problem", "model"))
    with tempfile.TemporaryDirectory(prefix=f"{problem}_art_") as art:
        p = Path(art) / "model.ckpt"
        torch.save(slim, p)
        log_checkpoint(p)
    return log_model(slim, meta, net, example, name="model", metadata=dict(metadata))


def publish(
    fitted: Fitted,
    outputs: ModelOutputs,
    slim: Mapping[str, Any],
    meta: Mapping[str, Any],
    metrics: Mapping[str, Any],
) -> None:
    """Write the model folder (checkpoint then meta: one unit), the metrics and the curves."""
    save_model_files(outputs.ckpt, slim, outputs.meta, meta)
    if outputs.metrics:
        write_json_atomic(outputs.metrics, dict(metrics))
    if outputs.curves:
        fitted.history.write_csv(outputs.curves)


def fit_result(
    fitted: Fitted,
    outputs: ModelOutputs,
    meta: dict[str, Any],
    metrics: dict[str, Any],
    model_uri: str | None,
) -> FitResult:
    """The stage's :class:`FitResult`; pairs per second from ``metrics["samples_seen"]``."""
    train_s = fitted.seconds
    return FitResult(
        Path(outputs.ckpt),
        meta,
        metrics,
        fitted.history.rows,
        fitted.run.info.run_id if fitted.run is not None else None,
        model_uri,
        round(train_s, 2),
        round(metrics["samples_seen"] / train_s, 3) if train_s > 0 else None,
        precision=fitted.precision,
    )
