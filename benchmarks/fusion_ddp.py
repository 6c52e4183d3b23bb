"""Fusion training throughput through Lightning, one process vs DDP ranks on this CPU (prints JSON).

    python -m benchmarks.fusion_ddp --devices 1 --threads 2     # one process, 2 torch threads
    python -m benchmarks.fusion_ddp --devices 2 --threads 1     # 2 DDP ranks (gloo), 1 thread each

The default profile's network (conf/fusion_model/resnet18.yaml: batch 8 per rank, flip/rotation
augmentation, channels_last) at the default grid (``--rows 256 --cols 176``) is trained by
:class:`~traffictwin.fusion.training.FusionLitModule` and
:class:`~traffictwin.fusion.training.FusionDataModule` (so DDP shares each epoch's draw, see
:class:`~traffictwin.trainer.RankShardSampler`) on random masses; the one validation batch after the epoch (the LR plateau needs it) is not timed.
``train_samples_per_s``: samples of all ranks per second of wall time from the start of step
``--warmup`` to the end of the last step (rank zero's clock; DDP steps are synchronous), i.e.
after process start-up, the gloo rendezvous and the first steps. Figures depend on the
machine's load; the JSON records the CPU, threads and the 1-min load average before and after.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch
import yaml
from lightning.pytorch.callbacks import Callback

from benchmarks.fusion_model import _cpu_name
from traffictwin.config import typed
from traffictwin.fusion.training import (
    DataSettings,
    FusionDataModule,
    FusionLitModule,
    FusionModelConfig,
)
from traffictwin.trainer import TrainerSettings, build_trainer

ROOT = Path(__file__).resolve().parents[1]


class StepClock(Callback):
    """Wall time from the start of training step ``warmup`` to the end of the last step."""

    def __init__(self, warmup: int) -> None:
        self.warmup = warmup
        self.t0 = self.t1 = 0.0
        self.steps = 0

    def on_train_batch_start(
        self, trainer: Any, pl_module: Any, batch: Any, batch_idx: int
    ) -> None:
        if batch_idx == self.warmup:
            self.t0 = time.perf_counter()

    def on_train_batch_end(
        self, trainer: Any, pl_module: Any, outputs: Any, batch: Any, batch_idx: int
    ) -> None:
        if batch_idx >= self.warmup:
            self.t1 = time.perf_counter()
            self.steps = batch_idx - self.warmup + 1


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description="fusion DDP training throughput on CPU (JSON)")
    ap.add_argument("--devices", type=int, default=1, help="DDP ranks (1: one process, no DDP)")
    ap.add_argument("--threads", type=int, default=1, help="torch intra-op threads per rank")
    ap.add_argument("--steps", type=int, default=24, help="timed optimiser steps per rank")
    ap.add_argument("--warmup", type=int, default=3, help="untimed first steps")
    ap.add_argument("--rows", type=int, default=256)
    ap.add_argument("--cols", type=int, default=176)
    a = ap.parse_args(argv)
    path = ROOT / "conf" / "fusion_model" / "resnet18.yaml"
    group = typed(yaml.safe_load(path.read_text()), FusionModelConfig, key="", source=path)
    bs = group.train.batch_size
    per_rank = (a.steps + a.warmup) * bs
    n = per_rank * a.devices
    g = torch.Generator().manual_seed(0)
    x = torch.rand(n, 4, a.rows, a.cols, generator=g) / 2  # m_F + m_O <= 1 per map
    y = torch.rand(n, 2, a.rows, a.cols, generator=g) / 2
    dm = FusionDataModule(
        ROOT / "unused",
        DataSettings(batch_size=bs, train_samples_per_epoch=n, val_samples=bs),
        seed=0,
        tensors={"train": (x, y), "val": (x[:bs], y[:bs])},
    )
    module = FusionLitModule(group.deeplab_spec(path, key="").as_dict(), asdict(group.hparams()))
    settings = TrainerSettings(
        accelerator="cpu",
        devices=a.devices,
        strategy="ddp" if a.devices > 1 else "auto",
        num_threads=a.threads,
    )
    clock = StepClock(a.warmup)
    trainer = build_trainer(settings, max_epochs=1, callbacks=[clock])
    load0 = os.getloadavg()[0]
    trainer.fit(module, datamodule=dm)
    if not trainer.is_global_zero:
        return
    seconds = clock.t1 - clock.t0
    samples = clock.steps * bs * trainer.world_size
    print(
        json.dumps(
            {
                "machine": {
                    "cpu": _cpu_name(),
                    "cores": os.cpu_count(),
                    "torch": torch.__version__,
                    "loadavg_1min_before": round(load0, 2),
                    "loadavg_1min_after": round(os.getloadavg()[0], 2),
                },
                "network": group.name,
                "grid": [a.rows, a.cols],
                "ranks": trainer.world_size,
                "threads_per_rank": torch.get_num_threads(),
                "batch_per_rank": bs,
                "timed_steps": clock.steps,
                "train_seconds": round(seconds, 2),
                "train_samples_per_s": round(samples / seconds, 2),
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
