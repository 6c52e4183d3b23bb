"""Stages `train_fusion@<cfg>` / `train_fusion_variant@<name>`: train one evidential DeepLabV3+ fusion network.

Usage: ``python -m pipelines.train_fusion --cfg B`` (the default-loss network of configuration B,
on ``data/prealigned/B``) or ``--variant D-paper`` (``fusion_variants.D-paper``: its configuration,
its inputs ``data/<inputs>/<config>`` and its loss). Reads params.yaml (``fusion_model``,
``trainer``, ``grid``, ``seed``, ``configurations``, ``fusion_variants``) and writes, each
atomically and only after training succeeded: ``models/fusion/<name>/model.ckpt`` (best on
val/kld_full = KLD(b)), ``models/fusion/<name>/model_meta.json``,
``reports/metrics/train_fusion_<name>.json``, ``reports/plots/train_fusion_<name>.csv`` and the
learning curves ``reports/figures/train_fusion_<name>.png``.
MLflow: experiment ``fusion``, run ``fusion-<name>``.
"""

from __future__ import annotations

import os

# Before torch loads libgomp: idle OpenMP threads sleep instead of spinning. On a small machine
# shared with other jobs, spinning made 2 torch threads ~3x slower than 1 thread; with passive
# waiting they stay within ~20 % of it (and use both cores when the machine is idle). Override by
# exporting OMP_WAIT_POLICY.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


import argparse  # noqa: E402
from contextlib import nullcontext  # noqa: E402

from traffictwin.config import ConfigError, flatten, get, typed  # noqa: E402
from traffictwin.fusion.config import (  # noqa: E402
    fusion_variants,
    grid_config,
    pose_configurations,
)
from traffictwin.fusion.training import (  # noqa: E402
    FusionModelConfig,
    TrackingSettings,
    fit_fusion,
)
from traffictwin.trainer import TrainerSettings, global_rank  # noqa: E402

from ._common import params, run_stage, setup_logging, stage_timer, training_record  # noqa: E402
from ._paths import (  # noqa: E402
    PARAMS,
    figure_file,
    fusion_data_dir,
    fusion_model_dir,
    metrics_file,
    plot_file,
    resume_dir,
)


def _target(argv: list[str] | None) -> tuple[str, str, str, str | None, object]:
    """``(name, configuration, inputs, loss or None, params)`` of ``--cfg`` or ``--variant``."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--cfg", help="pose-noise configuration (a key of `configurations`)")
    g.add_argument("--variant", help="a key of `fusion_variants` in params.yaml")
    a = ap.parse_args(argv)
    p = params()
    configs = pose_configurations(p)
    if a.cfg is not None:
        if a.cfg not in configs:
            raise ConfigError(
                f"params.yaml: configuration '{a.cfg}' not in 'configurations' (has {sorted(configs)})"
            )
        return a.cfg, a.cfg, "prealigned", None, p
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
    pose_noise = pose_configurations(p)[cfg_name]
    noise = {"r": pose_noise.r, "alpha": pose_noise.alpha}
    grid = grid_config(p)
    source = PARAMS.name
    model_cfg = typed(p["fusion_model"], FusionModelConfig, key="fusion_model", source=source)
    spec = model_cfg.deeplab_spec(source)
    hparams = model_cfg.hparams(loss)
    trainer = TrainerSettings.from_cfg(p, source=source)
    trainer.check_available(source)
    stage = f"train_fusion@{name}" if name == cfg_name else f"train_fusion_variant@{name}"
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
            fusion_data_dir(inputs, cfg_name),
            spec=spec,
            hparams=hparams,
            data=model_cfg.data(trainer.num_workers),
            loop=model_cfg.loop(),
            trainer_settings=trainer,
            seed=get(p, "seed", int, min=0),
            grid=grid,
            cfg_name=cfg_name,
            network=name,
            inputs=inputs,
            noise=noise,
            ckpt_out=out_dir / "model.ckpt",
            meta_out=out_dir / "model_meta.json",
            metrics_out=metrics_file(f"train_fusion_{name}"),
            curves_out=plot_file(f"train_fusion_{name}"),
            tracking=tracking,
            resume_dir=resume_dir(stage),
        )
        if res is not None:
            record.update(training_record(res, out_dir / "model.ckpt"))
    if res is not None:
        from traffictwin.fusion.figures import save_figure
        from traffictwin.fusion.training_figures import learning_curves

        title = f"{name}: {inputs} inputs of {cfg_name}, loss {hparams.loss}"
        save_figure(learning_curves(res.history, title), figure_file(f"train_fusion_{name}"))
        if res.run_id:
            from traffictwin.mlops.tracking import log_run_artifact

            log_run_artifact(res.run_id, figure_file(f"train_fusion_{name}"), "figures")
        m = res.metrics
        log.info(
            "%s: best epoch %s of %s, val KLD(b) %.4f (naive %.4f), val loss %.4f, %.1f s",
            stage,
            m["best_epoch"],
            m["epochs"],
            m.get("val/kld_full", float("nan")),
            m.get("val/kld_full_naive", float("nan")),
            m.get("val/loss", float("nan")),
            res.train_seconds,
        )


if __name__ == "__main__":
    run_stage(main, "train_fusion")
