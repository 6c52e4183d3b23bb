"""Callbacks of every training run: the finite-loss guard, best checkpoint, early stopping and
the metric :class:`History` (rows per epoch or per validation, logged to MLflow, written as CSV)."""

from __future__ import annotations

import csv
import logging
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from lightning.pytorch.callbacks import Callback

from traffictwin.io.atomic import atomic_path

log = logging.getLogger(
    "traffictwin.trainer"
)  # the package's logger, as the epoch lines always named it


class TrainingDiverged(FloatingPointError):
    """A training loss or monitored validation metric became NaN or infinite (see :class:`FiniteGuard`)."""


class FiniteGuard(Callback):
    """Stop training at the first non-finite training loss (after every training batch) or
    non-finite ``monitor`` value (after every validation), with :class:`TrainingDiverged`.

    The message names ``stage``, the epoch (1-based, as every log line counts them: see
    :class:`History`), the global step, the value, the current
    learning rate and ``hint`` (the setting to lower, e.g. ``fusion_model.optim.lr``), and says
    that NaN/inf in the data have the same effect (the loaders refuse non-finite shards, so here
    it is usually the learning rate). Read-only: it changes nothing in a run that stays finite.
    """

    def __init__(
        self,
        stage: str = "training",
        *,
        hint: str = "the learning rate",
        monitor: str | None = None,
    ) -> None:
        self.stage = stage
        self.hint = hint
        self.monitor = monitor

    def _fail(self, trainer: Any, what: str, value: float) -> None:
        lr = None
        if trainer.optimizers:
            lr = trainer.optimizers[0].param_groups[0].get("lr")
        lr_s = f", lr={float(lr):g}" if lr is not None else ""
        raise TrainingDiverged(
            f"{self.stage}: training diverged at epoch {int(trainer.current_epoch) + 1}, step "
            f"{int(trainer.global_step)}: {what} is {value}{lr_s}; lower {self.hint} "
            f"(or check the training data for NaN/inf)"
        )

    def on_train_batch_end(
        self, trainer: Any, pl_module: Any, outputs: Any, batch: Any, batch_idx: int
    ) -> None:
        loss = outputs.get("loss") if isinstance(outputs, Mapping) else outputs
        if loss is None:
            return
        v = _to_float(loss)
        if v is not None and not math.isfinite(v):
            self._fail(trainer, "the training loss", v)

    def on_validation_end(self, trainer: Any, pl_module: Any) -> None:
        if self.monitor is None or trainer.sanity_checking:
            return
        v = _to_float(trainer.callback_metrics.get(self.monitor))
        if v is not None and not math.isfinite(v):
            self._fail(trainer, self.monitor, v)


def best_checkpoint(
    dirpath: str | Path, monitor: str = "val/loss", mode: str = "min", filename: str = "best"
) -> Any:
    """ModelCheckpoint keeping only the best epoch on ``monitor`` (no 'last' file)."""
    from lightning.pytorch.callbacks import ModelCheckpoint

    return ModelCheckpoint(
        dirpath=str(dirpath),
        filename=filename,
        monitor=monitor,
        mode=mode,
        save_top_k=1,
        save_last=False,
        auto_insert_metric_name=False,
        enable_version_counter=False,
    )


def early_stopping(
    monitor: str = "val/loss", patience: int = 30, mode: str = "min", min_delta: float = 0.0
) -> Any:
    """EarlyStopping on ``monitor`` (checked after each validation)."""
    from lightning.pytorch.callbacks import EarlyStopping

    return EarlyStopping(
        monitor=monitor, patience=int(patience), mode=mode, min_delta=min_delta, check_finite=True
    )


def _to_float(v: Any) -> float | None:
    try:
        f = float(v.detach().cpu().item()) if isinstance(v, torch.Tensor) else float(v)
    except (TypeError, ValueError, RuntimeError):
        return None
    return f


