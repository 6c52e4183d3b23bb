"""Training of the DAVE-2-like risk network with Lightning (Feth et al., sec. 3.5).

The data (:class:`RiskSource`, :func:`prepare_split`): :mod:`traffictwin.risk.source`, its
loaders (:class:`RiskDataModule`): :mod:`traffictwin.risk.data_module`; the ``risk_model`` config
group and :class:`TrainConfig`: :mod:`traffictwin.risk.model_config` (all re-exported here, where
the training stages import them; stages that train nothing import the light modules themselves,
so that they do not import Lightning).
The arrays are normalised per batch on the device by the LightningModule (:class:`RiskRegressor`).
Loss: the variant's objective (:func:`~traffictwin.risk.dave2.risk_loss`: the paper's MSE on the
normalised risk, MSE on log THW, or MSE + a classification head at the critical THW); optimiser: Adam with a
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
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd
import torch
from torchmetrics import SumMetric

from traffictwin import resume
from traffictwin.config import flatten
from traffictwin.io.atomic import write_csv_atomic
from traffictwin.mlops.tracking import DATA_TAG
from traffictwin.risk.data_module import RiskDataModule
from traffictwin.risk.dave2 import (
    Dave2,
    Dave2Config,
    PackedDave2,
    count_parameters,
    normalise,
    pack_input,
    raw_to_risk,
    risk_loss,
)
from traffictwin.risk.model_config import (  # noqa: F401 - re-exported: the stages import them here
    LABELS,
    MIN_PRED_STD,
    ObjectiveSchema,
    RiskModelConfig,
    RiskTrainSchema,
    TrainConfig,
    VariantConfig,
)
from traffictwin.risk.model_io import CKPT, risk_checkpoint, risk_meta, save_risk_model
from traffictwin.risk.source import (  # noqa: F401 - re-exported: the stages import them here
    RiskArrays,
    RiskSource,
    check_label,
    input_keys,
    prepare_split,
    read_orb_table,
)
from traffictwin.trainer import (
    FitLoop,
    Fitted,
    NetModule,
    RunRecord,
    TrackingSettings,
    TrainerSettings,
    fit_run,
    log_checkpoint,
    log_final_metrics,
    log_model,
    seed_everything,
)

log = logging.getLogger(__name__)


class CollapsedModelError(RuntimeError):
    """The trained network predicts (nearly) one value for every validation frame."""


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
    splits: tuple[RiskArrays, RiskArrays],
    tc: TrainConfig,
    settings: TrainerSettings | None = None,
    *,
    tracking: TrackingSettings | None = None,
    session: resume.Session | None = None,
    record: RunRecord | None = None,
    fast_dev_run: bool | int = False,
) -> Iterator[tuple[TrainResult, Any] | None]:
    """Train a risk network on ``splits`` = (train, val) with the one training driver
    (:func:`traffictwin.trainer.fit_run`); yields ``(result, fitted)`` inside the still open MLflow
    run (``tracking``, recording ``record``), the result's network holding the weights of the best
    validation loss (CPU, eval mode), or ``None`` on other DDP ranks. ``session``: the run's
    resume folder (:class:`traffictwin.resume.Session`)."""
    settings = settings or TrainerSettings()
    tracking = tracking or TrackingSettings("risk", "risk", stage="train_risk", enabled=False)
    session = session or resume.Session(None, {})
    train, val = splits
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
    with fit_run(
        module,
        dm,
        settings=settings,
        loop=_fit_loop(tc, len(train)),
        tracking=tracking,
        session=session,
        record=record or RunRecord(),
        fast_dev_run=fast_dev_run,
    ) as fitted:
        if fitted is None:  # DDP: another rank trained along; rank zero writes
            yield None
            return
        yield _train_result(fitted, module, splits, tc, fast_dev_run), fitted


def _fit_loop(tc: TrainConfig, n_train: int) -> FitLoop:
    """Validation every ``val_every_n_steps`` optimiser steps, one History row per validation,
    the checkpoint of the lowest validation loss."""
    steps_per_epoch = math.ceil(n_train / tc.batch_size)
    total = steps_per_epoch * tc.epochs
    # validate at least once at the end: the interval never exceeds the run's step count
    interval = max(1, min(tc.val_every_n_steps, total))
    return FitLoop(
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


def _train_result(
    fitted: Fitted,
    module: RiskRegressor,
    splits: tuple[RiskArrays, RiskArrays],
    tc: TrainConfig,
    fast_dev_run: bool | int,
) -> TrainResult:
    """The best checkpoint's network (checked for collapse unless ``fast_dev_run``) and its facts."""
    cfg, (train, val) = module.cfg, splits
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
    return TrainResult(
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
    with fitting(
        cfg, (train, val), tc, settings, session=session, fast_dev_run=fast_dev_run
    ) as out:
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


@dataclass(frozen=True)
class RiskVariant:
    """One risk network to train: the variant's ``name``, its network ``cfg``, training
    ``label`` and optimisation settings ``train``; ``max_train_frames`` subsamples the training
    split (seeded; None: every frame); ``meta``: further facts for ``model_meta.json``."""

    name: str
    cfg: Dave2Config
    label: str
    train: TrainConfig
    max_train_frames: int | None = None
    meta: Mapping[str, Any] = field(default_factory=dict)


def fit_risk(
    data: RiskSource,
    variant: RiskVariant,
    settings: TrainerSettings,
    *,
    out_dir: str | Path,
    curves_out: str | Path | None = None,
    tracking: TrackingSettings | None = None,
    resume_dir: str | Path | None = None,
) -> TrainResult | None:
    """Train ``variant`` on ``data`` and publish it (rank zero; ``None`` on other ranks).

    Writes ``out_dir`` (replaced): ``model.ckpt``, ``model_meta.json`` (``variant.meta`` +
    training facts), ``history.csv``; ``curves_out`` (the same curves, for ``dvc plots``):
    identical runs write identical bytes (the MLflow run id, model URI and training seconds are
    only in the returned :class:`TrainResult`). With
    ``tracking`` enabled: an MLflow run with the params once, the curves, the final metrics,
    the checkpoint and an MLflow model (the same ``model.ckpt`` + ``model_meta.json``, no pickled
    code; its signature is that of :class:`PackedDave2`, one packed input tensor).
    ``resume_dir``: where a killed run's training state waits for the next run with the same
    config, data and code (:mod:`traffictwin.resume`); removed after the outputs are written.
    """
    out_dir = Path(out_dir)
    cfg, label, tc = variant.cfg, variant.label, variant.train
    tracking = tracking or TrackingSettings("risk", f"risk-{variant.name}", enabled=False)
    train = prepare_split(
        data, cfg, "train", label, max_frames=variant.max_train_frames, seed=tc.seed
    )
    val = prepare_split(data, cfg, "val", label)
    log.info(
        "%s: %d train / %d val frames (ORB-passed), label %s",
        tracking.stage,
        len(train),
        len(val),
        label,
    )
    manifest = data.risk.manifest_hash()
    record = _run_record(data, variant, settings, tracking, (train, val))
    session = resume.Session(
        resume_dir,
        {
            "problem": "risk",
            "cfg": cfg.to_dict(),
            "label": label,
            "train": asdict(tc),
            "trainer": settings.as_dict(),
            "variant": variant.name,
            "max_train_frames": variant.max_train_frames,
            "data": [manifest, data.disparity.manifest_hash() if data.disparity else None],
            "frames": [len(train), len(val)],
            "meta": dict(variant.meta),
        },
    )
    with fitting(
        cfg, (train, val), tc, settings, tracking=tracking, session=session, record=record
    ) as out:
        if out is None:  # DDP: the other ranks trained along; rank zero writes
            return None
        res, fitted = out
        full_meta = _publish(res, variant, out_dir, curves_out, manifest, tracking.profile)
        if fitted.run is not None:
            res.model_uri = _log_model(fitted, res, variant, out_dir, full_meta, val)
            res.run_id = fitted.run.info.run_id
    return res


def _run_record(
    data: RiskSource,
    variant: RiskVariant,
    settings: TrainerSettings,
    tracking: TrackingSettings,
    splits: tuple[RiskArrays, RiskArrays],
) -> RunRecord:
    """The MLflow run's tags, params (logged once) and datasets of a risk training."""
    cfg = variant.cfg
    manifest = data.risk.manifest_hash()
    params = {
        **tracking.params,
        "risk_model.variant": variant.name,
        "risk_model.inputs": ",".join(cfg.inputs),
        "risk_model.use_speed": cfg.use_speed,
        "risk_model.effective_label": variant.label,
        **flatten({"trainer": settings.as_dict()}),
        "seed": variant.train.seed,
        "data.n_train": len(splits[0]),
        "data.n_val": len(splits[1]),
    }
    datasets = [(data.risk.root, manifest)]
    if data.disparity is not None:
        datasets.append((data.disparity.root, data.disparity.manifest_hash()))
    tags = {"variant": variant.name, DATA_TAG: manifest, "label": variant.label}
    return RunRecord(tags=tags, params=params, datasets=datasets)


def _publish(
    res: TrainResult,
    variant: RiskVariant,
    out_dir: Path,
    curves_out: str | Path | None,
    manifest: str,
    profile: str,
) -> dict[str, Any]:
    """Replace ``out_dir`` with the model (checkpoint, meta) and its history; the curves to
    ``curves_out``. Returns the model meta."""
    if out_dir.exists():
        shutil.rmtree(out_dir)
    full_meta = {
        "variant": variant.name,
        "label": variant.label,
        "best_val_mse": res.best_val_mse,
        "best_step": res.best_step,
        "steps": res.steps,
        "n_train": res.n_train,
        "n_val": res.n_val,
        "data_manifest": manifest,
        "profile": profile,
        "train": variant.train.__dict__,
        **dict(variant.meta),
    }
    save_risk_model(res.net, out_dir, full_meta)
    for path in (out_dir / "history.csv", *([curves_out] if curves_out else [])):
        write_csv_atomic(path, res.history, float_format="%.9g", lineterminator="\n")
    return full_meta


def _log_model(
    fitted: Fitted,
    res: TrainResult,
    variant: RiskVariant,
    out_dir: Path,
    full_meta: dict[str, Any],
    val: RiskArrays,
) -> str:
    """Into the run's MLflow run: final metrics, the checkpoint and curves, the MLflow model
    (:class:`PackedDave2`'s signature, two validation frames as the example); its URI."""
    cfg = variant.cfg
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
    return log_model(
        risk_checkpoint(res.net, full_meta),
        risk_meta(res.net, full_meta),
        PackedDave2(res.net),
        example,
        metadata={"variant": variant.name, "label": variant.label},
    )


def train_config_dict(tc: TrainConfig) -> dict[str, Any]:
    return asdict(tc)
