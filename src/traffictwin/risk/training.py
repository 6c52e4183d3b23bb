"""Training of the DAVE-2-like risk network with Lightning (Feth et al., sec. 3.5).

Data: ``data/risk`` (kind "risk": ``left``/``right`` BGR images, ``disp_gt``, ``frames.csv``),
``data/disparity`` (kind "disparity": ``disp_sgm`` shards aligned 1:1 with data/risk) and the ORB
pair check ``data/orb/orb.csv``. Only frames whose stereo pair passed the ORB check
(``outlier == False``) are used, in the train/val/test splits of ``frames.csv`` (by scenario).

:class:`RiskSource` reads and cross-checks the three inputs; :func:`prepare_split` loads one split
at the model resolution into compact arrays (uint8 RGB, float16 disparity: ~92 kB a frame at
66×200), normalised per batch on the device by the LightningModule (:class:`RiskRegressor`).
Loss: the variant's objective (:func:`~traffictwin.risk.dave2.risk_loss`: the paper's MSE on the
normalised risk, MSE on log THW, or MSE + a classification head at 1.5 s); optimiser: Adam with a
linear learning-rate warm-up over the first ``warmup_steps`` steps; validation every ``val_every_n_steps`` optimiser steps (the paper: every
10), the checkpoint with the lowest validation loss of the objective is kept (for ``mse`` the
validation MSE, as in the paper). A run whose
best checkpoint predicts one value for every validation frame (spread < :data:`MIN_PRED_STD`)
raises :class:`CollapsedModelError`: nothing is published.

The Trainer, seeding, best-checkpoint callback, the history callback (here one row *per
validation*: the paper's Figs. 5–6 are over iterations, not epochs) and MLflow model logging
come from :mod:`traffictwin.trainer`.
"""

from __future__ import annotations

import logging
import math
import shutil
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import pandas as pd
import torch
from torch.utils.data import DataLoader, SequentialSampler, TensorDataset
from torchmetrics import SumMetric

from traffictwin import resume
from traffictwin.config import flatten
from traffictwin.config import spec as setting
from traffictwin.io.atomic import write_csv_atomic
from traffictwin.io.shards import Dataset, DatasetError
from traffictwin.mlops.tracking import DATA_TAG
from traffictwin.risk.dataset import SPLITS
from traffictwin.risk.dave2 import (
    OBJECTIVES,
    Dave2,
    Dave2Config,
    PackedDave2,
    count_parameters,
    normalise,
    pack_input,
    prepare_channels,
    raw_to_risk,
    risk_loss,
)
from traffictwin.risk.model_io import CKPT, risk_checkpoint, risk_meta, save_risk_model
from traffictwin.trainer import (
    FitLoop,
    NetModule,
    RankShardSampler,
    TrackingSettings,
    TrainerSettings,
    fit_run,
    log_checkpoint,
    log_final_metrics,
    log_model,
    rank_layout,
    seed_everything,
)

log = logging.getLogger(__name__)

LABELS = (
    "risk",
    "risk_thw_corridor",
    "risk_thw_paper",
    "risk_thw_fov",
    "risk_ttc",
    "risk_wttc",
)
#: a run whose validation predictions spread less than this (std of the normalised risk) has
#: collapsed to a constant: it fails instead of being published (:class:`CollapsedModelError`)
MIN_PRED_STD = 1e-3


class CollapsedModelError(RuntimeError):
    """The trained network predicts (nearly) one value for every validation frame."""


_FRAME_COLS = ("frame_id", "shard", "idx", "split", "speed")


# --------------------------------------------------------------------------------------------
# data
# --------------------------------------------------------------------------------------------


