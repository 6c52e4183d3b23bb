"""The one training driver (:func:`fit_run`; :func:`fit_and_publish` for a problem that
publishes its model right after) and the one trainer shape (:class:`NetModule`):
how a run loops and stops (:class:`FitLoop`), what it records in MLflow (:class:`RunRecord`)
and what it trained (:class:`Fitted`)."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import lightning as L
import torch

from traffictwin.model_format import model_checkpoint
from traffictwin.trainer.callbacks import FiniteGuard, History, best_checkpoint, early_stopping
from traffictwin.trainer.settings import TrainerSettings, build_trainer
from traffictwin.trainer.tracking import TrackingSettings, mlflow_logger, tracked_run


class NetModule(L.LightningModule):
    """The one trainer shape: a LightningModule around an injected network ``net`` and loss.

    ``loss(prediction, target, *args)`` -> scalar tensor. Optimiser: Adam on the network's
    parameters (``lr``, ``weight_decay``); with ``plateau = (factor, patience)`` the learning
    rate is reduced when ``monitor`` stops improving (checked once per epoch). Subclasses add
    the problem's steps and metrics (torchmetrics) and log ``split/name`` values, which
    :class:`History`, :func:`best_checkpoint` and :func:`early_stopping` read.
    """

    def __init__(
        self,
        net: torch.nn.Module,
        loss: Callable[..., torch.Tensor],
        *,
        lr: float,
        weight_decay: float = 0.0,
        plateau: tuple[float, int] | None = None,
        monitor: str = "val/loss",
    ) -> None:
        super().__init__()
        self.net = net
        self.loss_fn = loss
        self.lr, self.weight_decay = float(lr), float(weight_decay)
        self.plateau = plateau
        self.monitor = monitor

    def configure_optimizers(self) -> Any:
        opt = torch.optim.Adam(self.net.parameters(), lr=self.lr, weight_decay=self.weight_decay)
        if self.plateau is None:
            return opt
        factor, patience = self.plateau
        sched = torch.optim.lr_scheduler.ReduceLROnPlateau(
            opt, mode="min", factor=factor, patience=patience
        )
        return {
            "optimizer": opt,
            "lr_scheduler": {
                "scheduler": sched,
                "monitor": self.monitor,
                "interval": "epoch",
                "frequency": 1,
            },
        }


# ---------------------------------------------------------------------------------------------
# the one training driver


@dataclass(frozen=True)
class FitLoop:
    """How one training run loops, stops and keeps its best epoch, the same for every problem.

    ``monitor`` / ``mode``: the validation metric that picks the best checkpoint (and drives early
    stopping); ``max_epochs``; ``patience``: epochs without improvement of ``monitor`` before
    early stopping ends the run (None: no early stopping), an improvement counting only when it
    exceeds ``min_delta``; ``hint``: the setting to lower when the
    run diverges (:class:`FiniteGuard`); ``history`` / ``history_metrics``: :class:`History` rows
    per epoch or per validation; ``gradient_clip_val``; ``trainer_extra``: further
    ``lightning.Trainer`` arguments (e.g. ``val_check_interval``)."""

    monitor: str
    max_epochs: int
    mode: str = "min"
    patience: int | None = None
    min_delta: float = 0.0
    hint: str = "the learning rate"
    history: str = "epoch"
    history_metrics: tuple[str, ...] = ()
    gradient_clip_val: float | None = None
    trainer_extra: Mapping[str, Any] = field(default_factory=dict)


@dataclass
class Fitted:
    """What :func:`fit_run` trained (rank zero only): ``best`` = the best epoch's Lightning
    checkpoint (``state_dict``, ``epoch``, ``global_step``; None when no validation ran, e.g. a
    ``fast_dev_run``), the :class:`History`, the ``trainer``, the MLflow ``run`` and ``logger``
    (None without tracking), ``seconds`` = wall time of ``trainer.fit`` and the resolved
    ``precision``."""

    best: dict[str, Any] | None
    history: History
    trainer: Any
    run: Any
    logger: Any
    seconds: float
    precision: str

    @property
    def best_epoch(self) -> int:
        """The best checkpoint's epoch, 0-based (Lightning's; -1 when there is none): a log line
        says ``best_epoch + 1`` (see :class:`History`)."""
        return int(self.best.get("epoch", -1)) if self.best else -1

    def model_checkpoint(self, problem: str, architecture: Mapping[str, Any]) -> dict[str, Any]:
        """The best epoch as a slim checkpoint of the one model format (weights, ``epoch``,
        ``global_step``; no optimiser state): :func:`traffictwin.model_format.model_checkpoint`."""
        assert self.best is not None
        return model_checkpoint(
            problem,
            dict(architecture),
            self.best["state_dict"],
            {},
            epoch=self.best_epoch,
            global_step=int(self.best.get("global_step", -1)),
        )

    def best_row(self) -> dict[str, float]:
        """The history row of the best epoch (the last row when there is none)."""
        rows = self.history.rows
        return next(
            (r for r in rows if r.get("epoch") == self.best_epoch), rows[-1] if rows else {}
        )


@dataclass(frozen=True)
class RunRecord:
    """What the MLflow run records of one training beyond :class:`TrackingSettings`: ``tags``,
    ``params`` (added to the tracking's, logged once) and ``datasets`` ``(root, manifest hash)``
    (logged as MLflow datasets)."""

    tags: Mapping[str, Any] = field(default_factory=dict)
    params: Mapping[str, Any] = field(default_factory=dict)
    datasets: Sequence[tuple[str | Path, str]] = ()


BEST_DIR = "best"  # fit_run's folder for the best epoch's checkpoint, inside its work folder

# Lightning 2.6's CombinedLoader builds a torch.utils._pytree.LeafSpec() for every loader it
# wraps (lightning/pytorch/utilities/_pytree.py), which torch >= 2.9 deprecates with a
# FutureWarning at each fit (Lightning-AI/pytorch-lightning#21326). No Trainer or loader setting
# avoids it (a single loader, a list or a dict all end in a LeafSpec), and nothing of ours calls
# it: :func:`_quiet_fit` ignores exactly this warning from exactly that module, during the fit.
_LEAFSPEC_MESSAGE = r"`isinstance\(treespec, LeafSpec\)` is deprecated"
_LEAFSPEC_MODULE = r"lightning\.pytorch\.utilities\._pytree"


@contextmanager
def _quiet_fit(resumed_best_dir: str | Path | None = None) -> Iterator[None]:
    """Around ``trainer.fit``: ignore Lightning's ``LeafSpec`` FutureWarning (above); when the
    run resumes, also ModelCheckpoint's "Checkpoint directory ... exists and is not empty" for
    ``resumed_best_dir``, which then holds, by design, the best checkpoint the interrupted run
    wrote (its bookkeeping is restored from ``last.ckpt``). Other warnings pass as they are."""
    import re
    import warnings

    with warnings.catch_warnings():
        warnings.filterwarnings(
            "ignore", message=_LEAFSPEC_MESSAGE, category=FutureWarning, module=_LEAFSPEC_MODULE
        )
        if resumed_best_dir is not None:
            warnings.filterwarnings(
                "ignore",
                message=rf"Checkpoint directory {re.escape(str(resumed_best_dir))} exists and is not empty",
                category=UserWarning,
            )
        yield


@contextmanager
def fit_run(
    module: L.LightningModule,
    data: Any,
    *,
    settings: TrainerSettings,
    loop: FitLoop,
    tracking: TrackingSettings,
    session: Any,
    record: RunRecord = RunRecord(),
    fast_dev_run: bool | int = False,
) -> Iterator[Fitted | None]:
    """The one training driver of every problem (fusion, registration, risk): the problem gives
    its LightningModule and its ``data`` (a DataModule, or a ``(train, val)`` pair of loaders);
    this owns the rest.

    Opens the tracked MLflow run (:func:`tracked_run`; ``record``'s params logged once, its
    datasets as MLflow datasets, the run id in the resume folder), builds the
    :class:`History`, the best-checkpoint and early-stopping callbacks on ``loop.monitor``, the
    :class:`FiniteGuard` and the resume callbacks of ``session``
    (:class:`traffictwin.resume.Session`), trains with :func:`build_trainer` (resuming from
    ``session.resume_from``), then yields a :class:`Fitted` inside the still open MLflow run so the
    caller publishes its model (files, MLflow model) before the run ends; ``None`` on other DDP
    ranks. On a normal exit the resume folder is removed (``session.finish()``); an exception
    keeps it, so the next run resumes.
    """
    with (
        session.workdir(f"{tracking.stage.replace('@', '-')}-ckpt-") as work,
        tracked_run(
            tracking.experiment,
            tracking.run_name,
            profile=tracking.profile,
            stage=tracking.stage,
            tags=dict(record.tags),
            params={**tracking.params, **dict(record.params)},
            enabled=tracking.enabled,
            run_id=session.run_id(),
        ) as run,
    ):
        logger = mlflow_logger(run)
        if run is not None and session.resume_from is None:
            from traffictwin.mlops.tracking import log_dataset

            for root, digest in record.datasets:
                log_dataset(root, digest)
        session.started(run)
        history = History(loop.history, metrics=loop.history_metrics, logger=logger)
        # the best epoch's checkpoint in a folder of its own, which only this run writes: absent when
        # the run starts afresh (Session.workdir is new or just emptied, the resume folder already
        # holds resume.json), kept with the resume state when it resumes
        ckpt = best_checkpoint(Path(work) / BEST_DIR, monitor=loop.monitor, mode=loop.mode)
        callbacks = [history, ckpt, *_stop_callbacks(loop, tracking.stage), *session.callbacks()]
        trainer = build_trainer(
            settings,
            max_epochs=loop.max_epochs,
            callbacks=callbacks,
            default_root_dir=work,
            gradient_clip_val=loop.gradient_clip_val,
            fast_dev_run=fast_dev_run,
            **dict(loop.trainer_extra),
        )
        t0 = time.perf_counter()
        # ckpt.dirpath: the folder as Lightning names it in the warning (its realpath)
        with _quiet_fit(ckpt.dirpath if session.resume_from is not None else None):
            trainer.fit(
                module,
                **_data_kwargs(data),
                ckpt_path=session.resume_from,
                # last.ckpt holds tensors and plain containers only: read without unpickling code
                weights_only=True,
            )
        seconds = time.perf_counter() - t0
        if not trainer.is_global_zero:
            yield None
            return
        best = _read_best(ckpt, fast_dev_run)
        yield Fitted(best, history, trainer, run, logger, seconds, str(settings.precision))
    session.finish()


T = TypeVar("T")


def fit_and_publish(*args: Any, publish: Callable[[Fitted], T], **kwargs: Any) -> T | None:
    """:func:`fit_run` with these arguments, then ``publish(fitted)`` inside the still open MLflow
    run (the problem writes its model files and MLflow model there): its result, or None on
    other DDP ranks."""
    with fit_run(*args, **kwargs) as fitted:
        return None if fitted is None else publish(fitted)


def _stop_callbacks(loop: FitLoop, stage: str) -> list[Any]:
    """Early stopping on ``loop.monitor`` (when ``loop.patience`` is set) and the finite guard."""
    out: list[Any] = []
    if loop.patience is not None:
        out.append(
            early_stopping(loop.monitor, loop.patience, mode=loop.mode, min_delta=loop.min_delta)
        )
    out.append(FiniteGuard(stage, hint=loop.hint, monitor=loop.monitor))
    return out


def _data_kwargs(data: Any) -> dict[str, Any]:
    """``trainer.fit``'s data arguments for a DataModule or a ``(train, val)`` pair of loaders."""
    if isinstance(data, tuple):
        train, val = data
        return {"train_dataloaders": train, "val_dataloaders": val}
    return {"datamodule": data}


def _read_best(ckpt: Any, fast_dev_run: bool | int) -> dict[str, Any] | None:
    """The best epoch's Lightning checkpoint (weights, optimiser state, loops: tensors and plain
    containers), read like every other checkpoint without unpickling code; None when there is none."""
    path = getattr(ckpt, "best_model_path", "") if not fast_dev_run else ""
    if path and Path(path).exists():
        return torch.load(path, map_location="cpu", weights_only=True)
    return None