class History(Callback):
    """The one metric-history callback: rows for the curves CSV, logged to MLflow as they come.

    ``every="epoch"`` (fusion): one row per finished training epoch (after its validation):
    ``epoch`` (0-based), every ``callback_metrics`` name with a ``/``, ``lr`` (first param
    group); MLflow ``step = epoch``; and one log line ``epoch k/N ...``.

    Epoch numbers, the one convention: *stored* epochs are Lightning's 0-based
    ``current_epoch`` (the rows' and the curves CSV's ``epoch``, MLflow steps, a checkpoint's
    ``epoch``, the ``best_epoch`` of metrics and model meta files); every *human-readable* line
    (this log line, :class:`FiniteGuard`'s message, the report's sentences on where training
    stopped) counts from 1, i.e. says stored epoch + 1, "epoch k/N" meaning the k-th of N.

    ``every="validation"`` (risk; the paper's curves are over iterations): one row per
    validation: ``step`` (global step), ``epoch`` (fractional), ``train_loss`` = the mean
    training loss over the steps since the previous row, and the ``metrics`` names (NaN when
    absent); MLflow ``step = global step``.

    Rows (finite values) go to ``logger`` (a Lightning logger, e.g. :func:`mlflow_logger`'s
    ``MLFlowLogger`` on the stage's run) when given; rank zero only.
    """

    def __init__(
        self,
        every: str = "epoch",
        *,
        metrics: Sequence[str] = (),
        train_loss: str = "train/loss",
        logger: Any = None,
    ) -> None:
        if every not in ("epoch", "validation"):
            raise ValueError(f"History: every must be 'epoch' or 'validation', got {every!r}")
        self.every = every
        self.metrics = tuple(metrics)
        self.train_loss = train_loss
        self.logger = logger
        self.rows: list[dict[str, float]] = []
        self._losses: list[float] = []

    @property
    def columns(self) -> list[str]:
        """CSV columns: the step/epoch keys first, then the metric names."""
        if self.every == "validation":
            return ["step", "epoch", self.train_loss, *self.metrics]
        return ["epoch", *sorted({k for r in self.rows for k in r if k != "epoch"})]

    def on_train_batch_end(
        self, trainer: Any, pl_module: Any, outputs: Any, batch: Any, batch_idx: int
    ) -> None:
        if self.every != "validation":
            return
        loss = outputs["loss"] if isinstance(outputs, Mapping) else outputs
        if loss is not None:
            self._losses.append(float(loss.detach()))

    def on_train_epoch_end(self, trainer: Any, pl_module: Any) -> None:
        if self.every != "epoch" or trainer.sanity_checking or not trainer.is_global_zero:
            return
        row: dict[str, float] = {}
        for k, v in trainer.callback_metrics.items():
            if "/" in k:
                f = _to_float(v)
                if f is not None:
                    row[k] = f
        if trainer.optimizers:
            row["lr"] = float(trainer.optimizers[0].param_groups[0]["lr"])
        shown = " ".join(f"{k}={v:.4g}" for k, v in sorted(row.items()) if not k.endswith("_naive"))
        log.info("epoch %d/%d %s", trainer.current_epoch + 1, trainer.max_epochs, shown)
        self._add({"epoch": int(trainer.current_epoch), **row}, step=int(trainer.current_epoch))

    def on_validation_end(self, trainer: Any, pl_module: Any) -> None:
        if self.every != "validation" or trainer.sanity_checking or not trainer.is_global_zero:
            return
        m = trainer.callback_metrics
        row = {
            "step": int(trainer.global_step),
            "epoch": float(trainer.global_step) / max(1, trainer.num_training_batches),
            self.train_loss: float(np.mean(self._losses)) if self._losses else float("nan"),
            **{k: float(m[k]) if k in m else float("nan") for k in self.metrics},
        }
        self._losses = []
        self._add(row, step=row["step"])

    def state_dict(self) -> dict[str, Any]:
        """The rows so far (kept in Lightning checkpoints, so a resumed run continues them)."""
        return {"rows": [dict(r) for r in self.rows], "losses": list(self._losses)}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.rows = [dict(r) for r in state_dict.get("rows", [])]
        self._losses = list(state_dict.get("losses", []))

    def _add(self, row: dict[str, float], step: int) -> None:
        self.rows.append(row)
        if self.logger is not None:
            finite = {
                k: v for k, v in row.items() if k not in ("step", "epoch") and math.isfinite(v)
            }
            self.logger.log_metrics(finite, step=step)

    def frame(self) -> Any:
        """The rows as a pandas DataFrame with :attr:`columns`."""
        import pandas as pd

        return pd.DataFrame(self.rows, columns=self.columns)

    def write_csv(self, path: str | Path) -> None:
        """Write the rows as CSV (atomically); ``%.9g`` floats, empty cells for missing values."""
        cols = self.columns
        with atomic_path(path, suffix=".csv") as tmp:
            with open(tmp, "w", newline="") as fh:
                w = csv.writer(fh, lineterminator="\n")
                w.writerow(cols)
                for r in self.rows:
                    w.writerow(
                        [
                            r[c]
                            if isinstance(r.get(c), int)
                            else ("" if c not in r else f"{r[c]:.9g}")
                            for c in cols
                        ]
                    )