class RiskSource:
    """The risk frames that passed the ORB check, with their images and disparities.

    ``risk_root``: data/risk; ``disparity_root``: data/disparity (``None`` if no model input or
    baseline needs SGM disparity); ``orb_csv``: data/orb/orb.csv (``None`` = keep every frame).
    Raises :class:`DatasetError` naming the file and the problem when the three disagree.
    """

    def __init__(
        self,
        risk_root: str | Path,
        disparity_root: str | Path | None = None,
        orb_csv: str | Path | None = None,
    ) -> None:
        self.risk = Dataset(risk_root, kind="risk")
        self.disparity = (
            Dataset(disparity_root, kind="disparity") if disparity_root is not None else None
        )
        frames = self.risk.table("frames.csv")
        fpath = self.risk.root / "frames.csv"
        missing = [c for c in _FRAME_COLS if c not in frames.columns]
        if missing:
            raise DatasetError(f"{fpath}: column(s) {missing} missing (has {list(frames.columns)})")
        self._names = [s["name"] for s in self.risk.shards]
        counts = [int(s["count"]) for s in self.risk.shards]
        # frames.csv 'shard' is the writer's shard index; map it to the manifest position by name
        from traffictwin.io.shards import shard_name

        pos = {name: i for i, name in enumerate(self._names)}
        frames = frames.copy()
        frames["_pos"] = frames["shard"].map(lambda s: pos.get(shard_name(int(s)), -1))
        bad = frames[frames["_pos"] < 0]
        if len(bad):
            raise DatasetError(
                f"{fpath}: frame {bad['frame_id'].iloc[0]} refers to shard {bad['shard'].iloc[0]}, not in the manifest"
            )
        over = frames["idx"].to_numpy() >= np.asarray(counts)[frames["_pos"].to_numpy()]
        if over.any():
            r = frames[over].iloc[0]
            raise DatasetError(
                f"{fpath}: frame {r['frame_id']} has idx {r['idx']} beyond its shard's {counts[int(r['_pos'])]} frames"
            )
        bad_split = sorted(set(frames["split"]) - set(SPLITS))
        if bad_split:
            raise DatasetError(
                f"{fpath}: unknown split value(s) {bad_split} (expected {list(SPLITS)})"
            )
        if self.disparity is not None:
            dnames = [s["name"] for s in self.disparity.shards]
            dcounts = [int(s["count"]) for s in self.disparity.shards]
            if dnames != self._names or dcounts != counts:
                raise DatasetError(
                    f"{self.disparity.root / 'manifest.json'}: shards/counts {list(zip(dnames, dcounts))[:3]}… do not match "
                    f"{self.risk.root / 'manifest.json'} {list(zip(self._names, counts))[:3]}… (must be aligned 1:1)"
                )
        if orb_csv is not None:
            orb_path = Path(orb_csv)
            if not orb_path.exists():
                raise DatasetError(
                    f"{orb_path}: ORB check table not found (run the stage that writes it first)"
                )
            orb = read_orb_table(orb_path)
            outlier = orb.set_index("frame_id")["outlier"].map(_as_bool)
            flag = frames["frame_id"].map(outlier)
            if flag.isna().any():
                fid = frames.loc[flag.isna(), "frame_id"].iloc[0]
                raise DatasetError(
                    f"{orb_path}: no ORB result for frame {fid} of {fpath} ({int(flag.isna().sum())} frames lack one)"
                )
            self.n_orb_outliers = int(flag.astype(bool).sum())
            frames = frames[~flag.astype(bool).to_numpy()]
        else:
            self.n_orb_outliers = 0
        self.n_total = int(len(self.risk.table("frames.csv")))
        self.frames = frames.sort_values(["_pos", "idx"]).reset_index(drop=True)

    @property
    def camera(self) -> dict[str, float]:
        """The camera intrinsics of data/risk's manifest (``camera`` key)."""
        cam = self.risk.manifest.get("camera")
        if not isinstance(cam, dict):
            raise DatasetError(
                f"{self.risk.root / 'manifest.json'}: key 'camera' (intrinsics) missing"
            )
        return cam

    def split_frames(self, split: str) -> pd.DataFrame:
        if split not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
        return self.frames[self.frames["split"] == split].reset_index(drop=True)

    def iter_arrays(
        self, frames: pd.DataFrame, keys: Sequence[str]
    ) -> Iterator[tuple[pd.DataFrame, dict[str, np.ndarray]]]:
        """Per shard: the rows of ``frames`` in it and their arrays ``keys`` (left, right, disp_gt, disp_sgm).

        Checks that every array of a frame has the image's height and width.
        """
        keys = list(keys)
        for p, rows in frames.groupby("_pos", sort=True):
            idx = rows["idx"].to_numpy()
            arrays: dict[str, np.ndarray] = {}
            need_risk = [k for k in keys if k != "disp_sgm"]
            if need_risk:
                shard = self.risk.load_shard(int(p))
                for k in need_risk:
                    if k not in shard:
                        raise DatasetError(
                            f"{self.risk.root / self._names[int(p)]}: array '{k}' missing (has {sorted(shard)})"
                        )
                    arrays[k] = shard[k][idx]
            if "disp_sgm" in keys:
                if self.disparity is None:
                    raise ValueError(
                        "RiskSource: 'disp_sgm' requested but no disparity_root was given"
                    )
                dshard = self.disparity.load_shard(int(p))
                if "disp_sgm" not in dshard:
                    raise DatasetError(
                        f"{self.disparity.root / self._names[int(p)]}: array 'disp_sgm' missing"
                    )
                arrays["disp_sgm"] = dshard["disp_sgm"][idx]
            shapes = {k: tuple(v.shape[1:3]) for k, v in arrays.items()}
            if len(set(shapes.values())) > 1:
                files = f"{self.risk.root / self._names[int(p)]}" + (
                    f" / {self.disparity.root / self._names[int(p)]}"
                    if self.disparity is not None
                    else ""
                )
                raise DatasetError(
                    f"{files}: image and disparity sizes disagree {shapes} (H, W); "
                    "disparity maps must have the left image's size"
                )
            yield rows, arrays


