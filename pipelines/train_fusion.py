"""Stages `train_fusion` / `train_fusion_variant@<name>`: train one evidential DeepLabV3+ fusion network.

Usage: ``python -m pipelines.train_fusion`` (the one network: default loss, trained on
``data/prealigned/mixed``, the ``training_noise`` mixture; serves every configuration;
``models/fusion/network``) or ``--variant paper`` (``fusion_variants.paper``: its training set
``data/<inputs>/<config>``, ``config`` = ``mixed`` or one configuration, and its loss;
``models/fusion/paper``). Reads params.yaml (``fusion_model``, ``trainer``, ``grid``, ``seed``,
``configurations``, ``training_noise``, ``fusion_variants``) and writes, each atomically and only
after training succeeded: ``models/fusion/<name>/model.ckpt`` (best on val/kld_full = KLD(b)),
``models/fusion/<name>/model_meta.json``, ``reports/metrics/train_fusion_<name>.json``
and ``reports/plots/train_fusion_<name>.csv`` (the learning curves, which plot_data draws).
MLflow: experiment ``fusion``, run ``fusion-<name>``.
"""

from __future__ import annotations

import argparse
from contextlib import nullcontext

from traffictwin.config import ConfigError, flatten, get, typed
from traffictwin.fusion.config import (
    MIXED,
    NETWORK_MODEL,
    fusion_variants,
    grid_config,
    training_noise,
    training_noise_description,
)
from traffictwin.fusion.model_config import FusionModelConfig
from traffictwin.fusion.training import FusionSettings, fit_fusion
from traffictwin.fusion.training_data import TrainingSet
from traffictwin.trainer import ModelOutputs, TrackingSettings, TrainerSettings, global_rank

from ._common import params, run_stage, setup_logging, stage_timer, training_record
from ._paths import (
    PARAMS,
    fusion_data_dir,
    fusion_model_dir,
    metrics_file,
    plot_file,
    resume_dir,
)


def _target(argv: list[str] | None) -> tuple[str, str, str, str | None, object]:
    """``(name, training set, inputs, loss or None, params)`` of the one network or ``--variant``."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--variant", help="a key of `fusion_variants` in params.yaml")
    a = ap.parse_args(argv)
    p = params()
    if a.variant is None:
        training_noise(p)  # the mixture must be valid before any work
        return NETWORK_MODEL, MIXED, "prealigned", None, p
    variants = fusion_variants(p)
    if a.variant not in variants:
        raise ConfigError(
            f"params.yaml: '{a.variant}' is not a key of 'fusion_variants' (has {sorted(variants)})"
        )
    v = variants[a.variant]
    return a.variant, v.config, v.inputs, v.loss, p


def main(argv: list[str] | None = None) -> None:
    name, cfg_name, inputs, loss, p = _target(argv)
    log = setup_logging()
    noise = training_noise_description(p, cfg_name)
    grid = grid_config(p)
    source = PARAMS.name
    model_cfg = typed(p["fusion_model"], FusionModelConfig, key="fusion_model", source=source)
    spec = model_cfg.deeplab_spec(source)
    hparams = model_cfg.hparams(loss)
    trainer = TrainerSettings.from_cfg(p, source=source)
    trainer.check_available(source)
    stage = "train_fusion" if name == NETWORK_MODEL else f"train_fusion_variant@{name}"
    logged = flatten(
        {
            "fusion_model": get(p, "fusion_model", dict),
            "trainer": get(p, "trainer", dict),
            "grid": get(p, "grid", dict),
            "seed": get(p, "seed", int),
            "configuration": {"name": cfg_name, **noise},
            "network": {"name": name, "inputs": inputs, "loss": hparams.loss},
        }
    )
    tracking = TrackingSettings(
        experiment="fusion",
        run_name=f"fusion-{name}",
        profile=get(p, "profile.name", str),
        stage=stage,
        params=logged,
    )
    out_dir = fusion_model_dir(name)
    # under DDP the launcher re-runs this script per rank: only rank zero times the stage
    with stage_timer(stage) if global_rank() == 0 else nullcontext({}) as record:
        res = fit_fusion(
            TrainingSet(
                fusion_data_dir(inputs, cfg_name),
                cfg_name,
                noise,
                grid,
                get(p, "seed", int, min=0) + model_cfg.train.seed_offset,
                inputs,
            ),
            model=FusionSettings(
                spec, hparams, model_cfg.data(trainer.num_workers), model_cfg.loop(), name
            ),
            trainer_settings=trainer,
            outputs=ModelOutputs(
                out_dir / "model.ckpt",
                out_dir / "model_meta.json",
                metrics_file(f"train_fusion_{name}"),
                plot_file(f"train_fusion_{name}"),
            ),
            tracking=tracking,
            resume_dir=resume_dir(stage),
        )
        if res is not None:
            record.update(training_record(res, out_dir / "model.ckpt"))
    if res is not None:
        m = res.metrics
        log.info(
            "%s: best epoch %s of %s, val KLD(b) %.4f (naive %.4f), val loss %.4f, %.1f s",
            stage,
            m["best_epoch"] + 1,  # logs count epochs from 1; best_epoch is stored 0-based
            m["epochs"],
            m.get("val/kld_full", float("nan")),
            m.get("val/kld_full_naive", float("nan")),
            m.get("val/loss", float("nan")),
            res.train_seconds,
        )


if __name__ == "__main__":
    run_stage(main, "train_fusion")
