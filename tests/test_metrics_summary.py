"""The DVC metrics files: one small summary per problem (reports/metrics/summary_fusion.json by
evaluate_fusion, summary_risk.json by evaluate_risk), flat ``split/name`` keys, the only
``metrics:`` of dvc.yaml, so `dvc exp show` lists a handful of columns."""

from __future__ import annotations

import json
import math
from pathlib import Path

import yaml

from pipelines import evaluate_fusion, evaluate_risk

ROOT = Path(__file__).resolve().parents[1]


def _declared(kind: str) -> list[str]:
    dvc = yaml.safe_load((ROOT / "dvc.yaml").read_text())
    out = []
    for stage in dvc["stages"].values():
        body = stage.get("do", stage)
        for entry in body.get(kind) or []:
            out.extend(entry if isinstance(entry, dict) else [entry])
    return out


def test_the_two_summaries_are_the_only_dvc_metrics() -> None:
    assert sorted(_declared("metrics")) == [
        "reports/metrics/summary_fusion.json",
        "reports/metrics/summary_risk.json",
    ]
    outs = _declared("outs")
    # the detailed and per-epoch files stay outputs (`dvc metrics show <path>` reads them)
    for path in (
        "reports/metrics/train_fusion_network.json",
        "reports/metrics/train_registration.json",
        "reports/metrics/fusion.json",
        "reports/metrics/risk.json",
        "reports/summary.json",
    ):
        assert path in outs, path


def test_fusion_summary_is_best_epoch_validation_and_the_noisiest_test() -> None:
    meta = {"best_val_loss": 0.9, "best_val_kld_full": 0.8, "best_val_dice_occ": 0.7}
    metrics = {
        "test": {
            "A": {"dnn": {"kld_fou_mean": 0.1, "dice_occ": 0.99}},
            "D": {"dnn": {"kld_fou_mean": 0.4, "dice_occ": float("nan"), "n": 5}},
        }
    }
    got = evaluate_fusion.summary(metrics, meta, ["A", "D"])
    assert got == {
        "val/kld_full": 0.8,
        "val/dice_occ": 0.7,
        "test/D/kld_fou_mean": 0.4,  # the name the evaluation logs to the network's MLflow run
    }  # a NaN is left out, never written
    assert json.loads(json.dumps(got)) == got and all("/" in k for k in got)


def test_risk_summary_is_the_shipped_predictors_validation_and_test() -> None:
    selection = {
        "shipped": {"roc_auc": 0.95, "decision": {"1.5": {"balanced_accuracy": 0.9, "cut": 0.03}}}
    }
    metrics = {
        "models": {
            evaluate_risk.SHIPPED: {
                "at_1.5s": {"roc_auc": math.nan, "balanced_accuracy": 0.8, "accuracy": 0.85}
            }
        }
    }
    assert evaluate_risk.summary(metrics, selection, 1.5) == {
        "val/roc_auc": 0.95,
        "val/balanced_accuracy": 0.9,
        "test/balanced_accuracy": 0.8,
        "test/accuracy": 0.85,
    }
    assert evaluate_risk.summary({}, {}, 1.5) == {}
