"""Registry adapter of the promotion gate: tiny torch models in a temp MLflow database.

The pure decision (Gate, decide) is tested without MLflow in test_gate.py.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from _registry_models import load_linear, log_linear

from traffictwin.mlops import registry as reg

NAME = "traffictwin-fusion-T"
W_TRUE = np.array([[2.0, -1.0]], dtype=np.float32)
X = np.random.default_rng(0).normal(size=(64, 2)).astype(np.float32)
Y = X @ W_TRUE.T


def _log_model(weight_error: float) -> str:
    """Log a Linear(2,1) whose weights are off by ``weight_error``; returns the run id."""
    return log_linear(W_TRUE + weight_error)


def _evaluate(uri: str) -> dict[str, float]:
    """Same metric code for both versions: MSE on the fixed test set (X, Y)."""
    model = reg.load_registered(uri, load_linear)
    with torch.no_grad():
        pred = model(torch.from_numpy(X)).numpy()
    return {"test/mse": float(np.mean((pred - Y) ** 2)), "test/n": float(len(X))}


GATE = reg.Gate(metric="test/mse", mode="min", margin=1e-3)


def _promote(cl, run_id: str, log, **kw) -> reg.Decision:
    mv = reg.ensure_version(cl, NAME, run_id)
    d = reg.decide(cl, NAME, mv, _evaluate, GATE, test_fingerprint="fp-1", **kw)
    reg.apply(cl, d, log_path=log)
    return d


# ------------------------------------------------------------------ registry


def test_first_model_becomes_champion(cl, tmp_path):
    log = tmp_path / "promotions.jsonl"
    run_id = _log_model(0.5)
    d = _promote(cl, run_id, log)
    assert d.action == "first" and d.champion_value is None
    assert d.challenger_value == pytest.approx(_evaluate(reg.version_uri(NAME, 1))["test/mse"])
    assert str(reg.get_alias(cl, NAME, "champion").version) == "1"
    assert str(reg.get_alias(cl, NAME, "challenger").version) == "1"
    (rec,) = reg.read_log(log)
    assert rec["action"] == "first" and rec["name"] == NAME and rec["challenger_run_id"] == run_id
    # promoting the same run again registers nothing new and changes nothing
    d2 = _promote(cl, run_id, log)
    assert d2.action == "unchanged" and len(cl.search_model_versions(f"name='{NAME}'")) == 1
    assert len(reg.read_log(log)) == 1


def test_worse_challenger_does_not_move_champion_and_is_logged(cl, tmp_path):
    log = tmp_path / "promotions.jsonl"
    _promote(cl, _log_model(0.1), log)
    d = _promote(cl, _log_model(0.8), log)
    assert d.action == "rejected"
    assert str(reg.get_alias(cl, NAME, "champion").version) == "1"
    assert str(reg.get_alias(cl, NAME, "challenger").version) == "2"
    # both figures, measured by the same evaluate on the same test set
    exp_ch = _evaluate(reg.version_uri(NAME, 2))["test/mse"]
    exp_cp = _evaluate(reg.version_uri(NAME, 1))["test/mse"]
    assert exp_ch > exp_cp
    rec = reg.read_log(log)[-1]
    assert rec["challenger_value"] == pytest.approx(exp_ch) and rec[
        "champion_value"
    ] == pytest.approx(exp_cp)
    assert rec["champion_version"] == "1" and rec["test_fingerprint"] == "fp-1"
    tags = cl.get_model_version(NAME, "2").tags
    assert tags["gate.decision"] == "rejected"
    assert float(tags["gate.challenger_value"]) == pytest.approx(exp_ch)
    assert float(tags["gate.champion_value"]) == pytest.approx(exp_cp)
    # the rejected challenger is not re-evaluated against the same champion
    assert _promote(cl, rec["challenger_run_id"], log).action == "unchanged"
    assert len(reg.read_log(log)) == 2


def test_better_challenger_moves_champion(cl, tmp_path):
    log = tmp_path / "promotions.jsonl"
    _promote(cl, _log_model(0.8), log)
    d = _promote(cl, _log_model(0.05), log)
    assert d.action == "promoted" and d.challenger_value < d.champion_value - GATE.margin
    assert str(reg.get_alias(cl, NAME, "champion").version) == "2"
    assert str(cl.get_model_version(NAME, "1").version) == "1"  # old champion stays registered
    assert reg.champion_history(cl, NAME) == ["1", "2"]
    assert [r["action"] for r in reg.read_log(log)] == ["first", "promoted"]


def test_better_within_margin_is_rejected(cl, tmp_path):
    gate = reg.Gate("test/mse", "min", margin=10.0)
    mv1 = reg.ensure_version(cl, NAME, _log_model(0.8))
    reg.apply(cl, reg.decide(cl, NAME, mv1, _evaluate, gate))
    mv2 = reg.ensure_version(cl, NAME, _log_model(0.0))
    d = reg.decide(cl, NAME, mv2, _evaluate, gate)
    assert d.challenger_value < d.champion_value and d.action == "rejected"


def test_rollback_previous_and_explicit(cl, tmp_path):
    log = tmp_path / "promotions.jsonl"
    _promote(cl, _log_model(0.8), log)
    _promote(cl, _log_model(0.4), log)
    _promote(cl, _log_model(0.1), log)
    assert str(reg.get_alias(cl, NAME, "champion").version) == "3"
    rec = reg.rollback(cl, NAME, log_path=log)
    assert (rec["from_version"], rec["to_version"]) == ("3", "2")
    assert str(reg.get_alias(cl, NAME, "champion").version) == "2"
    reg.rollback(cl, NAME, log_path=log)
    assert str(reg.get_alias(cl, NAME, "champion").version) == "1"
    with pytest.raises(reg.RegistryError, match="no previous champion"):
        reg.rollback(cl, NAME)
    reg.rollback(cl, NAME, version=3, log_path=log)
    assert str(reg.get_alias(cl, NAME, "champion").version) == "3"
    with pytest.raises(reg.RegistryError, match="no version 9"):
        reg.rollback(cl, NAME, version=9)
    assert [r["event"] for r in reg.read_log(log)][-3:] == ["rollback"] * 3


def test_missing_model_alias_and_run_errors(cl):
    with pytest.raises(reg.RegistryError, match="traffictwin-risk.*champion"):
        reg.require_alias(cl, "traffictwin-risk", "champion")
    with pytest.raises(reg.RegistryError, match="no registered model 'nope'"):
        reg.rollback(cl, "nope")
    with pytest.raises(reg.RegistryError, match="run 'deadbeef'"):
        reg.ensure_version(cl, NAME, "deadbeef")


def test_evaluation_without_gate_metric_is_an_error(cl):
    mv = reg.ensure_version(cl, NAME, _log_model(0.1))
    with pytest.raises(reg.RegistryError, match="no metric 'test/mse'"):
        reg.decide(cl, NAME, mv, lambda uri: {"test/other": 1.0}, GATE)
    assert reg.get_alias(cl, NAME, "champion") is None


def test_apply_records_the_log_for_rollback(cl, tmp_path):
    log = tmp_path / "promotions.jsonl"
    assert reg.promotion_log(cl, NAME) is None
    _promote(cl, _log_model(0.5), log)
    assert reg.promotion_log(cl, NAME) == log.resolve()
    assert reg.registered_names(cl, "traffictwin-fusion-") == [NAME]
    assert reg.registered_names(cl, "traffictwin-risk") == []


def test_log_appends_lines(tmp_path):
    p = tmp_path / "log.jsonl"
    reg.append_log(p, {"a": 1})
    reg.append_log(p, {"b": np.float32(2.5), "c": [float("nan"), float("inf")]})
    assert reg.read_log(p) == [
        {"a": 1},
        {"b": 2.5, "c": [None, None]},
    ]  # strict JSON: non-finite -> null
    assert math.isclose(reg.read_log(p)[1]["b"], 2.5)


def test_promotion_writes_the_model_card_as_the_version_description(cl, tmp_path):
    """The applied decision's version gets the card: data hash, metrics with CIs, gate, limits;
    a dry run describes nothing, and re-running an already decided version keeps its card."""
    import json

    from traffictwin.mlops import promotion

    folder = tmp_path / "m"
    folder.mkdir()
    run_id = _log_model(0.0)
    meta = {"data_manifest_hash": "ab" * 32, "profile": "ci"}
    (folder / "model_meta.json").write_text(json.dumps(meta))
    record = tmp_path / "train_m.json"  # the training stage's run record holds the MLflow run id
    record.write_text(json.dumps({"run_id": run_id}))
    card = promotion.ModelCard(
        data="data/prealigned/T: simulated pairs",
        metrics={"test/mse": 0.25, "test/mse_ci": {"lo": 0.125, "hi": 0.5}, "test/n": 64},
        metrics_source="reports/metrics/t.json",
        limits=("Simulated data only.",),
    )
    job = promotion.GateJob(
        NAME, GATE, folder, lambda c: (_evaluate, "fp-1"), record, card=lambda c: card
    )
    promotion.promote([job], promotion.PromotionSettings(dry_run=True), client=cl)
    assert not cl.search_model_versions(f"name='{NAME}'")  # dry run: nothing registered
    (d,) = promotion.promote([job], promotion.PromotionSettings(), client=cl)
    text = cl.get_model_version(NAME, "1").description
    assert text == promotion.model_card(promotion.read_candidate(NAME, folder, record), d, card)
    assert f"# {NAME} v1" in text and run_id in text and "ab" * 32 in text
    assert "data/prealigned/T: simulated pairs" in text
    assert "| test/mse | 0.25 | [0.125, 0.5] |" in text and "| test/n | 64 | — |" in text
    assert "Decision **first** on test/mse (min, margin 0.001)" in text
    assert "Test set fingerprint: `fp-1`" in text and "- Simulated data only." in text
    cl.update_model_version(NAME, "1", description="edited by hand")
    (d2,) = promotion.promote([job], promotion.PromotionSettings(), client=cl)
    assert d2.action == "unchanged"
    assert cl.get_model_version(NAME, "1").description == "edited by hand"


def test_model_card_without_workflow_facts_shows_the_gate_figures():
    from traffictwin.mlops import promotion

    cand = promotion.Candidate("m", "r1", None, Path("x"), {"data_manifest": "h" * 64})
    d = reg.Decision(
        "m",
        "2",
        "r1",
        "1",
        "test/mse",
        "min",
        0.0,
        0.5,
        0.75,
        "promoted",
        "better",
        challenger_metrics={"test/mse": 0.5},
    )
    text = promotion.model_card(cand, d)
    assert "h" * 64 in text  # the risk meta's key is read too
    assert "From the promotion gate's fixed test set" in text and "| test/mse | 0.5 | — |" in text
    assert "champion v1: 0.75" in text and "## Limits" not in text
