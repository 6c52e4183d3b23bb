"""Helper of tests/test_ddp.py: ``trainer.validate`` of a trained checkpoint on 1 or N CPU ranks.

    python tests/ddp_validate.py fusion --model models/fusion/network --data data/prealigned/mixed \
        --devices 2 --subset 0:2 --subset 3:1 --out val.json
    python tests/ddp_validate.py risk --model models/risk/headline --repo . \
        --devices 2 --subset 0:2 --subset 3:1 --out val.json

Loads the published checkpoint into the stage's LightningModule and DataModule, runs Lightning's
validation loop (``strategy=ddp`` with gloo when ``--devices`` > 1; Lightning's launcher re-runs
this script for the other ranks) once per ``--subset N:B`` (the first N validation samples, 0: all,
in batches of B; one process group for all of them: the ranks start and import once) and writes,
on rank zero, one entry per subset: the ``val/*`` metrics and ``samples_seen``, the number of
validation samples summed over every rank (the subset's size when no sample was left out or
repeated). Not a test module itself (no ``test_`` prefix).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

import torch
from lightning.pytorch.callbacks import Callback

from traffictwin.trainer import TrainerSettings, build_trainer


class CountSamples(Callback):
    """Validation samples seen by this rank, summed over the ranks at the end of the epoch."""

    def __init__(self) -> None:
        self.local = 0
        self.total = 0

    def on_validation_batch_end(
        self, trainer: Any, pl_module: Any, outputs: Any, batch: Any, *a: Any
    ) -> None:
        self.local += int(batch[0].shape[0])

    def on_validation_epoch_end(self, trainer: Any, pl_module: Any) -> None:
        t = torch.tensor(float(self.local), dtype=torch.float64)
        self.total = int(trainer.strategy.reduce(t, reduce_op="sum").item())


def _fusion(a: argparse.Namespace) -> tuple[Any, Any]:
    from traffictwin.fusion.model_io import read_checkpoint
    from traffictwin.fusion.training import DataSettings, FusionDataModule, FusionLitModule
    from traffictwin.grid import GridSpec

    ck = read_checkpoint(Path(a.model) / "model.ckpt")
    info = ck["traffictwin"]
    module = FusionLitModule(info["architecture"], info["hparams"], meta={"seed": info["seed"]})
    module.load_state_dict(ck["state_dict"])
    g = info["grid"]
    settings = DataSettings(batch_size=a.batch_size, val_samples=a.n)
    dm = FusionDataModule(a.data, settings, seed=int(info["seed"]), grid=GridSpec(**g))
    return module, dm


def _risk(a: argparse.Namespace) -> tuple[Any, Any]:
    from traffictwin.risk.model_io import load_risk_model
    from traffictwin.risk.training import (
        RiskArrays,
        RiskDataModule,
        RiskRegressor,
        RiskSource,
        prepare_split,
    )

    model = load_risk_model(a.model)
    repo = Path(a.repo)
    src = RiskSource(repo / "data/risk", repo / "data/disparity", None)
    val = prepare_split(src, model.cfg, "val", model.meta["label"])
    if a.n:
        val = RiskArrays(
            *(getattr(val, k)[: a.n] for k in ("frame_id", "rgb", "disp", "speed", "y"))
        )
    module = RiskRegressor(model.cfg)
    module.net.load_state_dict(model.net.state_dict())
    dm = RiskDataModule(val, val, eval_batch_size=a.batch_size)
    return module, dm


def _subset(text: str) -> tuple[int, int]:
    """``N:B`` -> (samples, batch size)."""
    n, b = text.split(":")
    return int(n), int(b)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("problem", choices=("fusion", "risk"))
    ap.add_argument("--model", required=True)
    ap.add_argument("--data", default="")
    ap.add_argument("--repo", default=".")
    ap.add_argument("--devices", type=int, default=1)
    ap.add_argument("--subset", type=_subset, action="append", required=True, metavar="N:B")
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    torch.set_num_threads(1)
    settings = TrainerSettings(
        accelerator="cpu", devices=a.devices, strategy="ddp" if a.devices > 1 else "auto"
    )
    results = []
    for n, batch_size in a.subset:
        a.n, a.batch_size = n, batch_size
        module, dm = (_fusion if a.problem == "fusion" else _risk)(a)
        counter = CountSamples()
        trainer = build_trainer(settings, max_epochs=1, callbacks=[counter])
        trainer.validate(module, datamodule=dm, verbose=False)
        out = {k: float(v) for k, v in trainer.callback_metrics.items() if k.startswith("val/")}
        out["samples_seen"] = counter.total
        out["world_size"] = trainer.world_size
        results.append(out)
    if trainer.is_global_zero:
        Path(a.out).write_text(json.dumps(results, indent=1, sort_keys=True))
    print(f"rank {trainer.global_rank} pid {os.getpid()} done", file=sys.stderr)


if __name__ == "__main__":
    main()
