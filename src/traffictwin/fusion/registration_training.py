"""Training of the learned registration (:mod:`traffictwin.fusion.learned_registration`).

- :func:`load_registration_split` — a prealigned split with the correction targets: inputs,
  label, the true pixel sampling matrix ``M`` of map 2 and the rotation centre (noisy sensor-2
  position, pixels);
- :func:`perturb` — augmentation: map 2 warped by an extra random rigid motion about the rotation
  centre (drawn from the configuration's pose-noise model scaled by ``augment_scale``), the target
  updated to ``G⁻¹ M``; the label (map 1's frame) is unchanged;
- :class:`RegistrationLitModule` — Adam, :func:`~traffictwin.fusion.registration_loss.registration_loss`,
  validation metrics ``val/loss``, ``val/trans_err_m`` / ``val/rot_err_deg`` (mean), ``val/success_rate``
  (error < 0.5 m and < 1°), ``val/trans_err_m_median``, all over the whole validation subset;
- :func:`fit_registration` — the training run of a :class:`RegistrationSettings` on a
  :class:`~traffictwin.fusion.training_data.TrainingSet` (seeding, trainer, MLflow run, best
  checkpoint and early stopping on ``val/loss``, meta, metrics, curves), like
  :func:`traffictwin.fusion.training.fit_fusion`.

Reading a trained registration back (:func:`load_registration_model`, re-exported here) is
:mod:`traffictwin.fusion.registration_io`, which imports no Lightning.
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
from torch.utils.data import DataLoader, RandomSampler, Subset, TensorDataset
from torchmetrics import CatMetric, MeanMetric

from traffictwin import resume
from traffictwin import trainer as common
from traffictwin.evidential.masses import check_masses
from traffictwin.evidential.noise import noise_sigmas
from traffictwin.fusion.learned_registration import (
    LearnedRegistration,
    RegistrationNetSpec,
    correction_target,
    rotation_about,
    warp_by,
)
from traffictwin.fusion.model_config import (  # noqa: F401 - re-exported: the stage's settings
    RegistrationModelConfig,
    RegistrationTrainConfig,
)
from traffictwin.fusion.pairs import evenly_spaced
from traffictwin.fusion.registration_io import (  # noqa: F401 - re-exported
    PROBLEM,
    load_registration_model,
)
from traffictwin.fusion.registration_loss import registration_loss
from traffictwin.fusion.training_data import TrainingSet
from traffictwin.grid import GridSpec
from traffictwin.io.shards import Dataset, DatasetError
from traffictwin.mlops.tracking import DATA_TAG
from traffictwin.trainer import FitResult, ModelOutputs, TrackingSettings

log = logging.getLogger(__name__)

# checkpoint and early stopping: the validation loss. The success rate of a few hundred pairs moves
# in steps of 0.5 % and plateaus while the pose errors still fall (ties would keep an early epoch).
SELECTION_METRIC = "val/loss"


# -- data ------------------------------------------------------------------------------------------------
def load_registration_split(
    root: str | Path, split: str, grid: GridSpec
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``inputs (N,4,H,W)``, ``label (N,2,H,W)``, true sampling matrices ``M (N,3,3)`` and rotation
    centres ``(N,2)`` (float32) of a prealigned ``split``; masses and poses checked, errors name the file."""

    def masses_ok(name: str, arrays: dict[str, np.ndarray]) -> None:
        xs = arrays["inputs"]
        for key, arr in (("inputs", xs[:, :2]), ("inputs", xs[:, 2:]), ("label", arrays["label"])):
            try:
                check_masses(arr, name=f"{root}/{name}: split '{split}' array '{key}'")
            except ValueError as exc:
                raise DatasetError(str(exc)) from None

    ds = Dataset(root, kind="prealigned", verify=False)  # each shard's hash: checked as it is read
    a = ds.load_all(
        split, keys=["inputs", "label", "rel_pose_noisy", "rel_pose_true"], check=masses_ok
    )
    x, y = a["inputs"], a["label"]
    if x.ndim != 4 or x.shape[1] != 4 or tuple(x.shape[2:]) != grid.shape:
        raise DatasetError(
            f"{root}: split '{split}' array 'inputs' must be (N, 4, {grid.rows}, {grid.cols}) "
            f"(params.yaml 'grid'), got {x.shape}"
        )
    for key in ("rel_pose_noisy", "rel_pose_true"):
        p = np.asarray(a[key], dtype=np.float64)
        if p.shape != (len(x), 3) or not np.isfinite(p).all():
            raise DatasetError(
                f"{root}: split '{split}' array '{key}' must be finite (N, 3) = ({len(x)}, 3) poses"
            )
    m, c = correction_target(a["rel_pose_noisy"], a["rel_pose_true"], grid)
    f32 = lambda v: torch.from_numpy(np.ascontiguousarray(v, dtype=np.float32))  # noqa: E731
    return f32(x), f32(y), f32(m), f32(c)


