"""Training of the learned stereo network (:mod:`traffictwin.stereo.network`) on the risk data's rendered pairs and exact disparity (lives with the risk problem: it reads data/risk).

- :func:`load_pairs` — the fault-free stereo pairs of one split of a ``data/risk`` dataset (left,
  right BGR uint8, exact disparity px), evenly spaced up to a count;
- :class:`CropSet` — random crops (``crop_h`` x ``crop_w`` px, wider than ``max_disparity``) of
  the training pairs, drawn from a seeded generator;
- :class:`StereoLitModule` — :class:`~traffictwin.trainer.NetModule` around :class:`StereoNet`,
  validation on full frames: ``val/loss``, ``val/epe`` (px), ``val/bad1``, ``val/relerr_median``
  (median |d - d_gt| / d_gt) over the pixels with ground truth below ``max_disparity``;
- :func:`calibrate_spread` — EPE / bad-1 per decile of the predicted spread on validation and the
  spread threshold that keeps ``valid_density`` of the ground-truth pixels;
- :func:`fit_stereo` — the run (seeding, trainer driver, MLflow experiment ``stereo``, early
  stopping on ``val/epe``, calibration, model files, and with tracking the MLflow model of
  :class:`PackedStereo` with its signature and a validation pair as input example, which the
  promotion gate registers as ``traffictwin-stereo``); :func:`load_stereo_model` — the sealed,
  weights-only loader.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import DataLoader, RandomSampler, TensorDataset
from torch.utils.data import Dataset as TorchDataset
from torchmetrics import CatMetric, MeanMetric, SumMetric

from traffictwin import trainer as common
from traffictwin.io.shards import Dataset, DatasetError, derived_dataset
from traffictwin.mlops.tracking import DATA_TAG
from traffictwin.risk.stereo_io import (  # noqa: F401 - re-exported
    PROBLEM,
    SEALED_META,
    PackedStereo,
    StereoModelError,
    load_stereo_model,
    pack_pairs,
    predict,
)
from traffictwin.stereo.model_config import (  # noqa: F401 - re-exported: the stage's settings
    StereoModelConfig,
    StereoTrainConfig,
)
from traffictwin.stereo.network import StereoNet, StereoNetSpec, param_count, stereo_loss, to_input
from traffictwin.trainer import FitResult, ModelOutputs, TrackingSettings

log = logging.getLogger(__name__)

SELECTION_METRIC = "val/epe"


# -- data ---------------------------------------------------------------------------------------------
def evenly_spaced_index(n: int, k: int) -> np.ndarray:
    """``k`` (0 = all) evenly spaced indices of ``range(n)``."""
    if k <= 0 or k >= n:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, k).round().astype(int))


def load_pairs(
    root: str | Path,
    split: str,
    limit: int = 0,
    fault_free: bool = True,
    disparity: str | Path | None = None,
    exclude_templates: tuple[str, ...] = (),
) -> dict[str, np.ndarray]:
    """``left``/``right`` (N, H, W, 3) BGR uint8 and ``disp_gt`` (N, H, W) float32 px of the
    ``split`` frames of ``data/risk`` at ``root`` (only fault-free pairs when ``fault_free``: a
    faulty pair's images do not match its exact disparity), ``limit`` evenly spaced (0 = all);
    with ``disparity`` (a ``data/disparity`` folder aligned 1:1 with ``root``) also ``disp_sgm``
    (N, H, W) float32 px, -1 invalid: SGM of the full frames. ``exclude_templates``: road
    templates whose frames are left out (a generalisation run). Errors name the folder."""
    from traffictwin.risk.stereo_shards import load_stereo_shard

    ds = Dataset(root, kind="risk", verify=False)
    frames = ds.table("frames.csv")
    sel = frames[frames.split == split]
    if fault_free and "fault" in sel.columns:
        sel = sel[sel.fault == "none"]
    if exclude_templates:
        if "template" not in sel.columns:
            raise DatasetError(
                f"{Path(root) / 'frames.csv'}: no 'template' column to leave out the road "
                f"templates {list(exclude_templates)}"
            )
        sel = sel[~sel.template.astype(str).isin(list(exclude_templates))]
    sel = sel.sort_values(["shard", "idx"]).iloc[evenly_spaced_index(len(sel), limit)]
    if len(sel) == 0:
        raise DatasetError(f"{root}: no fault-free '{split}' frames to train / validate on")
    parts: dict[str, list[np.ndarray]] = {"left": [], "right": [], "disp_gt": []}
    sgm = None
    if disparity is not None:
        sgm = derived_dataset(disparity, "disparity", ds, str(root), "disparity")
        parts["disp_sgm"] = []
    for shard, g in sel.groupby("shard", sort=True):
        sh = load_stereo_shard(ds, int(shard), ("left", "right", "disp_gt"))
        idx = g.idx.to_numpy()
        for k in ("left", "right", "disp_gt"):
            parts[k].append(np.asarray(sh[k])[idx])
        if sgm is not None:
            parts["disp_sgm"].append(np.asarray(sgm.load_shard(int(shard))["disp_sgm"])[idx])
    return {k: np.concatenate(v) for k, v in parts.items()}


class CropSet(TorchDataset):
    """Random ``(crop_h, crop_w)`` crops of the pairs: (left, right, disp_gt[, disp_sgm]) tensors
    (3, h, w) float [0, 1] RGB and (1, h, w) px (SGM cropped from the full-frame SGM, so its left
    border is SGM's, not the crop's); offsets drawn from a generator seeded by ``seed``."""

    def __init__(self, pairs: dict[str, np.ndarray], crop_h: int, crop_w: int, seed: int) -> None:
        n, h, w = pairs["disp_gt"].shape
        if crop_h > h or crop_w > w:
            raise ValueError(f"crop {crop_h}x{crop_w} px larger than the images {h}x{w} px")
        self.p, self.ch, self.cw = pairs, crop_h, crop_w
        self.gen = torch.Generator().manual_seed(seed)

    def __len__(self) -> int:
        return len(self.p["disp_gt"])

    def __getitem__(self, i: int) -> tuple[torch.Tensor, ...]:
        _, h, w = self.p["disp_gt"].shape
        y = int(torch.randint(0, h - self.ch + 1, (1,), generator=self.gen))
        x = int(torch.randint(0, w - self.cw + 1, (1,), generator=self.gen))
        sl = (i, slice(y, y + self.ch), slice(x, x + self.cw))
        lr = to_input(np.stack([self.p["left"][sl], self.p["right"][sl]]))
        d = torch.from_numpy(np.ascontiguousarray(self.p["disp_gt"][sl], np.float32))[None]
        if "disp_sgm" not in self.p:
            return lr[0], lr[1], d
        sg = torch.from_numpy(np.ascontiguousarray(self.p["disp_sgm"][sl], np.float32))[None]
        return lr[0], lr[1], d, sg


def full_frames(pairs: dict[str, np.ndarray]) -> TensorDataset:
    """Whole frames as tensors (left, right, disp_gt) like :class:`CropSet`'s."""
    lr_l, lr_r = to_input(pairs["left"]), to_input(pairs["right"])
    d = torch.from_numpy(np.ascontiguousarray(pairs["disp_gt"], np.float32))[:, None]
    if "disp_sgm" not in pairs:
        return TensorDataset(lr_l, lr_r, d)
    sg = torch.from_numpy(np.ascontiguousarray(pairs["disp_sgm"], np.float32))[:, None]
    return TensorDataset(lr_l, lr_r, d, sg)


# -- module -------------------------------------------------------------------------------------------
class StereoLitModule(common.NetModule):
    """:class:`~traffictwin.trainer.NetModule` around :class:`StereoNet`."""

    def __init__(
        self, spec: dict[str, Any], hparams: dict[str, Any], meta: dict[str, Any] | None = None
    ) -> None:
        s = StereoNetSpec.from_dict(spec)
        super().__init__(
            StereoNet(s),
            stereo_loss,
            lr=hparams["lr"],
            weight_decay=hparams["weight_decay"],
            plateau=(hparams["lr_factor"], hparams["lr_patience"]),
            monitor=SELECTION_METRIC,
        )
        self.save_hyperparameters(
            {"spec": dict(spec), "hparams": dict(hparams), "meta": meta or {}}
        )
        self.hp = dict(hparams)
        self.max_d = float(s.max_disparity)
        self.val_loss = MeanMetric()
        self.val_abs = SumMetric()
        self.val_bad1 = SumMetric()
        self.val_n = SumMetric()
        self.val_rel = CatMetric()

    def _loss(self, out: dict[str, torch.Tensor], gt: torch.Tensor):
        return self.loss_fn(
            out,
            gt,
            max_disparity=self.max_d,
            rel_weight=self.hp["rel_weight"],
            coarse_weight=self.hp["coarse_weight"],
        )

    def _run(self, batch) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        """The network's output and the ground truth it is scored on (in ``base: sgm`` mode only
        SGM's valid pixels: the others stay invalid, whatever the network says)."""
        left, right, gt = batch[:3]
        sgm = batch[3] if len(batch) > 3 else None
        out = self.net(left, right, sgm)
        if sgm is not None:
            gt = torch.where(sgm >= 0, gt, torch.zeros_like(gt))
        return out, gt

    def training_step(self, batch, batch_idx: int) -> torch.Tensor:
        left = batch[0]
        out, gt = self._run(batch)
        loss, parts = self._loss(out, gt)
        n = left.shape[0]
        self.log("train/loss", loss, on_step=False, on_epoch=True, batch_size=n)
        for k, v in parts.items():
            self.log(f"train/{k}", v, on_step=False, on_epoch=True, batch_size=n)
        return loss

    def validation_step(self, batch, batch_idx: int) -> None:
        left = batch[0]
        out, gt = self._run(batch)
        loss, _ = self._loss(out, gt)
        self.val_loss.update(loss, weight=left.shape[0])
        valid = (gt > 0) & (gt < self.max_d)
        err = (out["disparity"] - gt).abs()[valid]
        self.val_abs.update(err.sum())
        self.val_bad1.update((err > 1.0).sum())
        self.val_n.update(valid.sum())
        self.val_rel.update((err / gt[valid])[::7])  # a fixed subsample for the median

    def on_validation_epoch_end(self) -> None:
        n = self.val_n.compute().clamp_min(1)
        self.log("val/loss", self.val_loss.compute())
        self.log("val/epe", self.val_abs.compute() / n)
        self.log("val/bad1", self.val_bad1.compute() / n)
        self.log("val/relerr_median", self.val_rel.compute().float().median())
        for m in (self.val_loss, self.val_abs, self.val_bad1, self.val_n, self.val_rel):
            m.reset()


# -- calibration (inference: stereo_io) ------------------------------------------------------------
def calibrate_spread(
    disp: np.ndarray, spread: np.ndarray, gt: np.ndarray, valid_density: float, max_disparity: float
) -> tuple[float, dict[str, float]]:
    """The spread threshold (px) that keeps ``valid_density`` of the ground-truth pixels
    (``0 < gt < max_disparity``) and the calibration table: ``spread_decile<k>/{spread_max_px,
    epe, bad1}`` per spread decile, plus EPE / bad-1 kept and dropped at the threshold."""
    has = (gt > 0) & (gt < max_disparity)
    s, e = spread[has].astype(np.float64), np.abs(disp[has] - gt[has]).astype(np.float64)
    if s.size == 0:
        raise ValueError("calibrate_spread: no ground-truth pixels")
    thr = float(np.quantile(s, valid_density))
    edges = np.quantile(s, np.linspace(0, 1, 11))
    k = np.clip(np.searchsorted(edges, s, side="right") - 1, 0, 9)
    cnt = np.bincount(k, minlength=10)
    se = np.bincount(k, weights=e, minlength=10)
    sb = np.bincount(k, weights=(e > 1.0).astype(float), minlength=10)
    table: dict[str, float] = {}
    for i in range(10):
        c = max(cnt[i], 1)
        table[f"spread_decile{i}/spread_max_px"] = float(edges[i + 1])
        table[f"spread_decile{i}/epe"] = float(se[i] / c)
        table[f"spread_decile{i}/bad1"] = float(sb[i] / c)
    keep = s <= thr
    for name, m in (("kept", keep), ("dropped", ~keep)):
        table[f"spread_{name}/epe"] = float(e[m].mean()) if m.any() else float("nan")
        table[f"spread_{name}/bad1"] = float((e[m] > 1.0).mean()) if m.any() else float("nan")
    table["spread_kept/density"] = float(keep.mean())
    return thr, table


# -- a whole training run -------------------------------------------------------------------------------
@dataclass(frozen=True)
class StereoData:
    """The training data: a ``data/risk`` folder, the seed and (``base: sgm`` mode) the
    ``data/disparity`` folder made from it."""

    root: Path
    seed: int
    disparity: Path | None = None
    #: road templates left out of training and validation (the generalisation model)
    exclude_templates: tuple[str, ...] = ()

    def manifest_hash(self) -> str:
        return Dataset(self.root, kind="risk", verify=False).manifest_hash()


def fit_stereo(
    data: StereoData,
    *,
    spec: StereoNetSpec,
    train: StereoTrainConfig,
    trainer_settings: common.TrainerSettings,
    outputs: ModelOutputs,
    tracking: TrackingSettings | None = None,
    resume_dir: str | Path | None = None,
) -> FitResult | None:
    """Train on the fault-free train split (random crops), keep the best epoch on ``val/epe``
    (full validation frames), calibrate the spread threshold on validation and publish the model
    files ``outputs`` (each atomically, only after training succeeded). MLflow: ``tracking``."""
    from traffictwin import resume

    common.seed_everything(data.seed)
    digest = data.manifest_hash()
    if spec.base == "sgm" and data.disparity is None:
        raise DatasetError(f"{data.root}: base 'sgm' trains on data/disparity: none given")
    dsgm = data.disparity if spec.base == "sgm" else None
    held = tuple(data.exclude_templates)
    tr = load_pairs(
        data.root, "train", train.max_train_frames, disparity=dsgm, exclude_templates=held
    )
    va = load_pairs(data.root, "val", train.val_frames, disparity=dsgm, exclude_templates=held)
    image_size = list(tr["disp_gt"].shape[1:])
    if tr["disp_gt"].shape[2] < train.crop_width or tr["disp_gt"].shape[1] < train.crop_height:
        raise DatasetError(
            f"{data.root}: images {image_size} px smaller than the crop "
            f"{train.crop_height}x{train.crop_width} px (stereo_model.train)"
        )
    crops = CropSet(tr, train.crop_height, train.crop_width, data.seed)
    gen = torch.Generator().manual_seed(data.seed)
    sampler = RandomSampler(
        crops, replacement=True, num_samples=train.steps_per_epoch * train.batch_size, generator=gen
    )
    train_dl = DataLoader(crops, batch_size=train.batch_size, sampler=sampler, drop_last=True)
    val_dl = DataLoader(full_frames(va), batch_size=4, shuffle=False)
    hp_keys = ("lr", "lr_factor", "lr_patience", "weight_decay", "rel_weight", "coarse_weight")
    hparams = {k: getattr(train, k) for k in hp_keys}
    meta_base = {
        "problem": PROBLEM,
        "data_manifest_hash": digest,
        "seed": int(data.seed),
        "profile": tracking.profile if tracking else "default",
        "image_size": image_size,
        "holdout_templates": list(held),
    }
    module = StereoLitModule(spec.as_dict(), hparams, meta_base)
    tracking = tracking or TrackingSettings("stereo", "stereo", stage="train_stereo", enabled=False)
    session = resume.Session(
        resume_dir,
        {"problem": PROBLEM, "spec": spec.as_dict(), "train": vars(train), "meta": meta_base},
    )
    record = common.RunRecord(
        tags={DATA_TAG: digest, "network": "stereo"},
        params={"data.manifest_hash": digest, "model.param_count": param_count(module.net)},
        datasets=[(data.root, digest)],
    )
    loop = common.FitLoop(
        monitor=SELECTION_METRIC,
        max_epochs=train.max_epochs,
        patience=train.early_stopping_patience,
        hint="stereo_model.train.lr",
    )
    return common.fit_and_publish(
        module,
        (train_dl, val_dl),
        settings=trainer_settings,
        loop=loop,
        tracking=tracking,
        session=session,
        record=record,
        publish=lambda f: _publish(f, spec, train, module, va, meta_base, outputs, len(tr["left"])),
    )


def _publish(
    fitted: common.Fitted,
    spec: StereoNetSpec,
    train: StereoTrainConfig,
    module: StereoLitModule,
    val: dict[str, np.ndarray],
    meta_base: dict[str, Any],
    outputs: ModelOutputs,
    n_train: int,
) -> FitResult:
    if fitted.best is None:
        raise RuntimeError(
            "stereo training produced no checkpoint (no finite val/epe: NaN/inf in the data or "
            "the learning rate stereo_model.train.lr?)"
        )
    slim = fitted.model_checkpoint(PROBLEM, spec.as_dict())
    row = fitted.best_row()
    if not math.isfinite(float(row.get(SELECTION_METRIC, float("nan")))):
        raise RuntimeError(f"stereo: best epoch has a non-finite {SELECTION_METRIC}: {row}")
    net = StereoNet(spec)
    net.load_state_dict(common.net_state_dict(slim))
    disp, spread = predict(net, val["left"], val["right"], sgm=val.get("disp_sgm"))
    gt = val["disp_gt"]
    if spec.base == "sgm":  # valid = SGM's valid: the spread (|residual|) table is information only
        gt = np.where(val["disp_sgm"] >= 0, gt, 0.0)
    thr, table = calibrate_spread(disp, spread, gt, train.valid_density, spec.max_disparity)
    if spec.base == "sgm":
        thr = spec.sgm_spread_bound_px  # the largest spread it can report: keeps every SGM pixel
    metrics = common.fit_metrics(
        fitted,
        train.max_epochs,
        samples_seen=train.steps_per_epoch * train.batch_size * len(fitted.history.rows),
        param_count=param_count(net),
        train_frames=n_train,
        val_frames=len(val["left"]),
        spread_threshold_px=thr,
        **{f"calibration/{k}": v for k, v in table.items()},
    )
    meta = {
        **meta_base,
        "architecture": spec.as_dict(),
        "param_count": param_count(net),
        "hparams": dict(module.hp),
        "best_epoch": slim["epoch"],
        "selection_metric": SELECTION_METRIC,
        "best_val_epe": metrics.get("val/epe"),
        "spread_threshold_px": thr,
        "valid_density": train.valid_density,
    }
    slim["traffictwin"].update(json.loads(json.dumps(meta, default=str)))
    uri = None
    if fitted.run is not None:
        common.log_final_metrics(
            fitted.logger, {f"best/{k.replace('/', '_')}": v for k, v in metrics.items()}
        )
        example = pack_pairs(val["left"][:1], val["right"][:1], _first(val.get("disp_sgm")))
        metadata = {"data_manifest_hash": meta["data_manifest_hash"], "base": spec.base}
        packed = PackedStereo(net.eval(), thr)
        uri = common.log_fitted_model(fitted, slim, meta, metrics, packed, example, metadata)
    common.publish(fitted, outputs, slim, meta, metrics)
    return common.fit_result(fitted, outputs, meta, metrics, uri)


def _first(a: np.ndarray | None) -> np.ndarray | None:
    return None if a is None else a[:1]
