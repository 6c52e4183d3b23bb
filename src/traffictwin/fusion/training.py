"""Training of the evidential DeepLabV3+ registration-and-fusion network (paper III, IV).

- The data (:class:`TrainingSet`, :class:`FusionDataModule`, :func:`augment`):
  :mod:`traffictwin.fusion.training_data`.
- :class:`FusionLitModule` — Adam, ReduceLROnPlateau on the selection metric ``val/kld_full``
  (KLD(b) over the full mass vector), the loss ``fusion_model.loss.name`` (:data:`LOSSES`: ``mass``,
  ``paper`` = eqs. (6)-(7), ``paper_kl``),
  validation metrics ``val/loss``, ``val/kld``, ``val/kld_full``, ``val/dice_occ``, ``val/dice_free``
  (+ precision/recall), all reduced over DDP ranks; the same KLDs and Dice of the naive fusion
  (Dempster on the noisily prealigned inputs) as ``val/*_naive`` reference lines.
- :func:`fit_fusion` — the whole training run (seeding, trainer, callbacks, optional MLflow run,
  slim best checkpoint published atomically, meta, metrics, curves) of a :class:`FusionSettings`
  on a :class:`TrainingSet`; the stage ``pipelines/train_fusion.py`` only reads params and calls it.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torchmetrics import MeanMetric

from traffictwin import resume
from traffictwin import trainer as common
from traffictwin.evidential.dempster import dempster
from traffictwin.fusion.deeplab import (
    DeepLabSpec,
    DeepLabV3Plus,
    channels_last_supported,
    count_parameters,
)
from traffictwin.fusion.losses import (
    LOSSES,
    ConfusionCounts,
    dice_from_counts,
    evidence_to_masses,
    fusion_loss,
    kld,
    kld_full,
)
from traffictwin.fusion.model_config import (  # noqa: F401 - re-exported: the stage's settings
    AugmentConfig,
    FusionHParams,
    FusionModelConfig,
    FusionTrainConfig,
    LoopSettings,
    OptimConfig,
    spec_from_cfg,
)
from traffictwin.fusion.model_io import CKPT_FORMAT
from traffictwin.fusion.training_data import (
    DataSettings,
    FusionDataModule,
    TrainingSet,
    augment,
)
from traffictwin.mlops.tracking import DATA_TAG
from traffictwin.trainer import FitResult, ModelOutputs, TrackingSettings

log = logging.getLogger(__name__)

VAL_METRICS = ("val/loss", "val/kld", "val/kld_full", "val/dice_occ", "val/dice_free")
SELECTION_METRIC = (
    "val/kld_full"  # KLD(b): checkpoint, early stopping and LR plateau (lower is better)
)


# ---------------------------------------------------------------------------------------------
# model


class FusionLitModule(common.NetModule):
    """:class:`~traffictwin.trainer.NetModule` with :class:`DeepLabV3Plus` and the evidential loss."""

    def __init__(
        self,
        spec: Mapping[str, Any],
        hparams: Mapping[str, Any],
        meta: Mapping[str, Any] | None = None,
    ) -> None:
        hp = FusionHParams(**hparams)
        if hp.loss not in LOSSES:
            raise ValueError(f"unknown fusion loss {hp.loss!r}; expected one of {list(LOSSES)}")
        super().__init__(
            DeepLabV3Plus(DeepLabSpec.from_dict(spec)),
            fusion_loss,
            lr=hp.lr,
            weight_decay=hp.weight_decay,
            plateau=(hp.lr_factor, hp.lr_patience),
            monitor=SELECTION_METRIC,
        )
        self.save_hyperparameters(
            {"spec": dict(spec), "hparams": dict(hparams), "meta": dict(meta or {})}
        )
        self.spec = self.net.spec
        self.hp = hp
        self.loss_settings = LOSSES[hp.loss].settings(**hp.loss_settings)
        # NHWC only where oneDNN supports every layer (see channels_last_supported)
        self.channels_last = self.hp.channels_last and channels_last_supported(self.net)
        if self.hp.channels_last and not self.channels_last:
            log.warning("channels_last off: a strided 1x1 conv with < 8 input channels (oneDNN)")
        if self.channels_last:
            self.net = self.net.to(memory_format=torch.channels_last)
        # validation metrics (torchmetrics: accumulated over batches, reduced over DDP ranks)
        self.val_means = torch.nn.ModuleDict(
            {k: MeanMetric() for k in ("loss", "kld", "kld_full", "kld_naive", "kld_full_naive")}
        )
        self.val_counts = ConfusionCounts()
        self.val_counts_naive = ConfusionCounts()
        self._aug_gen: torch.Generator | None = None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(self._layout(x))

    def _layout(self, x: torch.Tensor) -> torch.Tensor:
        return x.contiguous(memory_format=torch.channels_last) if self.channels_last else x

    def on_train_start(self) -> None:
        seed = int(self.hparams["meta"].get("seed", 0)) + 7919 * int(self.global_rank)
        self._aug_gen = torch.Generator().manual_seed(seed)

    def training_step(
        self, batch: tuple[torch.Tensor, torch.Tensor], batch_idx: int
    ) -> torch.Tensor:
        x, y = batch
        if self.hp.augment_flip or self.hp.augment_rotation_deg > 0:
            x, y = augment(
                x,
                y,
                flip=self.hp.augment_flip,
                max_rotation_deg=self.hp.augment_rotation_deg,
                generator=self._aug_gen,
            )
        e = self.net(self._layout(x)).float()
        loss = self.loss_fn(self.hp.loss, e, y.float(), self.loss_settings, self.current_epoch)
        self.log(
            "train/loss", loss, on_step=False, on_epoch=True, sync_dist=True, batch_size=x.shape[0]
        )
        return loss

    def validation_step(self, batch: tuple[torch.Tensor, torch.Tensor], batch_idx: int) -> None:
        x, y = batch
        e = self.net(self._layout(x)).float()
        y = y.float()
        loss = self.loss_fn(self.hp.loss, e, y, self.loss_settings)  # no regulariser
        m, _ = evidence_to_masses(e)
        # reference: the naive fusion of the same (noisily prealigned) inputs, Dempster's rule
        naive = dempster(x[:, :2].float(), x[:, 2:].float())
        n = x.shape[0]
        for name, value in (
            ("loss", loss),
            ("kld", kld(m, y).mean()),
            ("kld_full", kld_full(m, y).mean()),
            ("kld_naive", kld(naive, y).mean()),
            ("kld_full_naive", kld_full(naive, y).mean()),
        ):
            self.val_means[name].update(value, weight=n)
        self.val_counts.update(m, y)
        self.val_counts_naive.update(naive, y)

    def on_validation_epoch_end(self) -> None:
        for name, metric in self.val_means.items():
            self.log(f"val/{name}", metric.compute())
            metric.reset()
        for suffix, metric in (("", self.val_counts), ("_naive", self.val_counts_naive)):
            counts = metric.compute().cpu()
            metric.reset()
            for k, v in dice_from_counts(counts).items():
                if suffix and not k.startswith("dice"):
                    continue
                self.log(f"val/{k}{suffix}", float(v) if math.isfinite(v) else 0.0)


# ---------------------------------------------------------------------------------------------
# the ``fusion_model`` config group (validated once by the stage with traffictwin.config.typed)


# ---------------------------------------------------------------------------------------------
# a whole training run


@dataclass(frozen=True)
class FusionSettings:
    """How the fusion network trains: its ``spec`` and ``hparams``, the ``data`` and ``loop``
    settings and the model's ``network`` name (None: the configuration's name)."""

    spec: DeepLabSpec
    hparams: FusionHParams = FusionHParams()
    data: DataSettings = DataSettings()
    loop: LoopSettings = LoopSettings()
    network: str | None = None


def fit_fusion(
    pairs: TrainingSet,
    *,
    model: FusionSettings,
    trainer_settings: common.TrainerSettings,
    outputs: ModelOutputs,
    tracking: TrackingSettings | None = None,
    tensors: Mapping[str, tuple[torch.Tensor, torch.Tensor]] | None = None,
    resume_dir: str | Path | None = None,
    **trainer_extra: Any,
) -> FitResult | None:
    """Train on ``pairs``' train split, select on val/kld_full (KLD(b)), publish the best model.

    Writes ``outputs`` (rank zero, each atomically, only after training succeeded): the slim
    Lightning checkpoint, its meta (architecture, grid, cfg, data manifest hash), the best-epoch
    metrics (epochs, ``samples_seen``) and the per-epoch curves CSV:
    identical runs write identical bytes. What differs between runs (MLflow run id and model URI,
    training seconds and pairs per second) is only in the returned :class:`FitResult`.
    ``best_epoch`` (metrics, meta, the checkpoint's ``epoch``) and the curves' ``epoch`` are
    0-based, Lightning's count; human-readable lines say ``best_epoch + 1`` of ``epochs``
    (:class:`traffictwin.trainer.History`).
    Returns ``None`` on other DDP ranks. ``tensors``: the splits already in memory (tests).

    ``resume_dir``: a folder outside the outputs where the run keeps its training state
    (:mod:`traffictwin.resume`); a run killed before the end continues from there when run
    again with the same arguments, data and code (same weights as without the kill); removed
    after the outputs are written.
    """
    common.seed_everything(pairs.seed)
    spec, hparams = model.spec, model.hparams
    pairs.grid.check_divisible(spec.output_stride, name="grid (fusion network input)")
    manifest_hash = pairs.manifest_hash()
    tracking = tracking or TrackingSettings("fusion", "fusion", stage="train_fusion", enabled=False)
    meta_base = _meta_base(pairs, model, manifest_hash, tracking.profile)
    module = FusionLitModule(spec.as_dict(), asdict(hparams), meta=meta_base)
    dm = FusionDataModule(pairs.root, model.data, pairs.seed, pairs.grid, tensors=tensors)
    n_params = count_parameters(module.net)
    session = resume.Session(
        resume_dir,
        {
            "problem": "fusion",
            "spec": spec.as_dict(),
            "hparams": asdict(hparams),
            "data": asdict(model.data),
            "loop": asdict(model.loop),
            "trainer": trainer_settings.as_dict(),
            "meta": meta_base,
            "data_root": str(pairs.root),
            "tensors": tensors is not None,
            "extra": trainer_extra,
        },
    )
    if session.resume_from is not None:
        log.info("resuming %s from %s", tracking.stage, session.resume_from)
    record = common.RunRecord(
        tags={
            DATA_TAG: manifest_hash,
            "cfg": pairs.cfg_name,
            "network": meta_base["network"],
            "loss": hparams.loss,
        },
        params={"data.manifest_hash": manifest_hash, "model.param_count": n_params},
        datasets=[(pairs.root, manifest_hash)],
    )
    loop = _fit_loop(model.loop, trainer_extra)
    return common.fit_and_publish(
        module,
        dm,
        settings=trainer_settings,
        loop=loop,
        tracking=tracking,
        session=session,
        record=record,
        publish=lambda fitted: _publish(fitted, pairs, model, dm, meta_base, outputs, n_params),
    )


def _meta_base(
    pairs: TrainingSet, model: FusionSettings, manifest_hash: str, profile: str
) -> dict[str, Any]:
    """The provenance every fusion model records (module hyperparameters and model meta)."""
    return {
        "cfg": pairs.cfg_name,
        "network": model.network or pairs.cfg_name,
        "inputs": pairs.inputs,
        "loss": model.hparams.loss,
        "noise": dict(pairs.noise),
        "grid": pairs.grid_dict(),
        "seed": int(pairs.seed),
        "data_manifest_hash": manifest_hash,
        "profile": profile,
    }


def _fit_loop(loop: LoopSettings, trainer_extra: Mapping[str, Any]) -> common.FitLoop:
    """The driver's loop: select, stop early and decay the learning rate on KLD(b)."""
    return common.FitLoop(
        monitor=SELECTION_METRIC,
        max_epochs=loop.max_epochs,
        patience=loop.early_stopping_patience,
        min_delta=loop.early_stopping_min_delta,
        hint="fusion_model.optim.lr",
        gradient_clip_val=loop.gradient_clip_val,
        trainer_extra=trainer_extra,
    )


def _samples_seen(fitted: common.Fitted, data: DataSettings, n_train: int) -> int:
    """Training pairs of the whole run: per epoch each of the world_size ranks trains on
    k // world_size pairs (k = the epoch's draw) in full batches."""
    k = data.train_samples_per_epoch if data.train_samples_per_epoch > 0 else n_train
    world = int(fitted.trainer.world_size)
    per_rank = min(k, n_train) // world // data.batch_size * data.batch_size
    return per_rank * world * len(fitted.history.rows)


def _publish(
    fitted: common.Fitted,
    pairs: TrainingSet,
    model: FusionSettings,
    dm: FusionDataModule,
    meta_base: dict[str, Any],
    outputs: ModelOutputs,
    n_params: int,
) -> FitResult:
    """The best epoch as the fusion model: MLflow model (with tracking), files, result."""
    if fitted.best is None:
        raise RuntimeError("training produced no checkpoint (no validation epoch finished?)")
    spec, hparams = model.spec, model.hparams
    slim = fitted.model_checkpoint("fusion", spec.as_dict())
    n_train = len(dm.train_set) if dm.train_set is not None else 0
    metrics = common.fit_metrics(
        fitted,
        model.loop.max_epochs,
        samples_seen=_samples_seen(fitted, model.data, n_train),
        param_count=n_params,
        train_pairs=n_train,
        val_pairs=len(dm.val_set) if dm.val_set is not None else 0,
    )
    meta = {
        **meta_base,
        "format": CKPT_FORMAT,
        "architecture": spec.as_dict(),
        "param_count": n_params,
        "hparams": asdict(hparams),
        "best_epoch": slim["epoch"],
        "best_val_loss": metrics.get("val/loss"),
        "selection_metric": SELECTION_METRIC,
        "best_val_kld_full": metrics.get(SELECTION_METRIC),
        "best_val_dice_occ": metrics.get("val/dice_occ"),
    }
    slim["traffictwin"].update(json.loads(json.dumps(meta, default=str)))
    model_uri = None
    if fitted.run is not None:
        best_module = FusionLitModule(spec.as_dict(), asdict(hparams), meta_base)
        best_module.load_state_dict(slim["state_dict"])
        net = best_module.net.to(memory_format=torch.contiguous_format)  # plain NCHW for serving
        g = pairs.grid
        example = np.zeros((1, spec.backbone.in_channels, g.rows, g.cols), dtype=np.float32)
        metadata = {"cfg": pairs.cfg_name, "data_manifest_hash": meta_base["data_manifest_hash"]}
        model_uri = common.log_fitted_model(fitted, slim, meta, metrics, net, example, metadata)
    common.publish(fitted, outputs, slim, meta, metrics)
    return common.fit_result(fitted, outputs, meta, metrics, model_uri)
