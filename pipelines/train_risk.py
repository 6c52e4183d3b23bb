"""Stage `train_risk@<variant>`: train one DAVE-2-like risk network (Feth et al. sec. 3.5).

Usage: ``python -m pipelines.train_risk --variant rgbd``. Reads ``risk_model.*``, ``trainer.*``,
``seed``, ``profile.name``; data ``data/risk``, ``data/disparity``, ``data/orb/orb.csv``.
Writes ``models/risk/<variant>/`` (``model.ckpt``, ``model_meta.json``, ``history.csv``) and
``reports/plots/risk_training_<variant>.csv`` (train/val error per validation, for ``dvc plots``).
MLflow: experiment ``risk``, run ``risk-<variant>`` with the params once, the error curves, the
best checkpoint and an MLflow model (single-tensor input, :class:`~traffictwin.risk.dave2.PackedDave2`).
"""

from __future__ import annotations

import argparse
import shutil

import torch

from traffictwin.config import ConfigError, flatten, get, typed
from traffictwin.io.atomic import atomic_path
from traffictwin.risk.dave2 import PackedDave2, count_parameters, normalise, pack_input
from traffictwin.risk.model_io import CKPT, save_risk_model
from traffictwin.risk.training import RiskModelConfig, RiskSource, fit, prepare_split
from traffictwin.trainer import (
    TrainerSettings,
    global_rank,
    log_checkpoint,
    log_final_metrics,
    log_torch_model,
    mlflow_logger,
    tracked_run,
)

from ._common import params, run_stage, setup_logging, stage_timer
from ._paths import DISPARITY, ORB_CSV, PARAMS, RISK_DATA, plot_file, risk_model_dir


def training_domain(p, model: RiskModelConfig, label: str) -> dict:
    """What a user of the model must reproduce at inference: camera size, SGM / ORB settings, scales, label."""
    return {
        "camera": {
            "width": get(p, "risk_data.camera.width", int),
            "height": get(p, "risk_data.camera.height", int),
        },
        "sgm": get(p, "risk_data.sgm", dict),
        "orb": get(p, "risk_data.orb", dict),
        "disp_scale": model.disp_scale,
        "speed_scale": model.speed_scale,
        "label": label,
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--variant", required=True)
    args = ap.parse_args(argv)
    log = setup_logging()
    p = params()
    variant = args.variant
    source = PARAMS.name
    model = typed(p["risk_model"], RiskModelConfig, key="risk_model", source=source)
    if variant not in model.variants:
        raise ConfigError(
            f"{source}: 'risk_model.variants' has no variant {variant!r} (has {sorted(model.variants)})"
        )
    try:
        cfg, label = model.variant(variant)
    except ValueError as exc:
        raise ConfigError(f"{source}: risk_model / variant {variant!r}: {exc}") from None
    tc = model.train_config(get(p, "seed", int, min=0))
    max_train = model.train.max_train_frames
    settings = TrainerSettings.from_cfg(p, source=source)
    profile = get(p, "profile.name", str)
    stage = f"train_risk@{variant}"
    out_dir = risk_model_dir(variant)
    plot_csv = plot_file(f"risk_training_{variant}")

    with stage_timer(stage):
        orb = ORB_CSV if model.orb_filter else None
        data = RiskSource(RISK_DATA, DISPARITY, orb)
        train = prepare_split(data, cfg, "train", label, max_frames=max_train, seed=tc.seed)
        val = prepare_split(data, cfg, "val", label)
        log.info(
            "%s: %d train / %d val frames (ORB-passed), label %s",
            stage,
            len(train),
            len(val),
            label,
        )
        run_params = {
            **flatten(
                {
                    "risk_model": {
                        k: v for k, v in get(p, "risk_model", dict).items() if k != "variants"
                    }
                }
            ),
            "risk_model.variant": variant,
            "risk_model.inputs": ",".join(cfg.inputs),
            "risk_model.use_speed": cfg.use_speed,
            "risk_model.effective_label": label,
            **flatten({"trainer": settings.as_dict()}),
            "seed": tc.seed,
            "data.n_train": len(train),
            "data.n_val": len(val),
        }
        tags = {"variant": variant, "data_manifest": data.risk.manifest_hash(), "label": label}
        with tracked_run(
            "risk", f"risk-{variant}", profile=profile, stage=stage, tags=tags, params=run_params
        ) as run:
            logger = mlflow_logger(run)
            res = fit(cfg, train, val, tc, settings, logger=logger)
            if global_rank() != 0:  # DDP: the other ranks trained along; rank zero writes
                return
            if out_dir.exists():
                shutil.rmtree(out_dir)
            meta = {
                "variant": variant,
                "label": label,
                "best_val_mse": res.best_val_mse,
                "best_step": res.best_step,
                "steps": res.steps,
                "train_seconds": round(res.seconds, 2),
                "n_train": res.n_train,
                "n_val": res.n_val,
                "data_manifest": data.risk.manifest_hash(),
                "profile": profile,
                "train": tc.__dict__,
                "domain": training_domain(p, model, label),
            }
            save_risk_model(res.net, out_dir, meta)
            with atomic_path(out_dir / "history.csv", suffix=".csv") as tmp:
                res.history.to_csv(tmp, index=False, float_format="%.9g", lineterminator="\n")
            plot_csv.parent.mkdir(parents=True, exist_ok=True)
            with atomic_path(plot_csv, suffix=".csv") as tmp:
                res.history.to_csv(tmp, index=False, float_format="%.9g", lineterminator="\n")
            if run is not None:
                log_final_metrics(
                    logger,
                    {
                        "val/best_mse": res.best_val_mse,
                        "train/seconds": res.seconds,
                        "model/n_parameters": count_parameters(res.net),
                    },
                )
                log_checkpoint(out_dir / CKPT)
                n_ex = min(2, len(val))
                x = normalise(
                    cfg,
                    torch.from_numpy(val.rgb[:n_ex]) if "rgb" in cfg.inputs else None,
                    torch.from_numpy(val.disp[:n_ex]) if val.disp.shape[1] else None,
                )
                example = pack_input(cfg, x, torch.from_numpy(val.speed[:n_ex])).numpy()
                uri = log_torch_model(
                    PackedDave2(res.net), example, metadata={"variant": variant, "label": label}
                )
                meta.update(mlflow_run_id=run.info.run_id, mlflow_model_uri=uri)
                save_risk_model(res.net, out_dir, meta)
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