def read_orb_table(path: str | Path) -> pd.DataFrame:
    """The ORB check table (``frame_id``, ``outlier``, ...), checked: readable CSV, both columns
    present, ``frame_id`` integral and unique, ``outlier`` boolean. The only data file without a
    manifest hash, so every way it can be corrupt ends in a DatasetError naming file and column."""
    path = Path(path)
    try:
        orb = pd.read_csv(path)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError, ValueError) as exc:
        msg = " ".join(str(exc).split())
        raise DatasetError(
            f"{path}: not a readable CSV table ({type(exc).__name__}: {msg})"
        ) from None
    for c in ("frame_id", "outlier"):
        if c not in orb.columns:
            raise DatasetError(f"{path}: column '{c}' missing (has {list(orb.columns)})")
    fid = pd.to_numeric(orb["frame_id"], errors="coerce")
    if fid.isna().any() or not np.all(fid == np.round(fid)):
        row = int(np.flatnonzero(fid.isna() | (fid != np.round(fid)))[0])
        raise DatasetError(
            f"{path}: column 'frame_id' must hold integers, row {row + 2} has "
            f"{orb['frame_id'].iloc[row]!r}"
        )
    if fid.duplicated().any():
        dup = int(fid[fid.duplicated()].iloc[0])
        raise DatasetError(f"{path}: column 'frame_id' repeats frame {dup}")
    orb = orb.assign(frame_id=fid.astype(np.int64))
    bad = [v for v in orb["outlier"] if not _is_bool_like(v)]
    if bad:
        raise DatasetError(
            f"{path}: column 'outlier' must hold booleans (True/False, 1/0), got {bad[0]!r}"
        )
    return orb


def _is_bool_like(v: Any) -> bool:
    if isinstance(v, (bool, np.bool_)):
        return True
    if isinstance(v, str):
        return v.strip().lower() in ("true", "false", "1", "0", "yes", "no")
    return isinstance(v, (int, np.integer, float, np.floating)) and v in (0, 1)


def _as_bool(v: Any) -> bool:
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, str):
        s = v.strip().lower()
        if s in ("true", "1", "yes"):
            return True
        if s in ("false", "0", "no"):
            return False
        raise DatasetError(f"orb.csv: 'outlier' value {v!r} is not a boolean")
    return bool(v)


def input_keys(cfg: Dave2Config) -> list[str]:
    """Dataset arrays a model config needs: left (for rgb), disp_sgm, disp_gt."""
    return ["left" if c == "rgb" else c for c in cfg.inputs]


@dataclass
class RiskArrays:
    """One split at the model resolution (see :func:`prepare_channels`)."""

    frame_id: np.ndarray  # (N,)
    rgb: np.ndarray  # (N, 3 or 0, h, w) uint8
    disp: np.ndarray  # (N, k, h, w) float16 (k = disparity inputs, may be 0)
    speed: np.ndarray  # (N,) float32 m/s
    y: np.ndarray  # (N,) float32 normalised risk label

    def __len__(self) -> int:
        return len(self.frame_id)

    def tensors(self) -> TensorDataset:
        return TensorDataset(
            *(
                torch.from_numpy(np.ascontiguousarray(a))
                for a in (self.rgb, self.disp, self.speed, self.y)
            )
        )


def check_label(frames: pd.DataFrame, label: str, source: str = "frames.csv") -> np.ndarray:
    """The label column as float32; errors if missing, non-finite or outside [0, 1]."""
    if label not in frames.columns:
        raise DatasetError(f"{source}: label column '{label}' missing (has {list(frames.columns)})")
    y = frames[label].to_numpy(dtype=np.float64)
    if not np.all(np.isfinite(y)) or (len(y) and (y.min() < 0 or y.max() > 1)):
        raise DatasetError(
            f"{source}: label '{label}' must be finite and in [0, 1] (normalised risk)"
        )
    return y.astype(np.float32)


def prepare_split(
    source: RiskSource,
    cfg: Dave2Config,
    split: str,
    label: str,
    max_frames: int | None = None,
    seed: int = 0,
) -> RiskArrays:
    """Load ``split`` (ORB-passed frames) at the model resolution; ``max_frames`` subsamples (seeded)."""
    frames = source.split_frames(split)
    if max_frames is not None and len(frames) > max_frames:
        keep = np.sort(
            np.random.default_rng(seed).choice(len(frames), size=max_frames, replace=False)
        )
        frames = frames.iloc[keep].reset_index(drop=True)
    h, w = cfg.height, cfg.width
    n_disp = sum(1 for c in cfg.inputs if c != "rgb")
    rgb_parts, disp_parts, order = [], [], []
    for rows, arrays in source.iter_arrays(frames, input_keys(cfg)):
        rgb, disp = prepare_channels(
            cfg, arrays.get("left"), arrays.get("disp_sgm"), arrays.get("disp_gt")
        )
        n = len(rows)
        rgb_parts.append(rgb if rgb is not None else np.zeros((n, 0, h, w), np.uint8))
        disp_parts.append(disp if disp is not None else np.zeros((n, 0, h, w), np.float16))
        order.append(rows.index.to_numpy())
    if not order:
        return RiskArrays(
            np.zeros(0, np.int64),
            np.zeros((0, 3 if "rgb" in cfg.inputs else 0, h, w), np.uint8),
            np.zeros((0, n_disp, h, w), np.float16),
            np.zeros(0, np.float32),
            np.zeros(0, np.float32),
        )
    ix = np.concatenate(order)
    frames = frames.loc[ix].reset_index(drop=True)
    return RiskArrays(
        frame_id=frames["frame_id"].to_numpy(),
        rgb=np.concatenate(rgb_parts),
        disp=np.concatenate(disp_parts),
        speed=frames["speed"].to_numpy(dtype=np.float32),
        y=check_label(frames, label, str(source.risk.root / "frames.csv")),
    )


