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

from traffictwin.config import ConfigError, flatten, get
from traffictwin.io.atomic import atomic_path
from traffictwin.risk.dave2 import Dave2Config, PackedDave2, count_parameters, normalise, pack_input
from traffictwin.risk.model_io import CKPT, save_risk_model
from traffictwin.risk.training import LABELS, RiskSource, TrainConfig, fit, prepare_split
from traffictwin.trainer import (
    TrainerSettings,
    global_rank,
    log_checkpoint,
    log_torch_model,
    tracked_run,
)

from ._common import ROOT, params, run_stage, setup_logging, stage_timer


def model_config(p, variant: str) -> tuple[Dave2Config, str]:
    """The network config and training label of ``variant`` from params."""
    variants = get(p, "risk_model.variants", dict)
    if variant not in variants:
        raise ConfigError(
            f"params.yaml: 'risk_model.variants' has no variant {variant!r} (has {sorted(variants)})"
        )
    k = f"risk_model.variants.{variant}"
    label = get(p, f"{k}.label", (str, type(None)), default=None) or get(
        p, "risk_model.label", str, choices=LABELS
    )
    if label not in LABELS:
        raise ConfigError(f"params.yaml: '{k}.label' must be one of {list(LABELS)}, got {label!r}")
    try:
        cfg = Dave2Config(
            inputs=tuple(get(p, f"{k}.inputs", list)),
            height=get(p, "risk_model.height", int, min=1),
            width=get(p, "risk_model.width", int, min=1),
            use_speed=get(p, f"{k}.speed", bool),
            speed_scale=get(p, "risk_model.speed_scale", float, min=1e-6),
            disp_scale=get(p, "risk_model.disp_scale", float, min=1e-6),
            dropout=get(p, "risk_model.dropout", float, min=0.0, max=0.99),
        )
    except ValueError as exc:
        if isinstance(exc, ConfigError):
            raise
        raise ConfigError(f"params.yaml: risk_model / variant {variant!r}: {exc}") from None
    return cfg, label


def train_config(p) -> tuple[TrainConfig, int | None]:
    t = "risk_model.train"
    lvb = get(
        p, f"{t}.limit_val_batches"
    )  # int = number of batches, float = fraction (keep the type)
    if (
        isinstance(lvb, bool)
        or not isinstance(lvb, (int, float))
        or lvb <= 0
        or (isinstance(lvb, float) and lvb > 1)
    ):
        raise ConfigError(
            f"params.yaml: '{t}.limit_val_batches' must be a batch count (int >= 1) or a fraction in (0, 1], got {lvb!r}"
        )
    tc = TrainConfig(
        epochs=get(p, f"{t}.epochs", int, min=1),
        batch_size=get(p, f"{t}.batch_size", int, min=1),
        lr=get(p, f"{t}.lr", float, min=1e-12),
        weight_decay=get(p, f"{t}.weight_decay", float, min=0.0),
        val_every_n_steps=get(p, f"{t}.val_every_n_steps", int, min=1),
        limit_val_batches=lvb,
        eval_batch_size=get(p, f"{t}.eval_batch_size", int, min=1),
        seed=get(p, "seed", int, min=0) + get(p, f"{t}.seed_offset", int, min=0),
    )
    return tc, get(p, f"{t}.max_train_frames", (int, type(None)), default=None)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--variant", required=True)
    args = ap.parse_args(argv)
    log = setup_logging()
    p = params()
    variant = args.variant
    cfg, label = model_config(p, variant)
    tc, max_train = train_config(p)
    settings = TrainerSettings.from_cfg(p)
    profile = get(p, "profile.name", str)
    stage = f"train_risk@{variant}"
    out_dir = ROOT / "models" / "risk" / variant
    plot_csv = ROOT / "reports" / "plots" / f"risk_training_{variant}.csv"

    with stage_timer(stage):
        orb = ROOT / "data" / "orb" / "orb.csv" if get(p, "risk_model.orb_filter", bool) else None
        source = RiskSource(ROOT / "data" / "risk", ROOT / "data" / "disparity", orb)
        train = prepare_split(source, cfg, "train", label, max_frames=max_train, seed=tc.seed)
        val = prepare_split(source, cfg, "val", label)
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
        tags = {"variant": variant, "data_manifest": source.risk.manifest_hash(), "label": label}
        with tracked_run(
            "risk", f"risk-{variant}", profile=profile, stage=stage, tags=tags, params=run_params
        ) as run:
            res = fit(cfg, train, val, tc, settings, mlflow_log=run is not None)
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
                "data_manifest": source.risk.manifest_hash(),
                "profile": profile,
                "train": tc.__dict__,
            }
            save_risk_model(res.net, out_dir, meta)
            with atomic_path(out_dir / "history.csv", suffix=".csv") as tmp:
                res.history.to_csv(tmp, index=False, float_format="%.9g", lineterminator="\n")
            plot_csv.parent.mkdir(parents=True, exist_ok=True)
            with atomic_path(plot_csv, suffix=".csv") as tmp:
                res.history.to_csv(tmp, index=False, float_format="%.9g", lineterminator="\n")
            if run is not None:
                import mlflow

                mlflow.log_metrics(
                    {
                        "val/best_mse": res.best_val_mse,
                        "train/seconds": res.seconds,
                        "model/n_parameters": count_parameters(res.net),
                    }
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
