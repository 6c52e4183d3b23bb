"""Stage `train_fusion@<cfg>`: train the evidential DeepLabV3+ fusion network for one pose-noise configuration.

Usage: ``python -m pipelines.train_fusion --cfg B``. Reads params.yaml (``fusion_model``,
``trainer``, ``grid``, ``seed``, ``configurations.<cfg>``), trains on ``data/prealigned/<cfg>`` and
writes, each atomically and only after training succeeded:
``models/fusion/<cfg>/model.ckpt`` (best on val/loss), ``models/fusion/<cfg>/model_meta.json``,
``reports/metrics/train_fusion_<cfg>.json``, ``reports/plots/train_fusion_<cfg>.csv``.
MLflow: experiment ``fusion``, run ``fusion-<cfg>``.
"""

from __future__ import annotations

import os

# Before torch loads libgomp: idle OpenMP threads sleep instead of spinning. On a small machine
# shared with other jobs, spinning made 2 torch threads ~3x slower than 1 thread; with passive
# waiting they stay within ~20 % of it (and use both cores when the machine is idle). Override by
# exporting OMP_WAIT_POLICY.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402

from traffictwin.config import ConfigError, flatten, get  # noqa: E402
from traffictwin.fusion.training import (
    DataSettings,
    FusionHParams,
    LoopSettings,
    TrackingSettings,
    fit_fusion,
    spec_from_cfg,
)  # noqa: E402
from traffictwin.grid import GridSpec  # noqa: E402
from traffictwin.trainer import TrainerSettings  # noqa: E402

from ._common import ROOT, params, run_stage, setup_logging, stage_timer  # noqa: E402


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--cfg",
        required=True,
        help="pose-noise configuration (a key of `configurations` in params.yaml)",
    )
    args = ap.parse_args(argv)
    log = setup_logging()
    p = params()
    cfgs = get(p, "configurations", dict)
    if args.cfg not in cfgs:
        raise ConfigError(
            f"params.yaml: configuration '{args.cfg}' not in 'configurations' (have {sorted(cfgs)})"
        )
    noise = {
        "r": get(p, f"configurations.{args.cfg}.r", float, min=0),
        "alpha": get(p, f"configurations.{args.cfg}.alpha", float, min=0),
    }
    grid = GridSpec(
        get(p, "grid.rows", int, min=16),
        get(p, "grid.cols", int, min=16),
        get(p, "grid.cell", float, min=1e-6),
    )
    fm = "fusion_model"
    try:
        spec = spec_from_cfg(get(p, f"{fm}.architecture", dict))
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"params.yaml: '{fm}.architecture' is invalid: {exc}") from None
    hp = FusionHParams(
        lr=get(p, f"{fm}.optim.lr", float, min=1e-9),
        weight_decay=get(p, f"{fm}.optim.weight_decay", float, min=0),
        lr_factor=get(p, f"{fm}.optim.lr_factor", float, min=1e-6, max=1.0),
        lr_patience=get(p, f"{fm}.optim.lr_patience", int, min=0),
        occupied_weight=get(p, f"{fm}.loss.occupied_weight", float, min=1.0),
        kl_weight=get(p, f"{fm}.loss.kl_weight", float, min=0),
        kl_anneal_epochs=get(p, f"{fm}.loss.kl_anneal_epochs", int, min=1),
        augment_flip=get(p, f"{fm}.augment.flip", bool),
        augment_rotation_deg=get(p, f"{fm}.augment.rotation_deg", float, min=0, max=180),
        channels_last=get(p, f"{fm}.train.channels_last", bool),
    )
    trainer = TrainerSettings.from_cfg(p)
    data = DataSettings(
        batch_size=get(p, f"{fm}.train.batch_size", int, min=2),
        train_samples_per_epoch=get(p, f"{fm}.train.train_samples_per_epoch", int, min=0),
        val_samples=get(p, f"{fm}.train.val_samples", int, min=0),
        num_workers=trainer.num_workers,
    )
    clip = get(p, f"{fm}.train.gradient_clip_val", (float, type(None)))
    loop = LoopSettings(
        max_epochs=get(p, f"{fm}.train.max_epochs", int, min=1),
        early_stopping_patience=get(p, f"{fm}.train.early_stopping_patience", int, min=1),
        gradient_clip_val=clip,
    )
    profile = get(p, "profile.name", str)
    stage = f"train_fusion@{args.cfg}"
    logged = flatten(
        {
            "fusion_model": get(p, fm, dict),
            "trainer": get(p, "trainer", dict),
            "grid": get(p, "grid", dict),
            "seed": get(p, "seed", int),
            "configuration": {"name": args.cfg, **noise},
        }
    )
    tracking = TrackingSettings(
        experiment="fusion",
        run_name=f"fusion-{args.cfg}",
        profile=profile,
        stage=stage,
        params=logged,
    )
    out_dir = ROOT / "models" / "fusion" / args.cfg
    with stage_timer(stage):
        res = fit_fusion(
            ROOT / "data" / "prealigned" / args.cfg,
            spec=spec,
            hparams=hp,
            data=data,
            loop=loop,
            trainer_settings=trainer,
            seed=get(p, "seed", int, min=0),
            grid=grid,
            cfg_name=args.cfg,
            noise=noise,
            ckpt_out=out_dir / "model.ckpt",
            meta_out=out_dir / "model_meta.json",
            metrics_out=ROOT / "reports" / "metrics" / f"train_fusion_{args.cfg}.json",
            curves_out=ROOT / "reports" / "plots" / f"train_fusion_{args.cfg}.csv",
            tracking=tracking,
        )
    if res is not None:
        m = res.metrics
        log.info(
            "%s: best epoch %s of %s, val/loss %.4f, val/kld %.4f (naive %.4f), %.1f s",
            stage,
            m["best_epoch"],
            m["epochs"],
            m.get("val/loss", float("nan")),
            m.get("val/kld", float("nan")),
            m.get("val/kld_naive", float("nan")),
            m["train_seconds"],
        )


if __name__ == "__main__":
    run_stage(main, "train_fusion")
