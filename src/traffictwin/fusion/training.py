"""Training of the evidential DeepLabV3+ registration-and-fusion network (paper III, IV).

- :func:`augment` — random horizontal/vertical flips and a random rotation in
  ``[-max_rotation_deg, max_rotation_deg]`` applied with one ``grid_sample`` to inputs and
  label together (paper III-D). Bilinear sampling with zero padding mixes masses convexly with
  "unknown" (0, 0), so every cell stays on the simplex (``m_F, m_O >= 0``, ``m_F + m_O <= 1``).
- :class:`FusionDataModule` — the ``prealigned`` dataset's ``train``/``val`` splits held in memory;
  a seeded random subset of ``train_samples_per_epoch`` pairs per epoch (a fresh draw each epoch),
  a fixed evenly spaced subset of ``val_samples`` validation pairs. Under DDP the ranks split
  each epoch's draw (``train_samples_per_epoch`` pairs in all, not per rank) and the validation
  pairs (each on exactly one rank): :class:`~traffictwin.trainer.RankShardSampler`.
- :class:`FusionLitModule` — Adam, ReduceLROnPlateau on the selection metric ``val/kld_full``
  (KLD(b) over the full mass vector), the loss ``fusion_model.loss.name`` (:data:`LOSSES`: ``mass``,
  ``paper`` = eqs. (6)-(7), ``paper_kl``),
  validation metrics ``val/loss``, ``val/kld``, ``val/kld_full``, ``val/dice_occ``, ``val/dice_free``
  (+ precision/recall), all reduced over DDP ranks; the same KLDs and Dice of the naive fusion
  (Dempster on the noisily prealigned inputs) as ``val/*_naive`` reference lines.
- :func:`fit_fusion` — the whole training run (seeding, trainer, callbacks, optional MLflow run,
  slim best checkpoint published atomically, meta, metrics, curves); the stage
  ``pipelines/train_fusion.py`` only reads params and calls it.
"""

from __future__ import annotations

import json
import logging
import math
import tempfile
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
import torch.nn.functional as F
from torch.utils.data import (
    DataLoader,
    RandomSampler,
    Sampler,
    SequentialSampler,
    Subset,
    TensorDataset,
)
from torchmetrics import MeanMetric

from traffictwin import resume
from traffictwin import trainer as common
from traffictwin.config import ConfigError
from traffictwin.config import spec as setting
from traffictwin.evidential.dempster import dempster
from traffictwin.evidential.masses import check_masses
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
from traffictwin.fusion.model_io import CKPT_FORMAT
from traffictwin.fusion.pairs import evenly_spaced
from traffictwin.grid import GridSpec
from traffictwin.io.atomic import write_json_atomic
from traffictwin.io.shards import Dataset, DatasetError
from traffictwin.mlops.tracking import DATA_TAG
from traffictwin.trainer import TrackingSettings

log = logging.getLogger(__name__)

VAL_METRICS = ("val/loss", "val/kld", "val/kld_full", "val/dice_occ", "val/dice_free")
SELECTION_METRIC = (
    "val/kld_full"  # KLD(b): checkpoint, early stopping and LR plateau (lower is better)
)


# ---------------------------------------------------------------------------------------------
# augmentation


