"""Stage `train_stereo`: train the learned stereo network on data/risk's exact disparity.

Usage: ``python -m pipelines.train_stereo``. Reads params.yaml (``stereo_model``, ``trainer``,
``seed``), ``data/risk`` (fault-free train pairs as random crops, fault-free validation pairs
whole) and, for ``architecture.base: sgm`` (the refiner of SGM), ``data/disparity``'s SGM of the
same frames (full-frame SGM, cropped like the images). Writes, each atomically and only after training succeeded:
``models/stereo/learned/model.ckpt`` (best on val/epe), ``model_meta.json`` (with the spread
threshold calibrated on validation), ``reports/metrics/train_stereo.json``,
and ``reports/plots/train_stereo.csv`` (the learning curves, which plot_data draws).
MLflow: experiment ``stereo``, run ``stereo``. Library: :mod:`traffictwin.risk.stereo_training`.

``--holdout`` (stage ``train_stereo_holdout``): the same network and training without the frames
of ``stereo_model.holdout_templates`` (training and validation alike) -> ``models/stereo/holdout``,
``reports/metrics/train_stereo_holdout.json`` and ``reports/plots/train_stereo_holdout.csv``
(MLflow run ``stereo-holdout``): the generalisation model stereo_learned scores on the test
frames of those templates.
"""

from __future__ import annotations

import argparse

from traffictwin.config import ConfigError, flatten, get, typed
from traffictwin.io.shards import DatasetError
from traffictwin.stereo.model_config import StereoModelConfig

from ._common import params, run_stage, setup_logging, stage_timer, training_record
from ._paths import (
    DISPARITY,
    PARAMS,
    RISK_DATA,
    STEREO_HOLDOUT_MODEL,
    STEREO_MODEL,
    metrics_file,
    plot_file,
    resume_dir,
)

KEY = "stereo_model"
STAGE = "train_stereo"
HOLDOUT_STAGE = "train_stereo_holdout"


def model_config(p) -> StereoModelConfig:
    """The validated ``stereo_model`` group (its architecture builds, the crop fits it)."""
    mc = typed(get(p, KEY, dict), StereoModelConfig, key=KEY, source=PARAMS.name)
    mc.net_spec(PARAMS.name)
    return mc


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--holdout",
        action="store_true",
        help="train without stereo_model.holdout_templates -> models/stereo/holdout",
    )
    args = ap.parse_args(argv)
    # the training modules import Lightning: only here (the argument checks above stay light)
    from traffictwin.risk.stereo_training import StereoData, fit_stereo
    from traffictwin.trainer import ModelOutputs, TrackingSettings, TrainerSettings

    p = params()
    mc = model_config(p)
    spec = mc.net_spec(PARAMS.name)
    held = tuple(mc.holdout_templates) if args.holdout else ()
    if args.holdout and not held:
        raise ConfigError(
            f"{PARAMS.name}: 'stereo_model.holdout_templates' is empty: the generalisation model "
            "needs at least one road template to leave out"
        )
    stage, out = (HOLDOUT_STAGE, STEREO_HOLDOUT_MODEL) if args.holdout else (STAGE, STEREO_MODEL)
    if not (RISK_DATA / "manifest.json").exists():
        raise DatasetError(f"{RISK_DATA}: no manifest.json (run `dvc repro generate_risk` first)")
    if spec.base == "sgm" and not (DISPARITY / "manifest.json").exists():
        raise DatasetError(f"{DISPARITY}: no manifest.json (run `dvc repro disparity` first)")
    log = setup_logging()
    trainer = TrainerSettings.from_cfg(p, source=PARAMS.name)
    trainer.check_available(PARAMS.name)
    tracking = TrackingSettings(
        experiment="stereo",
        run_name="stereo-holdout" if args.holdout else "stereo",
        profile=get(p, "profile.name", str),
        stage=stage,
        params=flatten(
            {
                KEY: get(p, KEY, dict),
                "trainer": get(p, "trainer", dict),
                "seed": get(p, "seed", int),
            }
        ),
    )
    with stage_timer(stage) as record:
        res = fit_stereo(
            StereoData(RISK_DATA, get(p, "seed", int, min=0), DISPARITY, held),
            spec=spec,
            train=mc.train,
            trainer_settings=trainer,
            outputs=ModelOutputs(
                out / "model.ckpt", out / "model_meta.json", metrics_file(stage), plot_file(stage)
            ),
            tracking=tracking,
            resume_dir=resume_dir(stage),
        )
        if res is not None:
            record.update(training_record(res, out / "model.ckpt"))
    if res is not None:
        m = res.metrics
        log.info(
            "%s: best epoch %s of %s, val EPE %.3f px, bad-1 %.3f, spread threshold %.2f px, %.1f s",
            stage,
            m["best_epoch"] + 1,
            m["epochs"],
            m.get("val/epe", float("nan")),
            m.get("val/bad1", float("nan")),
            m["spread_threshold_px"],
            res.train_seconds,
        )


if __name__ == "__main__":
    import sys

    run_stage(main, HOLDOUT_STAGE if "--holdout" in sys.argv[1:] else STAGE)