def perturb(
    inputs: torch.Tensor,
    m_true: torch.Tensor,
    centre: torch.Tensor,
    *,
    sigma_px: float,
    sigma_rad: float,
    prob: float,
    grid_shape: tuple[int, int],
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """With probability ``prob`` per pair, warp map 2 by a random rigid motion ``G`` about ``centre``
    (Gaussian yaw ``sigma_rad``, shift ``sigma_px`` per axis) and return the target ``G⁻¹ M``."""
    b = inputs.shape[0]
    if prob <= 0 or (sigma_px <= 0 and sigma_rad <= 0):
        return inputs, m_true
    z = torch.randn(b, 3, generator=generator)
    on = (torch.rand(b, generator=generator) < prob).float()
    g = rotation_about(z[:, 2] * sigma_rad * on, centre, z[:, :2] * sigma_px * on[:, None])
    warped = warp_by(inputs[:, 2:4], g, grid_shape).clamp(0.0, 1.0)
    s = warped.sum(1, keepdim=True)
    warped = torch.where(s > 1.0, warped / s.clamp_min(1e-12), warped)
    return torch.cat([inputs[:, :2], warped], 1), torch.linalg.solve(g, m_true)


# -- module --------------------------------------------------------------------------------------------
class RegistrationLitModule(common.NetModule):
    """:class:`~traffictwin.trainer.NetModule` around :class:`LearnedRegistration`."""

    def __init__(
        self,
        spec: Mapping[str, Any],
        grid: Mapping[str, Any],
        hparams: Mapping[str, Any],
        meta: Mapping[str, Any] | None = None,
    ) -> None:
        g = GridSpec(**dict(grid))
        net = LearnedRegistration(
            RegistrationNetSpec.from_dict(dict(spec)), g, hparams.get("min_gain", 0.0)
        )
        super().__init__(
            net, registration_loss, lr=hparams["lr"], weight_decay=hparams.get("weight_decay", 0.0)
        )
        self.save_hyperparameters(
            {
                "spec": dict(spec),
                "grid": dict(grid),
                "hparams": dict(hparams),
                "meta": dict(meta or {}),
            }
        )
        self.hp = dict(hparams)
        self.val_loss = MeanMetric()
        self.val_trans = CatMetric()
        self.val_rot = CatMetric()
        self._gen: torch.Generator | None = None

    def on_train_start(self) -> None:
        seed = int(self.hparams["meta"].get("seed", 0)) + 7919 * int(self.global_rank)
        self._gen = torch.Generator().manual_seed(seed)

    def training_step(self, batch: tuple[torch.Tensor, ...], batch_idx: int) -> torch.Tensor:
        x, y, m, c = batch
        x, m = perturb(
            x,
            m,
            c,
            sigma_px=self.hp["augment_sigma_px"],
            sigma_rad=self.hp["augment_sigma_rad"],
            prob=self.hp["augment_prob"],
            grid_shape=self.net.grid_shape,
            generator=self._gen,
        )
        loss, parts = self.loss_fn(self.net, x, y, m, c, map_weight=self.hp["map_weight"])
        n = x.shape[0]
        self.log("train/loss", loss, on_step=False, on_epoch=True, sync_dist=True, batch_size=n)
        for k, v in parts.items():
            self.log(f"train/{k}", v, on_step=False, on_epoch=True, sync_dist=True, batch_size=n)
        return loss

    def validation_step(self, batch: tuple[torch.Tensor, ...], batch_idx: int) -> None:
        x, y, m, c = batch
        loss, _ = self.loss_fn(self.net, x, y, m, c, map_weight=self.hp["map_weight"])
        self.val_loss.update(loss, weight=x.shape[0])
        est = self.net.estimate(x, c).m.double()
        t, r = correction_errors(est, m.double(), c.double(), self.net.cell)
        self.val_trans.update(t)
        self.val_rot.update(r)

    def on_validation_epoch_end(self) -> None:
        self.log("val/loss", self.val_loss.compute())
        t, r = self.val_trans.compute().double(), self.val_rot.compute().double()
        for metric in (self.val_loss, self.val_trans, self.val_rot):
            metric.reset()
        self.log("val/trans_err_m", t.mean().float())
        self.log("val/trans_err_m_median", t.median().float())
        self.log("val/rot_err_deg", r.mean().float())
        self.log("val/success_rate", ((t <= 0.5) & (r <= 1.0)).double().mean().float())


def correction_errors(
    m_est: torch.Tensor, m_true: torch.Tensor, centre: torch.Tensor, cell: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Pose errors implied by two sampling matrices: translation (m) of map 2's sensor
    (``M⁻¹ c``) and yaw (deg)."""
    c1 = torch.cat([centre, torch.ones_like(centre[:, :1])], 1).unsqueeze(-1)
    pe = (torch.linalg.solve(m_est, c1)).squeeze(-1)[:, :2]
    pt = (torch.linalg.solve(m_true, c1)).squeeze(-1)[:, :2]
    rel = torch.linalg.solve(m_true, m_est)
    yaw = torch.atan2(rel[:, 1, 0], rel[:, 0, 0])
    return torch.linalg.vector_norm(pe - pt, dim=1) * cell, torch.rad2deg(yaw.abs())


# -- a whole training run --------------------------------------------------------------------------------
@dataclass(frozen=True)
class RegistrationSettings:
    """How the learned registration trains: the network ``spec``, its ``train`` settings, the
    fallback's ``min_gain`` and the pose-noise model ``augment_noise`` = (r m, alpha deg) the
    augmentation draws from (None: the training set's own ``noise``), scaled by
    ``train.augment_scale``."""

    spec: RegistrationNetSpec
    train: RegistrationTrainConfig
    min_gain: float = 0.0
    augment_noise: tuple[float, float] | None = None


def fit_registration(
    pairs: TrainingSet,
    *,
    model: RegistrationSettings,
    trainer_settings: common.TrainerSettings,
    outputs: ModelOutputs,
    tracking: TrackingSettings | None = None,
    resume_dir: str | Path | None = None,
) -> FitResult | None:
    """Train on ``pairs``' train split, keep the best epoch on ``val/loss``, publish it.

    Writes ``outputs`` (rank zero, each atomically, only after training succeeded): the slim
    checkpoint, its meta, the best-epoch metrics and the per-epoch curves; logs an MLflow run
    (params, curves, the checkpoint and the model as weights + JSON,
    :func:`traffictwin.trainer.log_model`) when ``tracking`` is enabled (registering it is the
    promotion gate's job). A non-finite validation loss fails the run (nothing is published).
    Identical runs write identical bytes: the MLflow run id, model URI and training time are only
    in the result. Returns ``None`` on other DDP ranks. ``resume_dir``: as for
    :func:`traffictwin.fusion.training.fit_fusion` (:mod:`traffictwin.resume`). ``best_epoch``
    is 0-based in the files, 1-based in messages (:class:`traffictwin.trainer.History`).
    """
    common.seed_everything(pairs.seed)
    manifest_hash = pairs.manifest_hash()
    train_dl, val_dl = _loaders(pairs, model.train)
    tracking = tracking or TrackingSettings(
        "fusion", "registration", stage="train_registration", enabled=False
    )
    meta_base = _meta_base(pairs, model, manifest_hash, tracking.profile)
    hparams = _hparams(model, pairs)
    module = RegistrationLitModule(asdict(model.spec), pairs.grid_dict(), hparams, meta_base)
    n_params = _param_count(module)
    session = resume.Session(
        resume_dir,
        {
            "problem": PROBLEM,
            "spec": asdict(model.spec),
            "train": asdict(model.train),
            "min_gain": model.min_gain,
            "trainer": trainer_settings.as_dict(),
            "meta": meta_base,
            "data_root": str(pairs.root),
        },
    )
    record = common.RunRecord(
        tags={
            DATA_TAG: manifest_hash,
            "cfg": pairs.cfg_name,
            "network": "learned",
            "method": "learned",
        },
        params={"data.manifest_hash": manifest_hash, "model.param_count": n_params},
        datasets=[(pairs.root, manifest_hash)],
    )
    loop = common.FitLoop(
        monitor=SELECTION_METRIC,
        max_epochs=model.train.max_epochs,
        patience=model.train.early_stopping_patience,
        hint="registration_model.train.lr",
    )
    loaders = (train_dl, val_dl)
    return common.fit_and_publish(
        module,
        loaders,
        settings=trainer_settings,
        loop=loop,
        tracking=tracking,
        session=session,
        record=record,
        publish=lambda fitted: _publish(fitted, pairs, model, module, loaders, meta_base, outputs),
    )


def _meta_base(
    pairs: TrainingSet, model: RegistrationSettings, manifest_hash: str, profile: str
) -> dict[str, Any]:
    """The provenance the learned registration records (module hyperparameters and model meta)."""
    return {
        "cfg": pairs.cfg_name,
        "network": "learned",
        "method": "learned",
        "noise": dict(pairs.noise),
        "grid": pairs.grid_dict(),
        "seed": int(pairs.seed),
        "data_manifest_hash": manifest_hash,
        "profile": profile,
        "min_gain": float(model.min_gain),
    }


def _param_count(module: RegistrationLitModule) -> int:
    return sum(p.numel() for p in module.net.parameters())


def _loaders(pairs: TrainingSet, train: RegistrationTrainConfig) -> tuple[DataLoader, DataLoader]:
    """The training loader (a seeded draw of ``train_samples_per_epoch`` pairs per epoch, full
    batches) and the validation loader (``val_samples`` evenly spaced pairs)."""
    tensors = {s: load_registration_split(pairs.root, s, pairs.grid) for s in ("train", "val")}
    if len(tensors["train"][0]) < train.batch_size:
        raise DatasetError(
            f"{pairs.root}: {len(tensors['train'][0])} training pairs < batch_size {train.batch_size}"
        )
    train_set = TensorDataset(*tensors["train"])
    val_full = TensorDataset(*tensors["val"])
    val_set = Subset(val_full, evenly_spaced(len(val_full), train.val_samples).tolist())
    k = train.train_samples_per_epoch
    k = len(train_set) if k <= 0 else min(k, len(train_set))
    gen = torch.Generator().manual_seed(pairs.seed)
    sampler = RandomSampler(train_set, replacement=False, num_samples=k, generator=gen)
    train_dl = DataLoader(train_set, batch_size=train.batch_size, sampler=sampler, drop_last=True)
    return train_dl, DataLoader(val_set, batch_size=train.batch_size, shuffle=False)


def _hparams(model: RegistrationSettings, pairs: TrainingSet) -> dict[str, Any]:
    """The module's hyperparameters; the augmentation's sigmas (px, rad) from the noise model
    ``model.augment_noise`` (default: ``pairs.noise``, a single configuration) scaled by
    ``train.augment_scale``."""
    train = model.train
    noise = pairs.noise
    r_aug, a_aug = (
        model.augment_noise if model.augment_noise is not None else (noise["r"], noise["alpha"])
    )
    sig_xy, sig_yaw = noise_sigmas(float(r_aug), float(a_aug))
    return {
        "lr": train.lr,
        "weight_decay": train.weight_decay,
        "min_gain": model.min_gain,
        "map_weight": train.map_weight,
        "augment_prob": train.augment_prob,
        "augment_sigma_px": train.augment_scale * sig_xy / pairs.grid.cell,
        "augment_sigma_rad": train.augment_scale * sig_yaw,
    }


def _publish(
    fitted: common.Fitted,
    pairs: TrainingSet,
    model: RegistrationSettings,
    module: RegistrationLitModule,
    loaders: tuple[DataLoader, DataLoader],
    meta_base: dict[str, Any],
    outputs: ModelOutputs,
) -> FitResult:
    """The best epoch as the learned registration: checks, MLflow model (with tracking), files."""
    if fitted.best is None:
        raise RuntimeError(
            "learned registration training produced no checkpoint (no finite val/loss: NaN/inf in the data or the learning rate?)"
        )
    slim = fitted.model_checkpoint(PROBLEM, asdict(model.spec))
    row = fitted.best_row()
    if not all(
        math.isfinite(float(row.get(k, float("nan")))) for k in ("val/loss", "val/trans_err_m")
    ):
        raise RuntimeError(
            f"learned registration: best epoch {slim['epoch'] + 1} (1-based) has non-finite "
            f"validation metrics {row}"
        )
    train, (train_dl, val_dl) = model.train, loaders
    k = len(train_dl.sampler)  # type: ignore[arg-type]
    metrics = common.fit_metrics(
        fitted,
        train.max_epochs,
        samples_seen=k // train.batch_size * train.batch_size * len(fitted.history.rows),
        param_count=_param_count(module),
        train_pairs=len(train_dl.dataset),  # type: ignore[arg-type]
        val_pairs=len(val_dl.dataset),  # type: ignore[arg-type]
    )
    meta = {
        **meta_base,
        "problem": PROBLEM,
        "architecture": asdict(model.spec),
        "param_count": _param_count(module),
        "hparams": dict(module.hp),
        "best_epoch": slim["epoch"],
        "selection_metric": SELECTION_METRIC,
        "best_val_loss": metrics.get("val/loss"),
        "best_val_success_rate": metrics.get("val/success_rate"),
    }
    slim["traffictwin"].update(json.loads(json.dumps(meta, default=str)))
    uri = None
    if fitted.run is not None:
        net = LearnedRegistration(model.spec, pairs.grid, model.min_gain)
        net.load_state_dict(common.net_state_dict(slim))
        example = np.zeros((1, 4, pairs.grid.rows, pairs.grid.cols), dtype=np.float32)
        metadata = {
            "cfg": pairs.cfg_name,
            "data_manifest_hash": meta["data_manifest_hash"],
            "method": "learned",
        }
        uri = common.log_fitted_model(fitted, slim, meta, metrics, net.eval(), example, metadata)
    common.publish(fitted, outputs, slim, meta, metrics)
    return common.fit_result(fitted, outputs, meta, metrics, uri)
