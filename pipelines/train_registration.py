"""Stage `train_registration`: train the one learned registration, for every pose-noise level.

Usage: ``python -m pipelines.train_registration``. Reads params.yaml (``registration_model``,
``trainer``, ``grid``, ``seed``, ``configurations``, ``training_noise``) and
``data/prealigned/mixed`` (train / val splits with the noisy and true relative poses, the
``training_noise`` mixture); the augmentation draws from the mixture's largest configuration
(× ``registration_model.train.augment_scale``). Writes, each atomically and only after training
succeeded: ``models/registration/learned/model.ckpt`` (best on val/loss), ``model_meta.json``,
``reports/metrics/train_registration.json`` and ``reports/plots/train_registration.csv`` (the
learning curves, which plot_data draws). MLflow: experiment ``registration``,
run ``registration``. Library: :mod:`traffictwin.fusion.registration_training`.
"""

from __future__ import annotations

import argparse

from traffictwin.config import flatten, get, typed
from traffictwin.fusion.config import (
    MIXED,
    grid_config,
    pose_configurations,
    training_noise,
    training_noise_description,
)
from traffictwin.fusion.model_config import RegistrationModelConfig
from traffictwin.trainer.settings import TrainerSettings
from traffictwin.trainer.tracking import TrackingSettings

from ._common import params, run_stage, setup_logging, stage_timer, training_record
from ._paths import (
    PARAMS,
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
    # the training imports Lightning: here, not at module level (check_params reads model_config)
    from traffictwin.fusion.registration_training import RegistrationSettings, fit_registration
    from traffictwin.fusion.training_data import TrainingSet
    from traffictwin.trainer.publish import ModelOutputs

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.parse_args(argv)
    p = params()
    rc = model_config(p)
    configs = pose_configurations(p)
    tn = training_noise(p)
    log = setup_logging()
    largest = tn.largest(configs)
    noise = training_noise_description(p, MIXED)
    grid = grid_config(p)
    trainer = TrainerSettings.from_cfg(p, source=PARAMS.name)
    trainer.check_available(PARAMS.name)
    stage = "train_registration"
    tracking = TrackingSettings(
        experiment="registration",
        run_name="registration",
        profile=get(p, "profile.name", str),
        stage=stage,
        params=flatten(
            {
                KEY: get(p, KEY, dict),
                "trainer": get(p, "trainer", dict),
                "grid": get(p, "grid", dict),
                "seed": get(p, "seed", int),
                "training_noise": {"name": MIXED, **noise},
            }
        ),
    )
    out = registration_model_dir()
    name = "train_registration"
    with stage_timer(stage) as record:
        res = fit_registration(
            TrainingSet(
                prealigned(MIXED),
                MIXED,
                noise,
                grid,
                get(p, "seed", int, min=0) + rc.train.seed_offset,
            ),
            model=RegistrationSettings(
                rc.net_spec(PARAMS.name), rc.train, rc.min_gain, (largest.r, largest.alpha)
            ),
            trainer_settings=trainer,
            outputs=ModelOutputs(
                out / "model.ckpt", out / "model_meta.json", metrics_file(name), plot_file(name)
            ),
            tracking=tracking,
            resume_dir=resume_dir(stage),
        )
        if res is not None:
            record.update(training_record(res, out / "model.ckpt"))
    if res is not None:
        m = res.metrics
        log.info(
            "%s: best epoch %s of %s, val success %.2f, trans err %.2f m, rot err %.2f deg, %.1f s",
            stage,
            m["best_epoch"] + 1,  # logs count epochs from 1; best_epoch is stored 0-based
            m["epochs"],
            m.get("val/success_rate", float("nan")),
            m.get("val/trans_err_m", float("nan")),
            m.get("val/rot_err_deg", float("nan")),
            res.train_seconds,
        )


if __name__ == "__main__":
    run_stage(main, "train_registration")