class RiskDataModule(L.LightningDataModule):
    """Train/val/test loaders over in-memory :class:`RiskArrays` (shuffled train, seeded)."""

    def __init__(
        self,
        train: RiskArrays,
        val: RiskArrays,
        test: RiskArrays | None = None,
        batch_size: int = 10,
        eval_batch_size: int = 256,
        num_workers: int = 0,
        seed: int = 0,
    ) -> None:
        super().__init__()
        if len(train) == 0:
            raise ValueError(
                "RiskDataModule: the training split has no frames (after the ORB check)"
            )
        if len(val) == 0:
            raise ValueError(
                "RiskDataModule: the validation split has no frames (after the ORB check)"
            )
        self.train, self.val, self.test = train, val, test
        self.batch_size, self.eval_batch_size = int(batch_size), int(eval_batch_size)
        self.num_workers, self.seed = int(num_workers), int(seed)

    def _loader(self, arrays: RiskArrays, shuffle: bool, bs: int) -> DataLoader:
        g = torch.Generator()
        g.manual_seed(self.seed)
        ds = arrays.tensors()
        world, rank = rank_layout(self.trainer)
        # DDP evaluation: every frame on exactly one rank, in one process's batches (Lightning's
        # DistributedSampler would repeat frames to even out the ranks and bias the summed
        # metrics); training keeps Lightning's shuffled DistributedSampler
        sampler = (
            RankShardSampler(SequentialSampler(ds), world, rank, even=False, block=bs)
            if world > 1 and not shuffle
            else None
        )
        return DataLoader(
            ds,
            batch_size=bs,
            shuffle=shuffle,
            sampler=sampler,
            generator=g if shuffle else None,
            num_workers=self.num_workers,
            persistent_workers=self.num_workers > 0,
            drop_last=False,
        )

    def train_dataloader(self) -> DataLoader:
        return self._loader(self.train, True, self.batch_size)

    def val_dataloader(self) -> DataLoader:
        return self._loader(self.val, False, self.eval_batch_size)

    def test_dataloader(self) -> DataLoader:
        if self.test is None:
            raise ValueError("RiskDataModule: no test split given")
        return self._loader(self.test, False, self.eval_batch_size)


# --------------------------------------------------------------------------------------------
# model
# --------------------------------------------------------------------------------------------


