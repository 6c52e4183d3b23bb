"""Lightning + MLflow helpers shared by the fusion and risk trainers (docs/design.md "Tracking").

Stable API (the fusion and the risk stages both use it):

- :class:`TrainerSettings` — the ``trainer`` config group (accelerator, devices, num_nodes,
  strategy, precision, num_workers, optional deterministic / num_threads), validated once with
  :func:`traffictwin.config.typed` by :meth:`TrainerSettings.from_cfg`.
- :func:`seed_everything` — seeds python/numpy/torch (and dataloader workers).
- :func:`build_trainer` — a ``lightning.Trainer`` from the settings, with no Lightning logger
  (metrics go to MLflow through :class:`History`, which logs one value per epoch).
- :class:`NetModule` — the one trainer shape: LightningModule with an injected network and
  loss, Adam (+ optional plateau decay); the fusion and risk modules subclass it.
- :class:`RankShardSampler` / :func:`rank_layout` — under DDP, this rank's share of a
  sampler's indices, for the loaders the DataModules build themselves: training gets the
  same per-epoch draw split evenly over the ranks, evaluation every sample exactly once
  (Lightning's own DistributedSampler would repeat samples to even out the ranks).
- :func:`best_checkpoint` / :func:`early_stopping` — callbacks on a monitored metric.
- :class:`FiniteGuard` — the one finite-loss guard of every trainer (:func:`build_trainer` adds
  one when the caller gave none): a NaN/inf training loss or monitored metric stops the run with
  :class:`TrainingDiverged` naming the stage, epoch, step, learning rate and the parameter to lower.
- :class:`History` — the metric rows (per epoch, or per validation for the risk net's
  per-iteration curves), logged to the active MLflow run (rank zero only), written as CSV.
- :func:`mlflow_logger` / :func:`log_final_metrics` — Lightning's ``MLFlowLogger`` on the
  stage's MLflow run, through which :class:`History` and the final metrics are logged.
- :func:`global_rank` / :func:`tracked_run` — an MLflow run on rank zero only (under DDP the
  launcher re-runs the stage script in every rank; the other ranks get ``None``).
- :func:`log_checkpoint` / :func:`log_model` — the best checkpoint as an artifact and the
  network as an MLflow model of weights + JSON (no pickled code, SHA-256 sealed) that
  :func:`traffictwin.mlops.registry.load_registered` restores with the problem's loader.
- One checkpoint format for every trained network (:data:`MODEL_FORMAT`):
  :func:`model_checkpoint` builds it, :func:`save_model_checkpoint` writes it atomically,
  :func:`read_model_checkpoint` reads it back with ``weights_only=True`` and checks it, and
  :func:`net_state_dict` gives the network's weights. A model folder's ``model.ckpt`` and
  ``model_meta.json`` are one unit: :func:`save_model_files` writes them (meta last, recording
  the checkpoint's SHA-256) and :func:`check_model_pair` refuses a pair that does not match.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import os
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from lightning.pytorch.callbacks import Callback
from torch.utils.data import DistributedSampler, Sampler

from traffictwin.config import ConfigError, spec, typed
from traffictwin.io.atomic import atomic_path
from traffictwin.model_format import (  # noqa: F401 - re-exported: the one checkpoint format
    CKPT_SHA_KEY,
    MODEL_FORMAT,
    CheckpointError,
    check_model_pair,
    model_checkpoint,
    net_state_dict,
    read_model_checkpoint,
    read_model_meta,
    save_model_checkpoint,
    save_model_files,
)
from traffictwin.threads import pin_threads

log = logging.getLogger(__name__)

PRECISIONS = (
    "auto",  # resolved by resolve_precision: bf16-mixed where the hardware has native bf16, else 32-true
    "32-true",
    "32",
    "64-true",
    "16-mixed",
    "bf16-mixed",
    "bf16-true",
    "16-true",
    "transformer-engine",
)
ACCELERATORS = ("cpu", "gpu", "cuda", "mps", "tpu", "auto")


@dataclass(frozen=True)
class TrainerSettings:
    """Where and how Lightning runs: one CPU, one GPU, or DDP over ``devices`` x ``num_nodes``.

    Also the schema of the ``trainer`` config group (:meth:`from_cfg`); ``deterministic`` and
    ``num_threads`` may be left out there, every other key is required.
    """

    accelerator: str = spec("cpu", choices=ACCELERATORS)
    devices: int | str = 1  # >= 1, -1 (all) or a Lightning string ("auto", "0,1")
    num_nodes: int = spec(1, min=1)
    strategy: str = "auto"
    precision: str | int = spec("32-true", choices=[*PRECISIONS, 32, 64])
    num_workers: int = spec(0, min=0)
    deterministic: bool | str | None = (
        None  # None: True on CPU, "warn" elsewhere (CUDA upsampling backward)
    )
    num_threads: int = spec(0, min=0)  # torch intra-op CPU threads; 0 = torch's default

    OPTIONAL = ("deterministic", "num_threads")

    @classmethod
    def from_cfg(cls, cfg: Any, *, source: str | Path, key: str = "trainer") -> TrainerSettings:
        """Validate the ``trainer`` group of ``cfg`` (the whole params tree) once; errors name ``source``."""
        node = cfg.get(key) if isinstance(cfg, Mapping) or hasattr(cfg, "get") else None
        if node is None:
            raise ConfigError(f"{source}: '{key}' is missing")
        for f in fields(cls):
            if f.name not in cls.OPTIONAL and f.name not in node:
                raise ConfigError(f"{source}: '{key}.{f.name}' is missing")
        settings = typed(node, cls, key=key, source=source)
        d = settings.devices
        if isinstance(d, int) and d < 1 and d != -1:
            raise ConfigError(f"{source}: '{key}.devices' must be >= 1 or -1, got {d!r}")
        return replace(
            settings, precision=resolve_precision(str(settings.precision), settings.accelerator)
        )

    def check_available(self, source: str | Path, key: str = "trainer") -> None:
        """The requested hardware must exist on this machine: CUDA for ``gpu``/``cuda``, at most
        as many GPUs (or, on CPU, cores) as ``devices`` asks for. Stages call this right after
        :meth:`from_cfg`, before any output is touched; ConfigError names the setting and what
        is available."""
        want = self.devices if isinstance(self.devices, int) and self.devices > 0 else None
        if self.accelerator in ("gpu", "cuda"):
            if not torch.cuda.is_available():
                raise ConfigError(
                    f"{source}: '{key}.accelerator' is {self.accelerator!r} but this machine has no "
                    f"CUDA device (torch {torch.__version__}, torch.cuda.is_available() is False): "
                    f"use trainer=cpu"
                )
            have = torch.cuda.device_count()
            if want is not None and want > have:
                raise ConfigError(
                    f"{source}: '{key}.devices' is {want} but this machine has {have} CUDA device(s)"
                )
        elif self.accelerator == "cpu" and want is not None and want > (os.cpu_count() or 1):
            raise ConfigError(
                f"{source}: '{key}.devices' is {want} CPU processes but this machine has "
                f"{os.cpu_count()} cores"
            )
        self._check_lightning(source, key)

    def _check_lightning(self, source: str | Path, key: str) -> None:
        """Lightning must accept accelerator/devices/num_nodes/strategy/precision together on this
        machine (e.g. ``mps`` or ``tpu`` that is not there, a device list on CPU, an unknown
        strategy): a throw-away ``Trainer`` is built; its error becomes a ConfigError."""
        from lightning.fabric.utilities.exceptions import MisconfigurationException

        # Lightning's startup banners -> warnings only (as in build_trainer)
        logging.getLogger("lightning.pytorch.utilities.rank_zero").setLevel(logging.WARNING)
        try:
            L.Trainer(
                accelerator=self.accelerator,
                devices=self.devices,
                num_nodes=self.num_nodes,
                strategy=self.strategy,
                precision=self.precision,  # type: ignore[arg-type]
                logger=False,
                enable_checkpointing=False,
                enable_progress_bar=False,
                enable_model_summary=False,
            )
        except (MisconfigurationException, ValueError, TypeError, ImportError, RuntimeError) as exc:
            msg = " | ".join(ln.strip() for ln in str(exc).splitlines() if ln.strip())
            raise ConfigError(
                f"{source}: '{key}' (accelerator={self.accelerator!r}, devices={self.devices!r}, "
                f"num_nodes={self.num_nodes}, strategy={self.strategy!r}, "
                f"precision={self.precision!r}) cannot run here: {type(exc).__name__}: {msg}"
            ) from None

    def resolved_deterministic(self) -> bool | str:
        if self.deterministic is not None:
            return self.deterministic
        return True if self.accelerator == "cpu" else "warn"

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def native_bf16_cpu(cpuinfo: str | Path = "/proc/cpuinfo") -> bool:
    """Whether this CPU computes bfloat16 natively (x86 ``avx512_bf16`` or ``amx_bf16``, as
    ``/proc/cpuinfo`` lists them). Elsewhere oneDNN emulates bf16, which is slower than fp32, so
    an unreadable ``cpuinfo`` (another OS) counts as no."""
    try:
        text = Path(cpuinfo).read_text(errors="replace")
    except OSError:
        return False
    flags = next((ln for ln in text.splitlines() if ln.startswith(("flags", "Features"))), "")
    have = set(flags.split(":", 1)[-1].split())
    return bool(have & {"avx512_bf16", "amx_bf16"})


def resolve_precision(
    precision: str, accelerator: str, cpuinfo: str | Path = "/proc/cpuinfo"
) -> str:
    """Lightning's precision for the ``trainer.precision`` setting: ``auto`` becomes ``bf16-mixed``
    where the hardware has native bf16 (a CUDA GPU that supports it; a CPU with AVX512-BF16 or
    AMX-BF16, :func:`native_bf16_cpu`) and ``32-true`` elsewhere; any other value is kept.
    Measured on the default fusion network's training step (2-core AMD EPYC with AVX512-BF16):
    0.258 s in fp32, 0.153 s in bf16 autocast at batch 8 (README, *How long it takes*)."""
    if precision != "auto":
        return precision
    if accelerator in ("gpu", "cuda", "auto") and torch.cuda.is_available():
        return "bf16-mixed" if torch.cuda.is_bf16_supported() else "32-true"
    if accelerator in ("cpu", "auto"):
        return "bf16-mixed" if native_bf16_cpu(cpuinfo) else "32-true"
    return "32-true"


def check_device(device: str, source: str | Path, key: str) -> None:
    """A torch device setting (``cpu``, ``cuda``, ``cuda:1``, ...) must name a device this machine
    has; ConfigError naming ``key`` otherwise (stages call it before any output is touched)."""
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as exc:
        raise ConfigError(
            f"{source}: '{key}' is not a torch device, got {device!r} ({exc})"
        ) from None
    if dev.type == "cuda":
        have = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if have <= (dev.index or 0):
            raise ConfigError(
                f"{source}: '{key}' is {device!r} but this machine has {have} CUDA device(s): use cpu"
            )
    elif dev.type != "cpu":
        raise ConfigError(f"{source}: '{key}' must be cpu or cuda[:i], got {device!r}")


def seed_everything(seed: int) -> None:
    """Seed python, numpy and torch (and dataloader workers, via Lightning) for run-to-run determinism."""
    import lightning as L

    os.environ.setdefault("PYTHONHASHSEED", "0")
    L.seed_everything(int(seed), workers=True, verbose=False)


def build_trainer(
    settings: TrainerSettings,
    *,
    max_epochs: int,
    callbacks: Sequence[Any] = (),
    default_root_dir: str | Path | None = None,
    fast_dev_run: bool | int = False,
    limit_train_batches: int | float | None = None,
    limit_val_batches: int | float | None = None,
    gradient_clip_val: float | None = None,
    num_sanity_val_steps: int = 0,
    enable_progress_bar: bool | None = None,
    **extra: Any,
) -> Any:
    """A ``lightning.Trainer`` for ``settings``; no Lightning logger (see :class:`History`).

    ``enable_progress_bar``: ``None`` shows Lightning's progress bar only when stderr is a
    terminal (not in DVC or CI logs, which get :class:`History`'s one line per epoch).
    """
    import sys

    import lightning as L
    from lightning.pytorch.callbacks import ModelCheckpoint

    if settings.num_threads > 0:
        pin_threads(settings.num_threads)
    # Lightning's startup banners ("GPU available", logger tips) -> warnings only; epochs are logged by History
    logging.getLogger("lightning.pytorch.utilities.rank_zero").setLevel(logging.WARNING)
    callbacks = list(callbacks)
    if not any(isinstance(cb, FiniteGuard) for cb in callbacks):
        callbacks.append(FiniteGuard())
    kw: dict[str, Any] = dict(
        accelerator=settings.accelerator,
        devices=settings.devices,
        num_nodes=settings.num_nodes,
        strategy=settings.strategy,
        precision=settings.precision,
        deterministic=settings.resolved_deterministic(),
        max_epochs=int(max_epochs),
        callbacks=list(callbacks),
        logger=False,
        # Lightning's implicit checkpoint callback would write into the cwd; only checkpoint when asked
        enable_checkpointing=any(isinstance(cb, ModelCheckpoint) for cb in callbacks),
        enable_progress_bar=sys.stderr.isatty()
        if enable_progress_bar is None
        else enable_progress_bar,
        enable_model_summary=False,
        num_sanity_val_steps=num_sanity_val_steps,
        default_root_dir=str(default_root_dir) if default_root_dir else None,
        fast_dev_run=fast_dev_run,
        gradient_clip_val=gradient_clip_val,
    )
    if limit_train_batches is not None:
        kw["limit_train_batches"] = limit_train_batches
    if limit_val_batches is not None:
        kw["limit_val_batches"] = limit_val_batches
    kw.update(extra)
    return L.Trainer(**kw)


def rank_layout(trainer: Any) -> tuple[int, int]:
    """``(world_size, global_rank)`` of the Lightning trainer a DataModule is attached to;
    ``(1, 0)`` when there is none (a DataModule used on its own)."""
    if trainer is None:
        return 1, 0
    return int(trainer.world_size), int(trainer.global_rank)


class RankShardSampler(DistributedSampler):
    """This rank's share of ``base``'s indices under DDP.

    ``base`` is iterated once per epoch on every rank; it must yield the same indices on every
    rank (a seeded sampler: e.g. a ``RandomSampler`` with a generator of a fixed seed, which
    then draws afresh each epoch, the same draw everywhere).

    ``even=True`` (training): ``list(base)[rank::num_replicas]`` without the last
    ``len(base) % num_replicas`` indices of the epoch's draw, so every rank gets
    ``len(base) // num_replicas`` and all ranks run the same number of optimiser steps; an epoch
    draws ``len(base)`` samples in all (e.g. a ``RandomSampler``'s ``num_samples``), not the
    whole dataset per rank.

    ``even=False`` (evaluation): nothing left out or repeated. The indices are cut into
    consecutive blocks of ``block`` (the loader's batch size) dealt round-robin to the ranks, so
    each rank evaluates exactly the batches one process would (same batch composition, same
    float32 arithmetic) and sums reduced over the ranks differ from one process's only in the
    order of the final additions. With fewer batches than ranks the blocks shrink to
    ``ceil(len(base) / num_replicas)``. Ranks may run different numbers of batches (the
    evaluation steps must not communicate per batch); every rank needs at least one index.

    A :class:`~torch.utils.data.DistributedSampler`, so Lightning does not wrap it again.
    """

    def __init__(
        self,
        base: Sampler[int],
        num_replicas: int,
        rank: int,
        *,
        even: bool,
        block: int = 1,
    ) -> None:
        n = len(base)  # type: ignore[arg-type]
        if not 0 <= rank < num_replicas:
            raise ValueError(f"RankShardSampler: rank {rank} not in [0, {num_replicas})")
        if block < 1:
            raise ValueError(f"RankShardSampler: block must be >= 1, got {block}")
        if not even and n < num_replicas:
            raise ValueError(
                f"RankShardSampler: {n} evaluation sample(s) cannot be shared by {num_replicas} "
                f"ranks (every rank needs at least one): use fewer devices or more samples"
            )
        super().__init__(base, num_replicas=num_replicas, rank=rank, shuffle=False)  # type: ignore[arg-type]
        self.base = base
        self.even = even
        self.n = n
        pos = np.arange(n)
        if even:
            self.positions = pos[: n - n % num_replicas][rank::num_replicas]
        else:
            if math.ceil(n / block) < num_replicas:
                block = math.ceil(n / num_replicas)
            self.positions = pos[(pos // block) % num_replicas == rank]
        self.block = block

    def __len__(self) -> int:
        return len(self.positions)

    def __iter__(self) -> Iterator[int]:
        idx = list(self.base)
        if len(idx) != self.n:
            raise RuntimeError(
                f"RankShardSampler: base sampler gave {len(idx)} indices, not {self.n}"
            )
        return iter([idx[p] for p in self.positions.tolist()])


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


def global_rank() -> int:
    """This process's global rank from the launcher's environment (0 outside distributed runs)."""
    for var in ("RANK", "SLURM_PROCID"):
        if os.environ.get(var, "").isdigit():
            return int(os.environ[var])
    local = int(os.environ.get("LOCAL_RANK", "0") or 0)
    node = int(os.environ.get("NODE_RANK", os.environ.get("GROUP_RANK", "0")) or 0)
    if node == 0:
        return local
    # world layout unknown here; any process that is not local rank 0 of node 0 is not rank zero
    return node * 1_000_000 + local


@dataclass(frozen=True)
class TrackingSettings:
    """MLflow: experiment, run name, profile and stage tags, params logged once; enabled=False skips MLflow."""

    experiment: str = "fusion"
    run_name: str = "fusion"
    profile: str = "default"
    stage: str = "train_fusion"
    enabled: bool = True
    params: Mapping[str, Any] = field(default_factory=dict)


def mlflow_logger(run: Any) -> Any:
    """Lightning's ``MLFlowLogger`` writing into the already started MLflow ``run`` (``None`` -> ``None``).

    The run's tracking URI is the active one (never Lightning's default ``./mlruns`` file store).
    """
    if run is None:
        return None
    import mlflow
    from lightning.pytorch.loggers import MLFlowLogger

    return MLFlowLogger(run_id=run.info.run_id, tracking_uri=mlflow.get_tracking_uri())


def log_final_metrics(logger: Any, metrics: Mapping[str, Any]) -> None:
    """Log the finite numeric ``metrics`` once (step 0) through ``logger`` (``None``: nothing)."""
    if logger is None:
        return
    finite = {
        k: float(v)
        for k, v in metrics.items()
        if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(float(v))
    }
    logger.log_metrics(finite, step=0)


@contextmanager
def tracked_run(
    experiment: str, run_name: str, *, enabled: bool = True, **run: Any
) -> Iterator[Any]:
    """:func:`traffictwin.mlops.tracking.start_run` (project tags, params logged once; ``run``
    holds its keyword arguments) on rank zero; ``None`` elsewhere or when disabled."""
    if not enabled or global_rank() != 0:
        yield None
        return
    from traffictwin.mlops.tracking import start_run

    with start_run(experiment, run_name, **run) as active:
        yield active


def log_checkpoint(path: str | Path, artifact_path: str = "checkpoints") -> None:
    """Log a checkpoint file as an artifact of the active MLflow run."""
    import mlflow

    mlflow.log_artifact(str(path), artifact_path=artifact_path)


def log_model(
    ckpt: Mapping[str, Any],
    meta: Mapping[str, Any],
    model: torch.nn.Module,
    input_example: np.ndarray,
    *,
    name: str = "model",
    metadata: Mapping[str, Any] | None = None,
) -> str:
    """Log a trained network as an MLflow model without pickled code; returns its model URI.

    The model directory (:mod:`traffictwin.mlops.model_artifact`) holds ``ckpt`` (a checkpoint
    of :data:`MODEL_FORMAT`, written with :func:`save_model_checkpoint`; loadable with
    ``weights_only=True``) as ``model.ckpt`` and ``meta`` (the architecture and meta, JSON) as
    ``model_meta.json``; the SHA-256 of every file is recorded on the logged model. The signature
    is inferred from ``input_example`` (float32 numpy) and ``model``'s output on it (``model``
    moved to CPU, eval mode; only run, never stored). Registering is the promotion gate's job
    (:func:`traffictwin.mlops.registry.ensure_version`, outside the cached stages); load it back
    with :func:`traffictwin.mlops.registry.load_registered` and the problem's loader.
    """
    import tempfile

    from mlflow.models import infer_signature

    from traffictwin.mlops import model_artifact as art

    info = ckpt.get("traffictwin") if isinstance(ckpt, Mapping) else None
    if not isinstance(info, Mapping) or info.get("format") != MODEL_FORMAT:
        raise CheckpointError(f"log_model: ckpt is not a '{MODEL_FORMAT}' checkpoint")
    model = model.to("cpu").eval()
    x = np.ascontiguousarray(input_example, dtype=np.float32)
    with torch.no_grad():
        y = model(torch.from_numpy(x))
    signature = infer_signature(x, y.float().numpy())
    with tempfile.TemporaryDirectory(prefix="tt-model-") as tmp:
        ck_path = save_model_checkpoint(Path(tmp) / art.CKPT, ckpt)
        meta_path = Path(tmp) / art.META
        from traffictwin.io.shards import sha256_file

        sealed = {**dict(meta), CKPT_SHA_KEY: sha256_file(ck_path)}  # the pair's seal, as on disk
        meta_path.write_text(json.dumps(sealed, indent=2, sort_keys=True, default=str) + "\n")
        uri, _ = art.log_model(
            {art.CKPT: ck_path, art.META: meta_path},
            problem=str(info.get("problem", "")),
            name=name,
            signature=signature,
            input_example=x,
            metadata=metadata,
        )
    return uri


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

    def best_row(self) -> dict[str, float]:
        """The history row of the best epoch (the last row when there is none)."""
        rows = self.history.rows
        return next(
            (r for r in rows if r.get("epoch") == self.best_epoch), rows[-1] if rows else {}
        )


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
    *,
    settings: TrainerSettings,
    loop: FitLoop,
    tracking: TrackingSettings,
    session: Any,
    tags: Mapping[str, Any] | None = None,
    params: Mapping[str, Any] | None = None,
    datasets: Sequence[tuple[str | Path, str]] = (),
    datamodule: Any = None,
    train_dataloaders: Any = None,
    val_dataloaders: Any = None,
    fast_dev_run: bool | int = False,
) -> Iterator[Fitted | None]:
    """The one training driver of every problem (fusion, registration, risk): the problem gives
    its LightningModule and its data (a DataModule or loaders); this owns the rest.

    Opens the tracked MLflow run (:func:`tracked_run`; params logged once, the ``datasets``
    ``(root, manifest hash)`` as MLflow datasets, the run id in the resume folder), builds the
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
            tags=dict(tags or {}),
            params={**tracking.params, **dict(params or {})},
            enabled=tracking.enabled,
            run_id=session.run_id(),
        ) as run,
    ):
        logger = mlflow_logger(run)
        if run is not None and session.resume_from is None:
            from traffictwin.mlops.tracking import log_dataset

            for root, digest in datasets:
                log_dataset(root, digest)
        session.started(run)
        history = History(loop.history, metrics=loop.history_metrics, logger=logger)
        # the best epoch's checkpoint in a folder of its own, which only this run writes: absent when
        # the run starts afresh (Session.workdir is new or just emptied, the resume folder already
        # holds resume.json), kept with the resume state when it resumes
        best_dir = Path(work) / BEST_DIR
        ckpt = best_checkpoint(best_dir, monitor=loop.monitor, mode=loop.mode)
        callbacks: list[Any] = [history, ckpt]
        if loop.patience is not None:
            callbacks.append(
                early_stopping(
                    loop.monitor, loop.patience, mode=loop.mode, min_delta=loop.min_delta
                )
            )
        callbacks.append(FiniteGuard(tracking.stage, hint=loop.hint, monitor=loop.monitor))
        callbacks += session.callbacks()
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
                datamodule=datamodule,
                train_dataloaders=train_dataloaders,
                val_dataloaders=val_dataloaders,
                ckpt_path=session.resume_from,
                # last.ckpt holds tensors and plain containers only: read without unpickling code
                weights_only=True,
            )
        seconds = time.perf_counter() - t0
        if not trainer.is_global_zero:
            yield None
            return
        path = getattr(ckpt, "best_model_path", "") if not fast_dev_run else ""
        best = None
        if path and Path(path).exists():
            # this run's own Lightning checkpoint (weights, optimiser state, loops: tensors and
            # plain containers), read like every other checkpoint without unpickling code
            best = torch.load(path, map_location="cpu", weights_only=True)
        yield Fitted(best, history, trainer, run, logger, seconds, str(settings.precision))
    session.finish()