def augmentation_matrices(
    n: int,
    height: int,
    width: int,
    *,
    flip: bool,
    max_rotation_deg: float,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """``(n, 2, 3)`` ``affine_grid`` matrices: random flips (p = 0.5 per axis) and rotation about the centre.

    The rotation is in metric (cell) space — cells are square — so the normalised-coordinate
    matrix is ``D^-1 R Fl D`` with ``D = diag(W/2, H/2)``.
    """
    g = generator
    ang = (torch.rand(n, generator=g, dtype=torch.float64) * 2.0 - 1.0) * math.radians(
        max_rotation_deg
    )
    if flip:
        fx = torch.where(torch.rand(n, generator=g) < 0.5, -1.0, 1.0).double()
        fy = torch.where(torch.rand(n, generator=g) < 0.5, -1.0, 1.0).double()
    else:
        fx = torch.ones(n, dtype=torch.float64)
        fy = torch.ones(n, dtype=torch.float64)
    c, s = torch.cos(ang), torch.sin(ang)
    sx, sy = width / 2.0, height / 2.0
    a = torch.zeros(n, 2, 3, dtype=torch.float64)
    # [x_in; y_in]_pix = R @ diag(fx, fy) @ [x_out; y_out]_pix, then normalised
    a[:, 0, 0] = c * fx
    a[:, 0, 1] = -s * fy * sy / sx
    a[:, 1, 0] = s * fx * sx / sy
    a[:, 1, 1] = c * fy
    return a.float()


def augment(
    inputs: torch.Tensor,
    label: torch.Tensor,
    *,
    flip: bool = True,
    max_rotation_deg: float = 20.0,
    mode: str = "bilinear",
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Apply the same random flip + rotation to ``inputs (N, C, H, W)`` and ``label (N, 2, H, W)``.

    Outside the rotated map the masses are (0, 0) (unknown). ``generator`` (CPU) makes the draw
    reproducible.
    """
    if inputs.shape[0] != label.shape[0] or inputs.shape[-2:] != label.shape[-2:]:
        raise ValueError(
            f"inputs {tuple(inputs.shape)} and label {tuple(label.shape)} must share N, H, W"
        )
    n, c, h, w = inputs.shape
    if not flip and max_rotation_deg <= 0:
        return inputs, label
    theta = augmentation_matrices(
        n, h, w, flip=flip, max_rotation_deg=max_rotation_deg, generator=generator
    )
    theta = theta.to(device=inputs.device, dtype=inputs.dtype)
    both = torch.cat([inputs, label.to(inputs.dtype)], dim=1)
    grid = F.affine_grid(theta, list(both.shape), align_corners=False)
    out = F.grid_sample(both, grid, mode=mode, padding_mode="zeros", align_corners=False)
    return out[:, :c], out[:, c:].to(label.dtype)


# ---------------------------------------------------------------------------------------------
# data


@dataclass(frozen=True)
class DataSettings:
    """How the prealigned dataset feeds training.

    batch_size: pairs per step; train_samples_per_epoch: pairs drawn (without replacement) per
    epoch, 0 = all; val_samples: fixed validation pairs, 0 = all; num_workers: loader workers.
    """

    batch_size: int = 8
    train_samples_per_epoch: int = 0
    val_samples: int = 0
    num_workers: int = 0


def load_prealigned(
    root: str | Path, split: str, grid: GridSpec | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """``inputs (N, 4, H, W)``, ``label (N, 2, H, W)`` float32 tensors of ``split`` (checked against
    ``grid``). Every shard read is checked against the manifest's SHA-256 and its masses (finite,
    on the simplex) as it is loaded (:meth:`~traffictwin.io.shards.Dataset.load_all`)."""

    def masses_ok(name: str, a: dict[str, np.ndarray]) -> None:
        # NaN, negative or off-simplex masses fail here, before any training
        for key, arr in (("inputs", a["inputs"][:, 0:2]), ("inputs", a["inputs"][:, 2:4])):
            _check_masses(arr, f"{root}/{name}: split '{split}' array '{key}'")
        _check_masses(a["label"], f"{root}/{name}: split '{split}' array 'label'")

    ds = Dataset(root, kind="prealigned", verify=False)  # each shard's hash: checked as it is read
    arrays = ds.load_all(split, keys=["inputs", "label"], check=masses_ok)
    x, y = arrays["inputs"], arrays["label"]
    if x.ndim != 4 or x.shape[1] != 4:
        raise DatasetError(f"{root}: array 'inputs' must be (N, 4, H, W), got {x.shape}")
    if y.shape != (x.shape[0], 2, *x.shape[2:]):
        raise DatasetError(
            f"{root}: array 'label' must be (N, 2, H, W) = {(x.shape[0], 2, *x.shape[2:])}, got {y.shape}"
        )
    if grid is not None and tuple(x.shape[2:]) != grid.shape:
        raise DatasetError(
            f"{root}: maps are {tuple(x.shape[2:])} cells but the grid parameter says {grid.shape} (rows, cols)"
        )
    return torch.from_numpy(np.ascontiguousarray(x, dtype=np.float32)), torch.from_numpy(
        np.ascontiguousarray(y, dtype=np.float32)
    )


def _check_masses(arr: np.ndarray, name: str) -> None:
    """:func:`~traffictwin.evidential.masses.check_masses` as a :class:`DatasetError`."""
    try:
        check_masses(arr, name=name)
    except ValueError as exc:
        raise DatasetError(str(exc)) from None


class FusionDataModule(L.LightningDataModule):
    """Prealigned pairs in memory; seeded per-epoch training subsets, a fixed validation subset."""

    def __init__(
        self,
        root: str | Path,
        settings: DataSettings,
        seed: int,
        grid: GridSpec | None = None,
        tensors: Mapping[str, tuple[torch.Tensor, torch.Tensor]] | None = None,
    ) -> None:
        super().__init__()
        self.root = Path(root)
        self.settings = settings
        self.seed = int(seed)
        self.grid = grid
        self._tensors = dict(tensors) if tensors else {}
        self.train_set: TensorDataset | None = None
        self.val_set: Subset | TensorDataset | None = None

    def setup(self, stage: str | None = None) -> None:
        if self.train_set is not None:
            return
        for split in ("train", "val"):
            if split not in self._tensors:
                self._tensors[split] = load_prealigned(self.root, split, self.grid)
        self.train_set = TensorDataset(*self._tensors["train"])
        val = TensorDataset(*self._tensors["val"])
        self.val_set = Subset(val, evenly_spaced(len(val), self.settings.val_samples).tolist())
        if len(self.train_set) < self.settings.batch_size:
            raise DatasetError(
                f"{self.root}: {len(self.train_set)} training pairs < batch_size {self.settings.batch_size}"
            )

    def train_dataloader(self) -> DataLoader:
        assert self.train_set is not None
        n = len(self.train_set)
        k = self.settings.train_samples_per_epoch
        k = n if k <= 0 else min(k, n)
        gen = torch.Generator().manual_seed(self.seed)
        sampler: Sampler[int] = RandomSampler(
            self.train_set, replacement=False, num_samples=k, generator=gen
        )
        world, rank = common.rank_layout(self.trainer)
        if world > 1:  # DDP: the same k-pair draw on every rank, k // world pairs each
            sampler = common.RankShardSampler(sampler, world, rank, even=True)
        return DataLoader(
            self.train_set,
            batch_size=self.settings.batch_size,
            sampler=sampler,
            drop_last=True,
            num_workers=self.settings.num_workers,
            persistent_workers=self.settings.num_workers > 0,
        )

    def val_dataloader(self) -> DataLoader:
        assert self.val_set is not None
        world, rank = common.rank_layout(self.trainer)
        # DDP: every validation pair on exactly one rank (no padding repeats), in the batches one
        # process would use, so the metrics reduced over the ranks are those of one process
        sampler = (
            common.RankShardSampler(
                SequentialSampler(self.val_set),
                world,
                rank,
                even=False,
                block=self.settings.batch_size,
            )
            if world > 1
            else None
        )
        return DataLoader(
            self.val_set,
            batch_size=self.settings.batch_size,
            shuffle=False,
            sampler=sampler,
            num_workers=self.settings.num_workers,
            persistent_workers=self.settings.num_workers > 0,
        )


# ---------------------------------------------------------------------------------------------
# model


@dataclass(frozen=True)
class FusionHParams:
    """Optimisation and loss settings (paper IV: Adam lr 0.01, plateau decay 0.5 / patience 10, o_w 3)."""

    lr: float = 0.01
    weight_decay: float = 0.0
    lr_factor: float = 0.5
    lr_patience: int = 10
    loss: str = "mass"  # LOSSES: mass | paper | paper_kl
    occupied_weight: float = 3.0
    kl_weight: float = 0.0  # paper_kl's KL regulariser weight (Sensoy et al.)
    kl_anneal_epochs: int = 10  # its weight ramps as min(1, epoch / kl_anneal_epochs)
    augment_flip: bool = True
    augment_rotation_deg: float = 20.0
    channels_last: bool = (
        True  # NHWC activations: ~1.2-1.5x faster convolutions on oneDNN CPUs and tensor cores
    )


def spec_from_cfg(model_cfg: Mapping[str, Any], in_channels: int = 4) -> DeepLabSpec:
    """DeepLabSpec from the ``fusion_model.architecture`` mapping (``backbone: {block, layers, base_width}``, ...)."""
    d = json.loads(json.dumps(dict(model_cfg)))
    bb = dict(d.pop("backbone", {}))
    bb.setdefault("in_channels", in_channels)
    if "output_stride" in bb:
        os_ = int(bb.pop("output_stride"))
        if os_ not in (8, 16, 32):
            raise ValueError(f"backbone.output_stride must be 8, 16 or 32, got {os_}")
        bb["dilate"] = {
            8: [False, True, True],
            16: [False, False, True],
            32: [False, False, False],
        }[os_]
        if os_ == 8:
            d.setdefault("aspp_rates", [12, 24, 36])
    return DeepLabSpec.from_dict({**d, "backbone": bb})


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
            raise ValueError(f"unknown fusion loss {hp.loss!r}; expected one of {LOSSES}")
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

    def _kl_weight(self) -> float:
        if self.hp.loss != "paper_kl" or self.hp.kl_weight <= 0:
            return 0.0
        return self.hp.kl_weight * min(1.0, self.current_epoch / max(1, self.hp.kl_anneal_epochs))

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
        loss = self.loss_fn(
            self.hp.loss,
            e,
            y.float(),
            occupied_weight=self.hp.occupied_weight,
            kl_weight=self._kl_weight(),
        )
        self.log(
            "train/loss", loss, on_step=False, on_epoch=True, sync_dist=True, batch_size=x.shape[0]
        )
        return loss

    def validation_step(self, batch: tuple[torch.Tensor, torch.Tensor], batch_idx: int) -> None:
        x, y = batch
        e = self.net(self._layout(x)).float()
        y = y.float()
        loss = self.loss_fn(self.hp.loss, e, y, occupied_weight=self.hp.occupied_weight)
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


@dataclass
class OptimConfig:
    """``fusion_model.optim``: Adam and the plateau decay of the learning rate."""

    lr: float = setting(min=1e-9)
    weight_decay: float = setting(min=0.0)
    lr_factor: float = setting(min=1e-6, max=1.0)
    lr_patience: int = setting(min=0)


@dataclass
class MassLossConfig:
    """``fusion_model.loss.mass``: o_w of the full-mass-vector KL loss."""

    occupied_weight: float = setting(min=1.0)


@dataclass
class PaperLossConfig:
    """``fusion_model.loss.paper``: eq. 7's occupied weight o_w."""

    occupied_weight: float = setting(min=1.0)


@dataclass
class PaperKLLossConfig:
    """``fusion_model.loss.paper_kl``: eq. 7 + the annealed KL regulariser."""

    occupied_weight: float = setting(min=1.0)
    kl_weight: float = setting(min=0.0)
    kl_anneal_epochs: int = setting(min=1)


@dataclass
class LossConfig:
    """``fusion_model.loss``: ``name`` picks the loss (``mass`` | ``paper`` | ``paper_kl``); each
    has its own block of weights (a variant with another loss uses that loss's block)."""

    name: str = setting(choices=LOSSES)
    mass: MassLossConfig = setting()
    paper: PaperLossConfig = setting()
    paper_kl: PaperKLLossConfig = setting()


@dataclass
class AugmentConfig:
    """``fusion_model.augment``: random flips and rotation (paper III-D)."""

    flip: bool = setting()
    rotation_deg: float = setting(min=0.0, max=180.0)


@dataclass
class FusionTrainConfig:
    """``fusion_model.train``: batches, epochs, stopping, memory format."""

    batch_size: int = setting(min=2)
    max_epochs: int = setting(min=1)
    train_samples_per_epoch: int = setting(min=0)
    val_samples: int = setting(min=0)
    early_stopping_patience: int = setting(min=1)
    early_stopping_min_delta: float = setting(min=0.0)
    gradient_clip_val: float | None = setting()
    channels_last: bool = setting()


@dataclass
class FusionModelConfig:
    """The ``fusion_model`` group: architecture (see :func:`spec_from_cfg`) and its training."""

    name: str = setting()
    architecture: dict[str, Any] = setting()
    optim: OptimConfig = setting()
    loss: LossConfig = setting()
    augment: AugmentConfig = setting()
    train: FusionTrainConfig = setting()

    def deeplab_spec(self, source: str | Path, key: str = "fusion_model") -> DeepLabSpec:
        """The network's :class:`DeepLabSpec`; an invalid architecture is a ConfigError."""
        try:
            return spec_from_cfg(self.architecture)
        except (TypeError, ValueError) as exc:
            full = f"{key}.architecture" if key else "architecture"
            raise ConfigError(f"{source}: '{full}' is invalid: {exc}") from None

    def hparams(self, loss: str | None = None) -> FusionHParams:
        """Optimisation and loss settings; ``loss`` overrides ``loss.name`` (a variant's loss)."""
        o, a = self.optim, self.augment
        name = loss or self.loss.name
        if name not in LOSSES:
            raise ConfigError(f"unknown fusion loss {name!r}; expected one of {LOSSES}")
        lo = getattr(self.loss, name)
        return FusionHParams(
            lr=o.lr,
            weight_decay=o.weight_decay,
            lr_factor=o.lr_factor,
            lr_patience=o.lr_patience,
            loss=name,
            occupied_weight=lo.occupied_weight,
            kl_weight=getattr(lo, "kl_weight", 0.0),
            kl_anneal_epochs=getattr(lo, "kl_anneal_epochs", 10),
            augment_flip=a.flip,
            augment_rotation_deg=a.rotation_deg,
            channels_last=self.train.channels_last,
        )

    def data(self, num_workers: int) -> DataSettings:
        return _from_fields(DataSettings, self.train, num_workers=num_workers)

    def loop(self) -> LoopSettings:
        return _from_fields(LoopSettings, self.train)


def _from_fields(cls: type, source: Any, **given: Any) -> Any:
    """``cls(**given)`` with every other field of ``cls`` taken from ``source``'s attribute of the same name."""
    names = {f.name for f in fields(cls)} - set(given)
    return cls(**{k: getattr(source, k) for k in names}, **given)


# ---------------------------------------------------------------------------------------------
# a whole training run


@dataclass(frozen=True)
class LoopSettings:
    """Epochs and stopping: max_epochs; early_stopping_patience (epochs without val/kld_full improvement)."""

    max_epochs: int = 200
    early_stopping_patience: int = 30
    early_stopping_min_delta: float = 0.0  # val KLD(b) must fall by more than this to count
    gradient_clip_val: float | None = None


@dataclass
class FitResult:
    """What :func:`fit_fusion` produced (paths written, best metrics, timing)."""

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


def fit_fusion(
    data_root: str | Path,
    *,
    spec: DeepLabSpec,
    hparams: FusionHParams,
    data: DataSettings,
    loop: LoopSettings,
    trainer_settings: common.TrainerSettings,
    seed: int,
    grid: GridSpec,
    cfg_name: str,
    noise: Mapping[str, float],
    ckpt_out: str | Path,
    network: str | None = None,
    inputs: str = "prealigned",
    meta_out: str | Path | None = None,
    metrics_out: str | Path | None = None,
    curves_out: str | Path | None = None,
    tracking: TrackingSettings | None = None,
    log_mlflow_model: bool = True,
    tensors: Mapping[str, tuple[torch.Tensor, torch.Tensor]] | None = None,
    resume_dir: str | Path | None = None,
    **trainer_extra: Any,
) -> FitResult | None:
    """Train on ``data_root``'s train split, select on val/kld_full (KLD(b)), publish the best model.

    Writes (rank zero, each atomically, only after training succeeded): ``ckpt_out`` (slim
    Lightning checkpoint), ``meta_out`` (architecture, grid, cfg, data manifest hash),
    ``metrics_out`` (best-epoch metrics, epochs, ``samples_seen``), ``curves_out`` (per-epoch CSV):
    identical runs write identical bytes. What differs between runs (MLflow run id and model URI,
    training seconds and pairs per second) is only in the returned :class:`FitResult`.
    ``best_epoch`` (metrics, meta, the checkpoint's ``epoch``) and the curves' ``epoch`` are
    0-based, Lightning's count; human-readable lines say ``best_epoch + 1`` of ``epochs``
    (:class:`traffictwin.trainer.History`).
    Returns ``None`` on other DDP ranks.

    ``resume_dir``: a folder outside the outputs where the run keeps its training state
    (:mod:`traffictwin.resume`); a run killed before the end continues from there when run
    again with the same arguments, data and code (same weights as without the kill); removed
    after the outputs are written.
    """
    common.seed_everything(seed)
    grid.check_divisible(spec.output_stride, name="grid (fusion network input)")
    ds = Dataset(
        data_root, kind="prealigned", verify=False
    )  # the loader checks every shard it reads
    manifest_hash = ds.manifest_hash()
    tracking = tracking or TrackingSettings("fusion", "fusion", stage="train_fusion", enabled=False)
    meta_base = {
        "cfg": cfg_name,
        "network": network or cfg_name,
        "inputs": inputs,
        "loss": hparams.loss,
        "noise": dict(noise),
        "grid": {"rows": grid.rows, "cols": grid.cols, "cell": grid.cell},
        "seed": int(seed),
        "data_manifest_hash": manifest_hash,
        "profile": tracking.profile,
    }
    module = FusionLitModule(spec.as_dict(), asdict(hparams), meta=meta_base)
    dm = FusionDataModule(data_root, data, seed, grid, tensors=tensors)
    n_params = count_parameters(module.net)
    session = resume.Session(
        resume_dir,
        {
            "problem": "fusion",
            "spec": spec.as_dict(),
            "hparams": asdict(hparams),
            "data": asdict(data),
            "loop": asdict(loop),
            "trainer": trainer_settings.as_dict(),
            "meta": meta_base,
            "data_root": str(data_root),
            "tensors": tensors is not None,
            "extra": trainer_extra,
        },
    )
    if session.resume_from is not None:
        log.info("resuming %s from %s", tracking.stage, session.resume_from)
    fit_loop = common.FitLoop(
        monitor=SELECTION_METRIC,
        max_epochs=loop.max_epochs,
        patience=loop.early_stopping_patience,
        min_delta=loop.early_stopping_min_delta,
        hint="fusion_model.optim.lr",
        gradient_clip_val=loop.gradient_clip_val,
        trainer_extra=trainer_extra,
    )
    with common.fit_run(
        module,
        settings=trainer_settings,
        loop=fit_loop,
        tracking=tracking,
        session=session,
        tags={
            DATA_TAG: manifest_hash,
            "cfg": cfg_name,
            "network": network or cfg_name,
            "loss": hparams.loss,
        },
        params={"data.manifest_hash": manifest_hash, "model.param_count": n_params},
        datasets=[(data_root, manifest_hash)],
        datamodule=dm,
    ) as fitted:
        if fitted is None:
            return None
        if fitted.best is None:
            raise RuntimeError("training produced no checkpoint (no validation epoch finished?)")
        slim = common.model_checkpoint(
            "fusion",
            spec.as_dict(),
            fitted.best["state_dict"],
            {},
            epoch=fitted.best_epoch,
            global_step=int(fitted.best.get("global_step", -1)),
        )
        best_epoch = slim["epoch"]
        row = fitted.best_row()
        epochs_run = len(fitted.history.rows)
        n_train = len(dm.train_set) if dm.train_set is not None else 0
        k = data.train_samples_per_epoch if data.train_samples_per_epoch > 0 else n_train
        # per epoch each of the world_size ranks trains on k // world_size pairs in full batches
        world = int(fitted.trainer.world_size)
        per_rank = min(k, n_train) // world // data.batch_size * data.batch_size
        samples_seen = per_rank * world * epochs_run
        metrics: dict[str, Any] = {key: row[key] for key in sorted(row) if "/" in key}
        metrics.update(
            {
                "best_epoch": best_epoch,
                "epochs": epochs_run,
                "max_epochs": loop.max_epochs,
                "stopped_early": stopped_early(epochs_run, loop.max_epochs),
                "samples_seen": samples_seen,
                "param_count": n_params,
                "train_pairs": n_train,
                "val_pairs": len(dm.val_set) if dm.val_set is not None else 0,
            }
        )
        meta = {
            **meta_base,
            "format": CKPT_FORMAT,
            "architecture": spec.as_dict(),
            "param_count": n_params,
            "hparams": asdict(hparams),
            "best_epoch": best_epoch,
            "best_val_loss": metrics.get("val/loss"),
            "selection_metric": SELECTION_METRIC,
            "best_val_kld_full": metrics.get(SELECTION_METRIC),
        }
        slim["traffictwin"].update(json.loads(json.dumps(meta, default=str)))
        model_uri = None
        run = fitted.run
        if run is not None:
            common.log_final_metrics(
                fitted.logger, {f"best/{k.replace('/', '_')}": v for k, v in metrics.items()}
            )
            with tempfile.TemporaryDirectory(prefix="fusion_art_") as art:
                p = Path(art) / "model.ckpt"
                torch.save(slim, p)
                common.log_checkpoint(p)
            best_module = FusionLitModule(spec.as_dict(), asdict(hparams), meta_base)
            best_module.load_state_dict(slim["state_dict"])
            example = np.zeros(
                (1, spec.backbone.in_channels, grid.rows, grid.cols), dtype=np.float32
            )
            logged_net = best_module.net.to(
                memory_format=torch.contiguous_format
            )  # plain NCHW for serving
            model_uri = common.log_model(
                slim,
                meta,
                logged_net,
                example,
                name="model",
                metadata={"cfg": cfg_name, "data_manifest_hash": manifest_hash},
            )
        common.save_model_files(ckpt_out, slim, meta_out, meta)  # one unit: meta last
        if metrics_out:
            write_json_atomic(metrics_out, metrics)
        if curves_out:
            fitted.history.write_csv(curves_out)
        train_s = fitted.seconds
        history_rows = fitted.history.rows
        precision = fitted.precision
    return FitResult(
        Path(ckpt_out),
        meta,
        metrics,
        history_rows,
        run.info.run_id if run is not None else None,
        model_uri,
        round(train_s, 2),
        round(samples_seen / train_s, 3) if train_s > 0 else None,
        precision,
    )
