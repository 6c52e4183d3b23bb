"""Stages train_risk@<variant> and evaluate_risk on the ci profile (outputs of the ``ci_dag`` run)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
import yaml
from conftest import run_record

from traffictwin.io.shards import sha256_file

ROOT = Path(__file__).resolve().parents[1]


def _variants(repo: Path) -> list[str]:
    return list(yaml.safe_load((repo / "params.yaml").read_text())["risk_model"]["run_variants"])


def test_dvc_stages_cover_the_configured_variants() -> None:
    """train_risk runs once per run_variant (each defined in variants); evaluate_risk depends on all of them."""
    from conftest import committed

    params = yaml.safe_load(committed("params.yaml"))["risk_model"]
    assert set(params["run_variants"]) <= set(params["variants"])
    # the default profile: the headline with 3 seeds and the paper's net (the objectives: an ablation)
    assert params["run_variants"] == ["headline", "headline_s1", "headline_s2", "paper"]
    dvc = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]
    assert dvc["train_risk"]["foreach"] == "${risk_model.run_variants}"
    assert dvc["train_risk"]["do"]["outs"] == ["models/risk/${item}"]
    # the learning curve is a stage plot: `dvc plots diff` shows it per revision
    (curve,) = dvc["train_risk"]["do"]["plots"]
    props = curve["reports/plots/risk_training_${item}.csv"]
    assert props["cache"] is False and (props["x"], props["y"]) == ("step", "val/loss")
    assert "models/risk" in dvc["evaluate_risk"]["deps"]


@pytest.mark.slow
def test_train_risk_writes_models_and_curves(ci_dag: Path) -> None:
    from traffictwin.risk.model_io import load_risk_model

    for v in _variants(ci_dag):
        d = ci_dag / "models" / "risk" / v
        m = load_risk_model(d)
        assert m.meta["variant"] == v and m.meta["label"].startswith("risk")
        assert m.meta["n_parameters"] > 1_000_000
        assert not {"mlflow_run_id", "mlflow_model_uri", "train_seconds"} & set(m.meta)
        h = pd.read_csv(d / "history.csv")
        assert len(h) >= 1 and {"step", "train/loss", "val/mse", "val/pred_std"} <= set(h.columns)
        assert np.isfinite(h["val/mse"]).all()
        assert m.meta["best_val_mse"] == pytest.approx(h["val/mse"].min())
        plot = pd.read_csv(ci_dag / "reports" / "plots" / f"risk_training_{v}.csv")
        assert plot.equals(h)
        rec = run_record(ci_dag, f"train_risk@{v}")
        assert rec["run_id"] and rec["model_uri"] and rec["train_seconds"] > 0
        assert rec["model_sha256"] == sha256_file(d / "model.ckpt")


@pytest.mark.slow
def test_mlflow_model_reloads_with_identical_outputs(
    ci_dag: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import mlflow

    from traffictwin.io.shards import Dataset
    from traffictwin.mlops.registry import load_registered
    from traffictwin.risk.dave2 import preprocess
    from traffictwin.risk.model_io import load_risk_model

    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{ci_dag / 'mlflow.db'}")
    mlflow.set_tracking_uri(f"sqlite:///{ci_dag / 'mlflow.db'}")
    shard = Dataset(ci_dag / "data" / "risk", kind="risk").load_shard(0)
    sgm = Dataset(ci_dag / "data" / "disparity", kind="disparity").load_shard(0)["disp_sgm"]
    speed = torch.tensor([5.0, 15.0])
    for v in ("paper", "headline"):
        local = load_risk_model(ci_dag / "models" / "risk" / v)
        x = preprocess(local.cfg, shard["left"][:2], sgm[:2], shard["disp_gt"][:2])
        with torch.no_grad():
            ref = local.net(x, speed if local.cfg.use_speed else None)
            uri = run_record(ci_dag, f"train_risk@{v}")["model_uri"]
            remote = load_registered(uri, load_risk_model)
            got = remote.net(x, speed if remote.cfg.use_speed else None)
        assert torch.equal(got, ref), v
    client = mlflow.tracking.MlflowClient()
    exp = client.get_experiment_by_name("risk")
    runs = client.search_runs([exp.experiment_id])
    by_stage = {
        r.data.tags["dvc_stage"]: r for r in sorted(runs, key=lambda r: r.info.start_time)
    }  # newest wins
    for v in _variants(ci_dag):
        r = by_stage[f"train_risk@{v}"]
        assert r.info.run_name.startswith(f"risk-{v}")
        assert r.info.run_id == run_record(ci_dag, f"train_risk@{v}")["run_id"]
        assert r.data.params["risk_model.variant"] == v
        assert (
            "val/mse" in r.data.metrics and "test/mse" in r.data.metrics
        )  # test/* added by evaluate_risk
        assert r.data.tags["profile"] == "ci" and r.data.tags["dvc_stage"] == f"train_risk@{v}"
        hist = client.get_metric_history(r.info.run_id, "val/mse")
        assert len(hist) == len(pd.read_csv(ci_dag / "models" / "risk" / v / "history.csv"))


@pytest.mark.slow
def test_evaluate_risk_outputs(ci_dag: Path) -> None:
    from traffictwin.risk.findings import findings

    metrics = json.loads((ci_dag / "reports" / "metrics" / "risk.json").read_text())
    variants = _variants(ci_dag)
    # the networks, the hybrid's seeds (ci: two) on SGM and on the learned stereo network's
    # disparity, and the shipped predictor (select_risk)
    assert set(metrics["models"]) == {
        *variants,
        "hybrid",
        "hybrid_s1",
        "hybrid_learned",
        "hybrid_learned_s1",
        "shipped",
    }
    assert metrics["groups"]["hybrid"]["n_seeds"] == 2
    assert {"train_mean", "train_median", "speed_only", "geometric_sgm", "geometric_gt"} <= set(
        metrics["baselines"]
    )
    for e in [*metrics["models"].values(), *metrics["baselines"].values()]:
        assert e["test/mse"] >= 0 and e["test/mae"] >= 0 and e["test/thw_mae_s"] >= 0
        for t in ("at_1.5s", "at_1s"):
            c = e[t]["confusion"]
            assert c["tp"] + c["fp"] + c["fn"] + c["tn"] == e["test/n"]
    assert metrics["paper"]["test/mse"] == 0.0147
    main = metrics["main_variant"]
    assert main == "headline" and metrics["primary_label"] == "risk_thw_corridor"
    assert {"risk_thw_paper", "risk_thw_fov"} <= set(metrics["region"]["predictors"][main])
    pred = pd.read_csv(ci_dag / "reports" / "plots" / "risk_predictions.csv")
    assert len(pred) == metrics["models"][main]["test/n"]
    assert {f"pred_{v}" for v in variants} | {
        "pred_speed_only",
        "pred_geometric_sgm",
        "pred_geometric_gt",
        "risk_thw_paper",
        "risk_thw_fov",
    } <= set(pred.columns)
    cm = pd.read_csv(ci_dag / "reports" / "plots" / "risk_confusion.csv")
    assert len(cm) == len(pred) and set(cm["actual"]) <= {"critical", "uncritical"}
    assert int((cm["actual"] == "critical").sum()) == (
        metrics["models"][main]["at_1.5s"]["confusion"]["tp"]
        + metrics["models"][main]["at_1.5s"]["confusion"]["fn"]
    )
    for f in (
        "risk_training_curves",
        "risk_scatter",
        "risk_examples",
        "risk_confusion",
        "risk_roc",
    ):
        png = ci_dag / "reports" / "figures" / f"{f}.png"
        assert png.stat().st_size > 5000 and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (ci_dag / "reports" / "timings" / "evaluate_risk.json").exists()
    text = findings(metrics)
    assert text.startswith("- **Paper comparison") and "camera_fov" in text
    # every metric with its sequence-bootstrap interval; targets and collapse flags
    assert metrics["bootstrap"]["n_boot"] >= 100
    for e in metrics["models"].values():
        assert set(e["test/mse_ci"]) == {"lo", "hi"} and isinstance(e["collapsed"], bool)
    assert {
        "shipped_balanced_accuracy_1.5s",
        "shipped_roc_auc",
        "learned_vs_rule_auc",
        "auc_vs_speed_only",
        "spread",
    } <= set(metrics["targets"])
    assert "test_mse" not in metrics["targets"]  # met by a constant


@pytest.mark.slow
def test_select_risk_chooses_on_validation_and_ships(ci_dag: Path) -> None:
    """select_risk: the rules' corridors, every predictor's decision cuts and the shipped predictor,
    all on the validation split; evaluate_risk applies them to the test split."""
    from traffictwin.risk.model_io import load_risk_model

    sel = json.loads((ci_dag / "reports" / "metrics" / "risk_selection.json").read_text())
    metrics = json.loads((ci_dag / "reports" / "metrics" / "risk.json").read_text())
    assert sel["split"] == "val"
    params = yaml.safe_load((ci_dag / "params.yaml").read_text())
    widths = params["evaluation"]["risk"]["geometric"]["half_widths"]
    for r in ("geometric_sgm", "geometric_gt"):
        rule = sel["rules"][r]
        if rule["note"]:  # too few critical validation frames to choose on: the label's corridor
            assert rule["note"].startswith("not enough validation") and rule["half_width"] == 1.75
        else:
            assert rule["half_width"] in widths
        assert [c["half_width"] for c in rule["candidates"].values()] == widths
        used = metrics["baselines"][r]["params"]["corridor_half_width"]
        assert used == rule["half_width"]
    shipped = sel["shipped"]["predictor"]
    assert shipped in sel["shipped"]["candidates"]
    if sel["shipped"]["note"]:  # the ci profile's 4 validation frames: nothing chosen on them
        assert shipped == "geometric_sgm" and sel["shipped"]["roc_auc"] is None
    else:
        best = max(sel["shipped"]["candidates"], key=lambda n: sel["predictors"][n]["roc_auc"])
        assert sel["predictors"][shipped]["roc_auc"] == sel["predictors"][best]["roc_auc"]
    m = load_risk_model(ci_dag / "models" / "risk_shipped")
    assert m.meta["shipped"]["predictor"] == shipped
    cut = sel["predictors"][shipped]["decision"]["1.5"]["cut"]
    assert metrics["models"]["shipped"]["at_1.5s"]["decision_cut"] == pytest.approx(cut)
    assert metrics["selection"]["shipped_from"] == shipped
    rec = run_record(ci_dag, "select_risk")
    assert rec["run_id"] and rec["model_uri"]
    assert rec["model_sha256"] == sha256_file(ci_dag / "models" / "risk_shipped" / "model.ckpt")


def test_stage_config_is_checked() -> None:
    """train_risk reads the variant, label and training settings with errors that name the key."""
    from omegaconf import OmegaConf

    from pipelines.train_risk import model_config, train_config
    from traffictwin.config import ConfigError

    p = OmegaConf.create(yaml.safe_load((ROOT / "params.yaml").read_text()))
    cfg, label = model_config(p, "fov")
    assert cfg.inputs == ("rgb", "disp_sgm") and label == "risk_thw_fov"
    cfg, label = model_config(p, "headline")
    assert cfg.use_speed and label == p.risk_model.label == "risk_thw_corridor"
    assert cfg.objective == "log_thw" and cfg.thw_cap_s == p.risk_model.objective.thw_cap_s
    cfg, label = model_config(p, "paper")
    assert not cfg.use_speed and label == "risk_thw_paper" and cfg.objective == "mse"
    cfg, _ = model_config(p, "headline_mse")
    assert cfg.objective == "mse" and cfg.use_speed
    with pytest.raises(ConfigError, match="no variant 'nope'"):
        model_config(p, "nope")
    p.risk_model.train.limit_val_batches = 5
    tc, _ = train_config(p)
    assert tc.limit_val_batches == 5 and isinstance(tc.limit_val_batches, int)
    p.risk_model.train.limit_val_batches = 1.5
    with pytest.raises(ConfigError, match="limit_val_batches"):
        train_config(p)
    p.risk_model.variants.rgbd.inputs = ["rgb", "depth"]
    with pytest.raises(ConfigError, match="variant 'rgbd'.*unknown channel group"):
        model_config(p, "rgbd")


def test_training_domain_records_what_inference_must_reproduce() -> None:
    """model_meta.json's ``domain``: camera size, SGM/ORB settings, scales, label and the top
    speed of the training data (the CLI's speed range), all from params.yaml."""
    from omegaconf import OmegaConf

    from pipelines.train_risk import risk_model, training_domain

    p = OmegaConf.create(yaml.safe_load((ROOT / "params.yaml").read_text()))
    d = training_domain(p, risk_model(p), "risk_thw_corridor")
    assert d["max_speed"] == p.risk_data.max_speed and isinstance(d["max_speed"], float)
    assert d["camera"] == {"width": p.risk_data.camera.width, "height": p.risk_data.camera.height}
    assert d["label"] == "risk_thw_corridor" and d["disp_scale"] == p.risk_model.disp_scale
    p.risk_data.max_speed = "fast"
    with pytest.raises(Exception, match="risk_data.max_speed"):
        training_domain(p, risk_model(p), "risk_thw_corridor")
