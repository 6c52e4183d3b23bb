"""Stage `train_registration@<cfg>`: train the learned registration of one pose-noise configuration.

Usage: ``python -m pipelines.train_registration --cfg D``. Reads params.yaml
(``registration_model``, ``trainer``, ``grid``, ``seed``, ``configurations``) and
``data/prealigned/<cfg>`` (train / val splits with the noisy and true relative poses); writes, each
atomically and only after training succeeded: ``models/registration/<cfg>/model.ckpt`` (best on
val/loss), ``model_meta.json``, ``reports/metrics/train_registration_<cfg>.json``,
``reports/plots/train_registration_<cfg>.csv`` and the learning curves
``reports/figures/train_registration_<cfg>.png``. MLflow: experiment ``fusion``, run
``registration-<cfg>``. Library: :mod:`traffictwin.fusion.registration_training`.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # see pipelines/train_fusion.py

import argparse  # noqa: E402

from traffictwin.config import ConfigError, flatten, get, typed  # noqa: E402
from traffictwin.fusion.config import grid_config, pose_configurations  # noqa: E402
from traffictwin.fusion.registration_training import (  # noqa: E402
    RegistrationModelConfig,
    fit_registration,
)
from traffictwin.trainer import TrackingSettings, TrainerSettings  # noqa: E402

from ._common import params, run_stage, setup_logging, stage_timer, training_record  # noqa: E402
from ._paths import (  # noqa: E402
    PARAMS,
    figure_file,
    metrics_file,
    plot_file,
    prealigned,
    registration_model_dir,
    resume_dir,
)

KEY = "registration_model"


def model_config(p) -> RegistrationModelConfig:
    """The validated ``registration_model`` group (its architecture builds)."""
    rc = typed(get(p, KEY, dict), RegistrationModelConfig, key=KEY, source=PARAMS.name)
    rc.net_spec(PARAMS.name)
    return rc


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--cfg", required=True, help="pose-noise configuration (a key of `configurations`)"
    )
    a = ap.parse_args(argv)
    p = params()
    rc = model_config(p)
    configs = pose_configurations(p)
    if a.cfg not in configs:
        raise ConfigError(
            f"params.yaml: configuration '{a.cfg}' not in 'configurations' (has {sorted(configs)})"
        )
    log = setup_logging()
    noise_cfg = configs[a.cfg]
    noise = {"r": noise_cfg.r, "alpha": noise_cfg.alpha}
    grid = grid_config(p)
    trainer = TrainerSettings.from_cfg(p, source=PARAMS.name)
    trainer.check_available(PARAMS.name)
    stage = f"train_registration@{a.cfg}"
    tracking = TrackingSettings(
        experiment="fusion",
        run_name=f"registration-{a.cfg}",
        profile=get(p, "profile.name", str),
        stage=stage,
        params=flatten(
            {
                KEY: get(p, KEY, dict),
                "trainer": get(p, "trainer", dict),
                "grid": get(p, "grid", dict),
                "seed": get(p, "seed", int),
                "configuration": {"name": a.cfg, **noise},
            }
        ),
    )
    out = registration_model_dir(a.cfg)
    name = f"train_registration_{a.cfg}"
    with stage_timer(stage) as record:
        res = fit_registration(
            prealigned(a.cfg),
            spec=rc.net_spec(PARAMS.name),
            train=rc.train,
            min_gain=rc.min_gain,
            trainer_settings=trainer,
            seed=get(p, "seed", int, min=0),
            grid=grid,
            cfg_name=a.cfg,
            noise=noise,
            ckpt_out=out / "model.ckpt",
            meta_out=out / "model_meta.json",
            metrics_out=metrics_file(name),
            curves_out=plot_file(name),
            tracking=tracking,
            resume_dir=resume_dir(stage),
        )
        if res is not None:
            record.update(training_record(res, out / "model.ckpt"))
    if res is not None:
        from traffictwin.fusion.figures import save_figure
        from traffictwin.fusion.registration_training import learning_curves

        save_figure(
            learning_curves(res.history, f"learned registration, configuration {a.cfg}"),
            figure_file(name),
        )
        if res.run_id:
            from traffictwin.mlops.tracking import log_run_artifact

            log_run_artifact(res.run_id, figure_file(name), "figures")
        m = res.metrics
        log.info(
            "%s: best epoch %s of %s, val success %.2f, trans err %.2f m, rot err %.2f deg, %.1f s",
            stage,
            m["best_epoch"],
            m["epochs"],
            m.get("val/success_rate", float("nan")),
            m.get("val/trans_err_m", float("nan")),
            m.get("val/rot_err_deg", float("nan")),
            res.train_seconds,
        )


if __name__ == "__main__":
    run_stage(main, "train_registration")
