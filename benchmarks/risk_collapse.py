"""Does the LR warm-up stop the risk network from collapsing? (issue: a constant-output run)

Trains one risk variant on the default data (``data/risk``, ``data/disparity``, ORB-filtered as in
``train_risk``) with the default training settings, once without and once with the learning-rate
warm-up, for a few seeds, and reports the spread (std) of each run's validation predictions and
whether :func:`traffictwin.risk.training.check_spread` would call it collapsed. Default variant:
the monocular net without speed on the paper's label, the configuration of the run that collapsed
(``rgb``, lr 1e-3, Adam, no warm-up).

``python -m benchmarks.risk_collapse [--variant rgb --speed false --label risk_thw_paper]
[--seeds 0 1] [--warmups 0 100] [--out reports/metrics/risk_collapse.json]``. Needs ``dvc repro
orb_filter`` first. Minutes per run on 2 CPU cores.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import yaml

from traffictwin.config import typed
from traffictwin.io.atomic import write_json_atomic
from traffictwin.risk.dave2 import Dave2Config
from traffictwin.risk.training import (
    MIN_PRED_STD,
    RiskModelConfig,
    RiskSource,
    check_spread,
    fit,
    prepare_split,
)
from traffictwin.trainer import TrainerSettings

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--inputs", nargs="+", default=["rgb"])
    ap.add_argument("--speed", choices=("true", "false"), default="false")
    ap.add_argument("--label", default="risk_thw_paper")
    ap.add_argument("--objective", default="mse")
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1])
    ap.add_argument("--warmups", nargs="+", type=int, default=[0, 100])
    ap.add_argument("--out", default=str(ROOT / "reports" / "metrics" / "risk_collapse.json"))
    a = ap.parse_args(argv)
    params = yaml.safe_load((ROOT / "params.yaml").read_text())
    model = typed(params["risk_model"], RiskModelConfig, key="risk_model")
    base = model.train_config(int(params["seed"]))
    cfg = Dave2Config(
        inputs=tuple(a.inputs),
        height=model.height,
        width=model.width,
        use_speed=a.speed == "true",
        speed_scale=model.speed_scale,
        disp_scale=model.disp_scale,
        objective=a.objective,
    )
    src = RiskSource(
        ROOT / "data" / "risk",
        ROOT / "data" / "disparity",
        ROOT / "data" / "orb" / "orb.csv" if model.orb_filter else None,
    )
    train = prepare_split(src, cfg, "train", a.label)
    val = prepare_split(src, cfg, "val", a.label)
    runs = []
    for warmup in a.warmups:
        for seed in a.seeds:
            tc = replace(base, seed=seed, warmup_steps=warmup, min_pred_std=0.0)
            res = fit(cfg, train, val, tc, TrainerSettings())
            std = check_spread(res.net, val, cfg, min_std=0.0)
            runs.append(
                {
                    "warmup_steps": warmup,
                    "seed": seed,
                    "val_pred_std": std,
                    "collapsed": bool(std < MIN_PRED_STD),
                    "best_val_mse": res.best_val_mse,
                }
            )
            print(json.dumps(runs[-1]))
    out = {
        "variant": {
            "inputs": list(cfg.inputs),
            "speed": cfg.use_speed,
            "label": a.label,
            "objective": a.objective,
        },
        "train": {"epochs": base.epochs, "lr": base.lr, "batch_size": base.batch_size},
        "n_train": len(train),
        "n_val": len(val),
        "label_std_val": float(val.y.std()),
        "min_pred_std": MIN_PRED_STD,
        "runs": runs,
    }
    write_json_atomic(a.out, out)
    return out


if __name__ == "__main__":
    print(json.dumps(main(), indent=2))
