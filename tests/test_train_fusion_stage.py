"""Stages train_fusion (the one network) and train_fusion_variant@registered on the ci profile:
outputs, MLflow run + model round trip, loader checks, DVC no-op."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import mlflow
import numpy as np
import pytest
from conftest import run, run_record, stage_in_process

from traffictwin.fusion.model_io import FusionModelError, load_fusion_model, predict_masses
from traffictwin.io.shards import Dataset
from traffictwin.mlops.registry import load_registered

# model folder -> (training stage, training set: data/<inputs>/<set>)
MODELS = {"network": ("train_fusion", "prealigned/mixed")}  # no fusion_variants by default
pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("single_torch_thread")]


def test_stage_writes_model_meta_metrics_and_curves(ci_dag: Path) -> None:
    for name, (stage, data) in MODELS.items():
        d = ci_dag / "models" / "fusion" / name
        assert (d / "model.ckpt").stat().st_size > 0
        meta = json.loads((d / "model_meta.json").read_text())
        # one model per task: trained on the noise of every configuration (the mixture)
        assert meta["cfg"] == "mixed" and meta["grid"] == {"rows": 128, "cols": 96, "cell": 0.64}
        assert sorted(meta["noise"]["configurations"]) == ["A", "B", "C", "D"]
        assert meta["noise"]["kind"] == "mixture"
        assert meta["architecture"]["backbone"]["base_width"] == 8 and meta["param_count"] > 0
        kind = "prealigned"
        data_hash = Dataset(ci_dag / "data" / data, kind=kind).manifest_hash()
        assert meta["data_manifest_hash"] == data_hash
        assert not {"mlflow_run_id", "mlflow_model_uri", "data_root"} & set(meta)
        metrics = json.loads(
            (ci_dag / "reports" / "metrics" / f"train_fusion_{name}.json").read_text()
        )
        for k in (
            "train/loss",
            "val/loss",
            "val/kld",
            "val/kld_full",
            "val/dice_occ",
            "val/dice_free",
            "val/kld_naive",
        ):
            assert np.isfinite(metrics[k]), k
        # the run says whether early stopping ended it (the ci profile's 2 epochs do not)
        assert metrics["max_epochs"] == 2 and metrics["stopped_early"] is False
        with open(ci_dag / "reports" / "plots" / f"train_fusion_{name}.csv") as fh:
            rows = list(csv.DictReader(fh))
        assert len(rows) == metrics["epochs"] and [int(r["epoch"]) for r in rows] == list(
            range(len(rows))
        )
        assert {"train/loss", "val/loss", "lr"} <= set(rows[0])
        assert not {"train_seconds", "train_samples_per_s"} & set(metrics)
        rec = run_record(ci_dag, stage)
        assert rec["run_id"] and rec["model_uri"] and rec["train_seconds"] > 0
        # the run record says how it trained and on what, so its wall time can be judged
        assert rec["precision"] in ("bf16-mixed", "32-true")
        assert rec["machine"]["cpu_count"] >= 1 and len(rec["machine"]["load_start"]) == 3


def test_no_fusion_variant_is_trained_by_default(ci_dag: Path) -> None:
    assert sorted(p.name for p in (ci_dag / "models" / "fusion").iterdir()) == ["network"]


def test_mlflow_run_and_logged_model_reload_identically(ci_dag: Path) -> None:
    mlflow.set_tracking_uri(f"sqlite:///{ci_dag / 'mlflow.db'}")
    try:
        client = mlflow.tracking.MlflowClient()
        exp = client.get_experiment_by_name("fusion")
        assert exp is not None
        meta = json.loads((ci_dag / "models/fusion/network/model_meta.json").read_text())
        rec = run_record(ci_dag, "train_fusion")
        runs = client.search_runs([exp.experiment_id], "tags.dvc_stage = 'train_fusion'")
        assert rec["run_id"] in {r.info.run_id for r in runs}
        r = client.get_run(rec["run_id"])
        # the ci DAG runs params.yaml composed with profile=ci against the committed default
        assert r.info.run_name == "fusion-network [profile=ci]"
        assert r.data.tags["profile"] == "ci" and r.data.tags["dvc_stage"] == "train_fusion"
        assert r.data.params["data.manifest_hash"] == meta["data_manifest_hash"]
        assert (
            r.data.params["configuration.name"] == "mixed"
            and r.data.params["configuration.configurations.D.r"] == "5.0"
            and r.data.params["fusion_model.train.max_epochs"] == "2"
        )
        # per epoch, then the best epoch's value again at the last step (the run's value)
        hist = client.get_metric_history(r.info.run_id, "val/kld")
        steps = [m.step for m in hist]
        assert steps == [*range(len(hist) - 1), len(hist) - 2] and len(hist) >= 2
        dvc = json.loads((ci_dag / "reports/metrics/train_fusion_network.json").read_text())
        assert r.data.metrics["val/kld"] == dvc["val/kld"]
        assert [a.path for a in client.list_artifacts(r.info.run_id, "checkpoints")] == [
            "checkpoints/model.ckpt"
        ]
        # the learned registration runs in its own experiment
        assert client.get_experiment_by_name("registration") is not None

        val = Dataset(ci_dag / "data/prealigned/B", kind="prealigned").load_all(
            "val", keys=["inputs"]
        )["inputs"][:3]
        net = load_fusion_model(ci_dag / "models/fusion/network/model.ckpt", expected_cfg="mixed")
        logged = load_registered(rec["model_uri"], load_fusion_model)
        m_a, u_a = predict_masses(net, val)
        m_b, u_b = predict_masses(logged, val)
        np.testing.assert_array_equal(m_a, m_b)
        np.testing.assert_array_equal(u_a, u_b)
        assert m_a.shape == (len(val), 2, 128, 96)
    finally:
        mlflow.set_tracking_uri(None)


def test_checkpoint_of_another_training_noise_is_refused(ci_dag: Path) -> None:
    with pytest.raises(
        FusionModelError, match="trained on the pose noise of 'mixed' .* expected 'A'"
    ):
        load_fusion_model(ci_dag / "models/fusion/network/model.ckpt", expected_cfg="A")


@pytest.mark.xdist_group("ci_dag_dvc")  # DVC commands in the shared ci DAG: one at a time
def test_rerun_is_a_dvc_noop(ci_dag: Path) -> None:
    out = run(["dvc", "status", "train_fusion", "train_fusion_variant"], ci_dag).stdout
    assert "up to date" in out.lower(), out


def test_stage_without_data_fails_clearly_and_writes_nothing(repo_copy: Path) -> None:
    """In this process (the stage's main under run_stage: the checks end before any work)."""
    code, err = stage_in_process(repo_copy, "train_fusion")
    assert code != 0
    assert "data/prealigned/mixed: dataset folder not found" in err
    assert not (repo_copy / "models" / "fusion" / "network").exists()
    code, err = stage_in_process(repo_copy, "train_fusion", ["--variant", "Z"])
    assert code != 0 and "'Z' is not a key of 'fusion_variants'" in err
