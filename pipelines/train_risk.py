"""Stage `train_risk@<variant>`: train one DAVE-2-like risk network (Feth et al. sec. 3.5).

Usage: ``python -m pipelines.train_risk --variant headline``. Reads ``risk_model.*``, ``trainer.*``,
``seed``, ``profile.name``; data ``data/risk``, ``data/disparity``, ``data/orb/orb.csv``.
Writes ``models/risk/<variant>/`` (``model.ckpt``, ``model_meta.json``, ``history.csv``) and
``reports/plots/risk_training_<variant>.csv`` (train/val error per validation, for ``dvc plots``).
MLflow: experiment ``risk``, run ``risk-<variant>`` with the params once, the error curves, the
best checkpoint and an MLflow model (single-tensor input, :class:`~traffictwin.risk.dave2.PackedDave2`).
"""

from __future__ import annotations

import argparse
from contextlib import nullcontext

from traffictwin.config import ConfigError, flatten, get, typed
from traffictwin.risk.dave2_config import Dave2Config
from traffictwin.risk.model_config import RiskModelConfig, TrainConfig
from traffictwin.trainer.settings import TrainerSettings
from traffictwin.trainer.tracking import TrackingSettings, global_rank

from ._common import params, run_stage, setup_logging, stage_timer, training_record
from ._paths import (
    DISPARITY,
    ORB_CSV,
    PARAMS,
    RISK_DATA,
    plot_file,
    resume_dir,
    risk_model_dir,
)


def training_domain(p, model: RiskModelConfig, label: str) -> dict:
    """What a user of the model must reproduce at inference: camera size, SGM / ORB settings, scales,
    label, and ``max_speed`` (m/s): the top ego speed of the training data (the CLI's speed range)."""
    return {
        "camera": {
            "width": get(p, "risk_data.camera.width", int),
            "height": get(p, "risk_data.camera.height", int),
        },
        "max_speed": get(p, "risk_data.max_speed", float),
        "sgm": get(p, "risk_data.sgm", dict),
        "orb": get(p, "risk_data.orb", dict),
        "disp_scale": model.disp_scale,
        "speed_scale": model.speed_scale,
        "label": label,
    }


def risk_model(p) -> RiskModelConfig:
    """The ``risk_model`` group, validated once."""
    return typed(p["risk_model"], RiskModelConfig, key="risk_model", source=PARAMS.name)


def model_config(p, variant: str) -> tuple[Dave2Config, str]:
    """The network config and training label of ``variant``; errors name the key."""
    return variant_config(risk_model(p), variant)


def variant_config(model: RiskModelConfig, variant: str) -> tuple[Dave2Config, str]:
    """``variant``'s network config and label from the validated group."""
    if variant not in model.variants:
        raise ConfigError(
            f"{PARAMS.name}: 'risk_model.variants' has no variant {variant!r} (has {sorted(model.variants)})"
        )
    try:
        return model.variant(variant)
    except ValueError as exc:
        raise ConfigError(f"{PARAMS.name}: risk_model / variant {variant!r}: {exc}") from None


def train_config(p, variant: str | None = None) -> tuple[TrainConfig, int | None]:
    """Optimisation settings (seed = ``seed`` + ``risk_model.train.seed_offset`` + the variant's
    ``seed_offset``) and max_train_frames."""
    return train_settings(risk_model(p), p, variant)


def train_settings(
    model: RiskModelConfig, p, variant: str | None = None
) -> tuple[TrainConfig, int | None]:
    """``model``'s optimisation settings with the global seed, and max_train_frames."""
    try:
        tc = model.train_config(get(p, "seed", int, min=0), variant)
    except ValueError as exc:
        raise ConfigError(f"{PARAMS.name}: risk_model: {exc}") from None
    return tc, model.train.max_train_frames


def check_disparity_scale(p, cfg: Dave2Config) -> None:
    """A network fed SGM disparity needs ``risk_data.sgm.num_disparities <= risk_model.disp_scale``:
    SGM finds disparities up to num_disparities - 1 px and the network sees them divided by
    disp_scale, trained for inputs in [0, 1] (ConfigError naming both settings)."""
    if "disp_sgm" not in cfg.inputs:
        return
    nd = get(p, "risk_data.sgm.num_disparities", int, min=1)
    if nd > cfg.disp_scale:
        raise ConfigError(
            f"{PARAMS.name}: 'risk_data.sgm.num_disparities'={nd} exceeds "
            f"'risk_model.disp_scale'={cfg.disp_scale:g}: SGM disparities up to {nd - 1} px would "
            f"reach {(nd - 1) / cfg.disp_scale:.2f} after normalisation (1.0 at disp_scale px); "
            f"set risk_model.disp_scale >= num_disparities"
        )


def main(argv: list[str] | None = None) -> None:
    # the training imports torch and Lightning: here, not at module level (check_params reads
    # the settings)
    from traffictwin.risk.dave2 import count_parameters
    from traffictwin.risk.source import RiskSource
    from traffictwin.risk.training import RiskVariant, fit_risk

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--variant", required=True)
    args = ap.parse_args(argv)
    log = setup_logging()
    p = params()
    variant = args.variant
    source = PARAMS.name
    model = risk_model(p)
    cfg, label = variant_config(model, variant)
    check_disparity_scale(p, cfg)
    tc, max_train = train_settings(model, p, variant)
    settings = TrainerSettings.from_cfg(p, source=source)
    settings.check_available(source)
    profile = get(p, "profile.name", str)
    stage = f"train_risk@{variant}"
    out_dir = risk_model_dir(variant)

    tracking = TrackingSettings(
        "risk",
        f"risk-{variant}",
        profile=profile,
        stage=stage,
        params=flatten(
            {"risk_model": {k: v for k, v in get(p, "risk_model", dict).items() if k != "variants"}}
        ),
    )
    # under DDP the launcher re-runs this script per rank: only rank zero times the stage
    with stage_timer(stage) if global_rank() == 0 else nullcontext({}) as record:
        res = fit_risk(
            RiskSource(RISK_DATA, DISPARITY, ORB_CSV if model.orb_filter else None),
            RiskVariant(
                variant,
                cfg,
                label,
                tc,
                max_train,
                meta={
                    "domain": training_domain(p, model, label),
                    "objective": cfg.objective,
                    "replicate_of": model.variants[variant].replicate_of,
                },
            ),
            settings,
            out_dir=out_dir,
            curves_out=plot_file(f"risk_training_{variant}"),
            tracking=tracking,
            resume_dir=resume_dir(stage),
        )
        if res is not None:
            record.update(training_record(res, out_dir / "model.ckpt"))
            log.info(
                "%s: best val MSE %.5f (%d params, %.1f s) -> %s",
                stage,
                res.best_val_mse,
                count_parameters(res.net),
                res.seconds,
                out_dir,
            )


if __name__ == "__main__":
    run_stage(main, "train_risk")
