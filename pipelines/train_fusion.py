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


from traffictwin.config import flatten, get, typed  # noqa: E402
from traffictwin.fusion.config import grid_config  # noqa: E402
from traffictwin.fusion.training import (  # noqa: E402
    FusionModelConfig,
    TrackingSettings,
    fit_fusion,
)
from traffictwin.trainer import TrainerSettings  # noqa: E402

from ._common import run_stage, setup_logging, stage_timer  # noqa: E402
from ._configuration import configuration  # noqa: E402
from ._paths import (  # noqa: E402
    PARAMS,
    fusion_model_dir,
    metrics_file,
    plot_file,
    prealigned,
)


def main(argv: list[str] | None = None) -> None:
    name, pose_noise, p = configuration(argv, __doc__.splitlines()[0])
    log = setup_logging()
    noise = {"r": pose_noise.r, "alpha": pose_noise.alpha}
    grid = grid_config(p)
    source = PARAMS.name
    model_cfg = typed(p["fusion_model"], FusionModelConfig, key="fusion_model", source=source)
    spec = model_cfg.deeplab_spec(source)
    trainer = TrainerSettings.from_cfg(p, source=source)
    stage = f"train_fusion@{name}"
    logged = flatten(
        {
            "fusion_model": get(p, "fusion_model", dict),
            "trainer": get(p, "trainer", dict),
            "grid": get(p, "grid", dict),
            "seed": get(p, "seed", int),
            "configuration": {"name": name, **noise},
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
    with stage_timer(stage):
        res = fit_fusion(
            prealigned(name),
            spec=spec,
            hparams=model_cfg.hparams(),
            data=model_cfg.data(trainer.num_workers),
            loop=model_cfg.loop(),
            trainer_settings=trainer,
            seed=get(p, "seed", int, min=0),
            grid=grid,
            cfg_name=name,
            noise=noise,
            ckpt_out=out_dir / "model.ckpt",
            meta_out=out_dir / "model_meta.json",
            metrics_out=metrics_file(f"train_fusion_{name}"),
            curves_out=plot_file(f"train_fusion_{name}"),
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