def mse_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean squared error on the normalised risk (computed in float32)."""
    return torch.mean((pred.float() - target) ** 2)


class RiskRegressor(NetModule):
    """:class:`~traffictwin.trainer.NetModule` with Dave2 and its objective's loss (Adam).

    Logs ``train/loss`` (per step; the objective's loss), ``val/loss`` (the same on the
    validation frames: selects the checkpoint), ``val/mse``, ``val/mae`` (of the predicted
    normalised risk, whatever the objective), ``val/pred_std`` (spread of the predictions: ~0 =
    collapsed), ``test/*``.
    """

    def __init__(
        self,
        cfg: Dave2Config,
        lr: float = 1e-4,
        weight_decay: float = 0.0,
        bce_weight: float = 0.05,
        warmup_steps: int = 0,
    ) -> None:
        super().__init__(Dave2(cfg), mse_loss, lr=lr, weight_decay=weight_decay)
        self.cfg = cfg
        self.bce_weight = float(bce_weight)
        self.warmup_steps = int(warmup_steps)
        # per-split sums (torchmetrics, float64; reduced over DDP ranks)
        self.eval_sums = torch.nn.ModuleDict(
            {
                split: torch.nn.ModuleDict(
                    {
                        k: SumMetric().set_dtype(torch.float64)
                        for k in ("se", "ae", "n", "p", "p2", "loss")
                    }
                )
                for split in ("val", "test")
            }
        )

    def configure_optimizers(self) -> Any:
        """Adam; with ``warmup_steps`` the learning rate rises linearly from lr / warmup_steps to
        lr over the first steps. Adam's first updates move every weight by about lr in the
        direction of its gradient's sign, whatever the gradient's size (so clipping does not
        help): across the 1164 x 1152 first FC layer such a coherent step at lr 1e-3 can push every
        ReLU of the head negative for every input — a dead head that outputs one constant (the
        collapsed ``rgb`` run). The warm-up keeps those first steps small."""
        opt = torch.optim.Adam(self.net.parameters(), lr=self.lr, weight_decay=self.weight_decay)
        if self.warmup_steps <= 0:
            return opt
        n = self.warmup_steps
        sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda step: min(1.0, (step + 1) / n))
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}

    def forward(self, rgb: torch.Tensor, disp: torch.Tensor, speed: torch.Tensor) -> torch.Tensor:
        """Normalised risk (N,)."""
        return raw_to_risk(self.cfg, self.raw(rgb, disp, speed))

    def raw(self, rgb: torch.Tensor, disp: torch.Tensor, speed: torch.Tensor) -> torch.Tensor:
        x = normalise(self.cfg, rgb if rgb.shape[1] else None, disp if disp.shape[1] else None)
        return self.net.raw(x, speed if self.cfg.use_speed else None)

    def training_step(self, batch: Sequence[torch.Tensor], batch_idx: int) -> torch.Tensor:
        rgb, disp, speed, y = batch
        loss = risk_loss(self.cfg, self.raw(rgb, disp, speed), y, self.bce_weight)
        self.log("train/loss", loss, on_step=True, on_epoch=False, prog_bar=True, batch_size=len(y))
        return loss

    def _eval_step(self, batch: Sequence[torch.Tensor], prefix: str) -> None:
        rgb, disp, speed, y = batch
        raw = self.raw(rgb, disp, speed)
        pred = raw_to_risk(self.cfg, raw).double()
        err = pred - y.double()
        sums = self.eval_sums[prefix]
        sums["loss"].update(risk_loss(self.cfg, raw, y, self.bce_weight).double() * len(y))
        sums["se"].update(torch.sum(err**2))
        sums["ae"].update(torch.sum(err.abs()))
        sums["n"].update(float(len(y)))
        sums["p"].update(torch.sum(pred))
        sums["p2"].update(torch.sum(pred**2))

    def _eval_end(self, prefix: str) -> None:
        sums = self.eval_sums[prefix]
        se, ae, n, p, p2, loss = (
            float(sums[k].compute()) for k in ("se", "ae", "n", "p", "p2", "loss")
        )
        for metric in sums.values():
            metric.reset()
        n = max(n, 1.0)
        self.log(f"{prefix}/loss", loss / n)
        self.log(f"{prefix}/mse", se / n)
        self.log(f"{prefix}/mae", ae / n)
        self.log(f"{prefix}/pred_std", math.sqrt(max(p2 / n - (p / n) ** 2, 0.0)))

    def validation_step(self, batch: Sequence[torch.Tensor], batch_idx: int) -> None:
        self._eval_step(batch, "val")

    def on_validation_epoch_end(self) -> None:
        self._eval_end("val")

    def test_step(self, batch: Sequence[torch.Tensor], batch_idx: int) -> None:
        self._eval_step(batch, "test")

    def on_test_epoch_end(self) -> None:
        self._eval_end("test")


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation settings (paper sec. 3.5: Adam, batch 10, 30 epochs, validation every 10 steps)."""

    epochs: int = 30
    batch_size: int = 10
    lr: float = 1e-4
    weight_decay: float = 0.0
    val_every_n_steps: int = 10
    limit_val_batches: int | float = 1.0
    eval_batch_size: int = 256
    seed: int = 0
    warmup_steps: int = 0
    bce_weight: float = 0.05
    min_pred_std: float = MIN_PRED_STD

    def __post_init__(self) -> None:
        for k in ("epochs", "batch_size", "val_every_n_steps", "eval_batch_size"):
            if int(getattr(self, k)) < 1:
                raise ValueError(f"TrainConfig.{k} must be >= 1, got {getattr(self, k)}")
        if not self.lr > 0:
            raise ValueError(f"TrainConfig.lr must be > 0, got {self.lr}")


# the ``risk_model`` config group (validated once by the stage with traffictwin.config.typed)


@dataclass
class VariantConfig:
    """``risk_model.variants.<name>``: input channel groups, speed input, label (None = ``label``),
    training objective (:data:`~traffictwin.risk.dave2.OBJECTIVES`), the seed offset added to the
    training seed, and ``replicate_of``: the variant this one repeats with another seed (None)."""

    inputs: list[str] = setting()  # checked by Dave2Config (rgb, disp_sgm, disp_gt)
    speed: bool = setting()
    label: str | None = setting(choices=(*LABELS, None))
    objective: str = setting(choices=tuple(OBJECTIVES))
    seed_offset: int = setting(min=0)
    replicate_of: str | None = setting()


@dataclass
class ObjectiveSchema:
    """``risk_model.objective``: the THW (s) that stands for "nothing ahead" in ``log_thw``, and
    the weight of the classification term and its THW threshold (s) in ``mse_bce``."""

    thw_cap_s: float = setting(min=0.1)
    bce_weight: float = setting(min=0.0)
    critical_thw_s: float = setting(min=0.1)


@dataclass
class RiskTrainSchema:
    """``risk_model.train``; ``limit_val_batches``: a batch count (int >= 1) or a fraction in (0, 1]."""

    epochs: int = setting(min=1)
    batch_size: int = setting(min=1)
    lr: float = setting(min=1e-12)
    weight_decay: float = setting(min=0.0)
    warmup_steps: int = setting(min=0)
    min_pred_std: float = setting(min=0.0)
    val_every_n_steps: int = setting(min=1)
    limit_val_batches: Any = setting()
    eval_batch_size: int = setting(min=1)
    max_train_frames: int | None = setting(min=1)
    seed_offset: int = setting(min=0)


@dataclass
class RiskModelConfig:
    """The ``risk_model`` group: the network (per variant) and its training."""

    orb_filter: bool = setting()
    label: str = setting(choices=LABELS)
    height: int = setting(min=1)
    width: int = setting(min=1)
    disp_scale: float = setting(min=1e-6)
    speed_scale: float = setting(min=1e-6)
    dropout: float = setting(min=0.0, max=0.99)
    objective: ObjectiveSchema = setting()
    train: RiskTrainSchema = setting()
    run_variants: list[str] = setting()
    variants: dict[str, VariantConfig] = setting()

    def __post_init__(self) -> None:
        unknown = [v for v in self.run_variants if v not in self.variants]
        if unknown:
            raise ValueError(
                f"run_variants {unknown} are not in variants (has {sorted(self.variants)})"
            )
        for name, v in self.variants.items():
            base = v.replicate_of
            if base is None:
                continue
            b = self.variants.get(base)
            if b is None or b.replicate_of is not None:
                raise ValueError(
                    f"variants.{name}.replicate_of must name a variant that is not itself a "
                    f"replicate, got {base!r}"
                )
            same = ("inputs", "speed", "label", "objective")
            diff = [k for k in same if getattr(v, k) != getattr(b, k)]
            if diff or v.seed_offset == b.seed_offset:
                raise ValueError(
                    f"variants.{name} replicates {base!r}: it must have the same {list(same)} "
                    f"(differs in {diff}) and another seed_offset"
                )

    def variant(self, name: str) -> tuple[Dave2Config, str]:
        """The network config and the training label of variant ``name``."""
        if name not in self.variants:
            raise KeyError(f"no variant {name!r} (has {sorted(self.variants)})")
        v = self.variants[name]
        cfg = Dave2Config(
            inputs=tuple(v.inputs),
            height=self.height,
            width=self.width,
            use_speed=v.speed,
            speed_scale=self.speed_scale,
            disp_scale=self.disp_scale,
            dropout=self.dropout,
            objective=v.objective,
            thw_cap_s=self.objective.thw_cap_s,
            critical_thw_s=self.objective.critical_thw_s,
        )
        return cfg, v.label or self.label

    def train_config(self, seed: int, variant: str | None = None) -> TrainConfig:
        """Optimisation settings; the seed is the global ``seed`` + ``train.seed_offset`` (+ the
        variant's ``seed_offset``).

        Raises ValueError when ``train.limit_val_batches`` is neither a batch count (int >= 1)
        nor a fraction in (0, 1].
        """
        t = self.train
        lvb = t.limit_val_batches
        if (
            isinstance(lvb, bool)
            or not isinstance(lvb, (int, float))
            or lvb <= 0
            or (isinstance(lvb, float) and lvb > 1)
        ):
            raise ValueError(
                "'train.limit_val_batches' must be a batch count (int >= 1) or a fraction"
                f" in (0, 1], got {lvb!r}"
            )
        same = {f.name for f in fields(TrainConfig)} - {"seed", "bce_weight"}
        extra = self.variants[variant].seed_offset if variant is not None else 0
        return TrainConfig(
            **{k: getattr(t, k) for k in same},
            seed=seed + t.seed_offset + extra,
            bce_weight=self.objective.bce_weight,
        )


@dataclass
class TrainResult:
    net: Dave2
    history: pd.DataFrame
    best_val_mse: float
    best_step: int
    steps: int
    seconds: float
    n_train: int
    n_val: int
    run_id: str | None = None  # MLflow run (set by fit_risk with tracking): for the run record only
    model_uri: str | None = None
    precision: str | None = None  # the trainer's resolved precision: for the run record only


@contextmanager
def fitting(
    cfg: Dave2Config,
    train: RiskArrays,
    val: RiskArrays,
    tc: TrainConfig,
    settings: TrainerSettings | None = None,
    *,
    tracking: TrackingSettings | None = None,
    session: resume.Session | None = None,
    tags: Mapping[str, Any] | None = None,
    params: Mapping[str, Any] | None = None,
    datasets: Sequence[tuple[str | Path, str]] = (),
    fast_dev_run: bool | int = False,
) -> Iterator[tuple[TrainResult, Any] | None]:
    """Train a risk network with the one training driver (:func:`traffictwin.trainer.fit_run`);
    yields ``(result, fitted)`` inside the still open MLflow run (``tracking``), the result's
    network holding the weights of the best validation loss (CPU, eval mode), or ``None`` on other
    DDP ranks. ``session``: the run's resume folder (:class:`traffictwin.resume.Session`)."""
    settings = settings or TrainerSettings()
    tracking = tracking or TrackingSettings("risk", "risk", stage="train_risk", enabled=False)
    session = session or resume.Session(None, {})
    seed_everything(tc.seed)
    dm = RiskDataModule(
        train,
        val,
        batch_size=tc.batch_size,
        eval_batch_size=tc.eval_batch_size,
        num_workers=settings.num_workers,
        seed=tc.seed,
    )
    module = RiskRegressor(
        cfg,
        lr=tc.lr,
        weight_decay=tc.weight_decay,
        bce_weight=tc.bce_weight,
        warmup_steps=tc.warmup_steps,
    )
    steps_per_epoch = math.ceil(len(train) / tc.batch_size)
    total = steps_per_epoch * tc.epochs
    # validate at least once at the end: the interval never exceeds the run's step count
    interval = max(1, min(tc.val_every_n_steps, total))
    loop = FitLoop(
        monitor="val/loss",
        max_epochs=tc.epochs,
        hint="risk_model.train.lr",
        history="validation",
        history_metrics=("val/loss", "val/mse", "val/mae", "val/pred_std"),
        trainer_extra={
            "limit_val_batches": tc.limit_val_batches,
            "val_check_interval": interval,
            "check_val_every_n_epoch": None,
        },
    )
    with fit_run(
        module,
        settings=settings,
        loop=loop,
        tracking=tracking,
        session=session,
        tags=tags,
        params=params,
        datasets=datasets,
        datamodule=dm,
        fast_dev_run=fast_dev_run,
    ) as fitted:
        if fitted is None:  # DDP: another rank trained along; rank zero writes
            yield None
            return
        best_step = -1
        if fitted.best is not None:
            module.load_state_dict(fitted.best["state_dict"])
            best_step = int(fitted.best.get("global_step", -1))
        hist = fitted.history.frame()
        # the validation MSE of the kept checkpoint (the one with the lowest validation loss)
        best_val = (
            float(hist["val/mse"][hist["val/loss"].idxmin()])
            if len(hist) and hist["val/loss"].notna().any()
            else float("nan")
        )
        net = module.net.cpu().eval()
        if not fast_dev_run:
            check_spread(net, val, cfg, tc.min_pred_std)
        log.info(
            "risk net %s: %d params, %d steps in %.1f s, best val MSE %.5f at step %d",
            list(cfg.inputs),
            count_parameters(net),
            fitted.trainer.global_step,
            fitted.seconds,
            best_val,
            best_step,
        )
        res = TrainResult(
            net,
            hist,
            best_val,
            best_step,
            int(fitted.trainer.global_step),
            fitted.seconds,
            len(train),
            len(val),
            precision=fitted.precision,
        )
        yield res, fitted


def fit(
    cfg: Dave2Config,
    train: RiskArrays,
    val: RiskArrays,
    tc: TrainConfig,
    settings: TrainerSettings | None = None,
    fast_dev_run: bool | int = False,
    session: resume.Session | None = None,
) -> TrainResult:
    """Train a risk network without tracking (:func:`fitting`); returns the weights of the best
    validation loss (CPU, eval mode). ``session``: the run's resume folder."""
    with fitting(cfg, train, val, tc, settings, session=session, fast_dev_run=fast_dev_run) as out:
        if out is None:
            raise RuntimeError("risk training: fit() on a DDP rank other than zero")
        return out[0]


def check_spread(
    net: Dave2, val: RiskArrays, cfg: Dave2Config, min_std: float = MIN_PRED_STD
) -> float:
    """Std of the network's predicted risk over the validation frames; raises
    :class:`CollapsedModelError` when it is below ``min_std`` (one output for every frame)."""
    with torch.no_grad():
        preds = []
        for i in range(0, len(val), 256):
            sl = slice(i, i + 256)
            x = normalise(
                cfg,
                torch.from_numpy(val.rgb[sl]) if val.rgb.shape[1] else None,
                torch.from_numpy(val.disp[sl]) if val.disp.shape[1] else None,
            )
            preds.append(net(x, torch.from_numpy(val.speed[sl]) if cfg.use_speed else None))
    p = torch.cat(preds).double() if preds else torch.zeros(0, dtype=torch.float64)
    std = float(p.std(unbiased=False)) if len(p) else 0.0
    if not std >= min_std:
        raise CollapsedModelError(
            f"risk network {list(cfg.inputs)} (speed {cfg.use_speed}, objective {cfg.objective}) "
            f"collapsed: its predictions on the {len(p)} validation frames spread by {std:.2e} "
            f"(std of the normalised risk, minimum {min_std:g}) — it outputs one value for every "
            f"frame; not published (check the learning rate, initialisation and the label)"
        )
    return std


def fit_risk(
    data: RiskSource,
    cfg: Dave2Config,
    label: str,
    tc: TrainConfig,
    settings: TrainerSettings,
    *,
    variant: str,
    out_dir: str | Path,
    curves_out: str | Path | None = None,
    max_train_frames: int | None = None,
    tracking: TrackingSettings | None = None,
    meta: Mapping[str, Any] | None = None,
    resume_dir: str | Path | None = None,
) -> TrainResult | None:
    """Train variant ``variant`` on ``data`` and publish it (rank zero; ``None`` on other ranks).

    Writes ``out_dir`` (replaced): ``model.ckpt``, ``model_meta.json`` (``meta`` + training
    facts), ``history.csv``; ``curves_out`` (the same curves, for ``dvc plots``): identical runs
    write identical bytes (the MLflow run id, model URI and training seconds are only in the
    returned :class:`TrainResult`). With
    ``tracking`` enabled: an MLflow run with the params once, the curves, the final metrics,
    the checkpoint and an MLflow model (the same ``model.ckpt`` + ``model_meta.json``, no pickled
    code; its signature is that of :class:`PackedDave2`, one packed input tensor).
    ``resume_dir``: where a killed run's training state waits for the next run with the same
    config, data and code (:mod:`traffictwin.resume`); removed after the outputs are written.
    """
    out_dir = Path(out_dir)
    tracking = tracking or TrackingSettings("risk", f"risk-{variant}", enabled=False)
    train = prepare_split(data, cfg, "train", label, max_frames=max_train_frames, seed=tc.seed)
    val = prepare_split(data, cfg, "val", label)
    log.info(
        "%s: %d train / %d val frames (ORB-passed), label %s",
        tracking.stage,
        len(train),
        len(val),
        label,
    )
    run_params = {
        **tracking.params,
        "risk_model.variant": variant,
        "risk_model.inputs": ",".join(cfg.inputs),
        "risk_model.use_speed": cfg.use_speed,
        "risk_model.effective_label": label,
        **flatten({"trainer": settings.as_dict()}),
        "seed": tc.seed,
        "data.n_train": len(train),
        "data.n_val": len(val),
    }
    manifest = data.risk.manifest_hash()
    tags = {"variant": variant, DATA_TAG: manifest, "label": label}
    session = resume.Session(
        resume_dir,
        {
            "problem": "risk",
            "cfg": cfg.to_dict(),
            "label": label,
            "train": asdict(tc),
            "trainer": settings.as_dict(),
            "variant": variant,
            "max_train_frames": max_train_frames,
            "data": [manifest, data.disparity.manifest_hash() if data.disparity else None],
            "frames": [len(train), len(val)],
            "meta": dict(meta or {}),
        },
    )
    datasets = [(data.risk.root, manifest)]
    if data.disparity is not None:
        datasets.append((data.disparity.root, data.disparity.manifest_hash()))
    with fitting(
        cfg,
        train,
        val,
        tc,
        settings,
        tracking=tracking,
        session=session,
        tags=tags,
        params=run_params,
        datasets=datasets,
    ) as out:
        if out is None:  # DDP: the other ranks trained along; rank zero writes
            return None
        res, fitted = out
        if out_dir.exists():
            shutil.rmtree(out_dir)
        full_meta = {
            "variant": variant,
            "label": label,
            "best_val_mse": res.best_val_mse,
            "best_step": res.best_step,
            "steps": res.steps,
            "n_train": res.n_train,
            "n_val": res.n_val,
            "data_manifest": manifest,
            "profile": tracking.profile,
            "train": tc.__dict__,
            **dict(meta or {}),
        }
        save_risk_model(res.net, out_dir, full_meta)
        for path in (out_dir / "history.csv", *([curves_out] if curves_out else [])):
            write_csv_atomic(path, res.history, float_format="%.9g", lineterminator="\n")
        run = fitted.run
        if run is not None:
            log_final_metrics(
                fitted.logger,
                {
                    "val/best_mse": res.best_val_mse,
                    "train/seconds": res.seconds,
                    "model/n_parameters": count_parameters(res.net),
                },
            )
            log_checkpoint(out_dir / CKPT)
            log_checkpoint(out_dir / "history.csv", artifact_path="curves")
            n_ex = min(2, len(val))
            x = normalise(
                cfg,
                torch.from_numpy(val.rgb[:n_ex]) if "rgb" in cfg.inputs else None,
                torch.from_numpy(val.disp[:n_ex]) if val.disp.shape[1] else None,
            )
            example = pack_input(cfg, x, torch.from_numpy(val.speed[:n_ex])).numpy()
            uri = log_model(
                risk_checkpoint(res.net, full_meta),
                risk_meta(res.net, full_meta),
                PackedDave2(res.net),
                example,
                metadata={"variant": variant, "label": label},
            )
            res.run_id, res.model_uri = run.info.run_id, uri
    return res


def train_config_dict(tc: TrainConfig) -> dict[str, Any]:
    return asdict(tc)
