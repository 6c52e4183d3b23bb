"""pipelines.promote (workflow) and traffictwin.mlops.promotion (library): jobs, selection, errors.

The registry round trip of the gate is in test_registry.py; the pure decision in test_gate.py.
"""

from __future__ import annotations

import hashlib
import json
import re

import pytest
from _registry_models import load_linear, log_linear

from pipelines import promote as pm
from pipelines._paths import PARAMS
from traffictwin.config import ConfigError, load_params
from traffictwin.mlops import promotion
from traffictwin.mlops import registry as reg
from traffictwin.mlops.gate import Decision, Gate


def test_unknown_model_is_an_error_naming_it(capfd):
    """An unknown model is an error naming it and the known ones (before any registry access)."""
    assert pm.main(["--only", "traffictwin-fusion-Q", "--dry-run"]) == 1
    err = capfd.readouterr().err
    assert "unknown model(s) ['traffictwin-fusion-Q']" in err and "traffictwin-risk" in err
    assert "traffictwin-fusion," in err or "traffictwin-fusion'" in err


def test_jobs_follow_the_configurations_and_the_risk_variant():
    cfg = load_params(PARAMS)
    rc = pm.registry_config(cfg)
    jobs = pm.build_jobs(cfg, rc)
    # one registered model per task: no configuration in any name
    names = [rc.fusion.name, rc.registration.name, rc.stereo.name, rc.risk.name]
    assert [j.name for j in jobs] == names
    assert [j.name for j in jobs] == [
        "traffictwin-fusion",
        "traffictwin-registration",
        "traffictwin-stereo",
        "traffictwin-risk",
    ]
    assert pm.model_names(cfg, rc) == [j.name for j in jobs]
    assert jobs[0].model_dir == pm.fusion_model_dir()
    # the MLflow run ids come from the training stages' run records (reports/timings, outside DVC)
    assert jobs[0].record_path == pm.ROOT / "reports" / "timings" / "train_fusion.json"
    assert jobs[1].record_path.name == "train_registration.json"
    # the risk model users get: the predictor select_risk chose on validation
    assert rc.risk.variant == "shipped"
    assert jobs[-1].record_path.name == "select_risk.json"
    assert jobs[0].tags == {"model_dir": "models/fusion/network"}
    reg_job = jobs[1]
    assert reg_job.model_dir == pm.registration_model_dir()
    assert reg_job.tags == {"model_dir": "models/registration/learned"}
    assert reg_job.gate == Gate(
        rc.registration.metric, rc.registration.mode, rc.registration.margin
    )
    # the gates compare on validation data: the test split is read once, by the evaluation
    assert {rc.fusion.split, rc.registration.split, rc.stereo.split, rc.risk.split} == {"val"}
    assert jobs[-1].model_dir == pm.SHIPPED_RISK_MODEL
    assert jobs[-1].tags == {"model_dir": "models/risk_shipped"}
    assert jobs[-1].gate == Gate(rc.risk.metric, rc.risk.mode, rc.risk.margin)
    assert [j.name for j in promotion.select(jobs, {rc.risk.name})] == [rc.risk.name]


def test_registry_group_is_validated_once():
    cfg = load_params(PARAMS)
    bad = cfg.copy()
    bad.registry.risk.variant = "nope"
    with pytest.raises(
        ConfigError, match="'registry.risk.variant' is 'nope'.*'shipped'.*run_variants"
    ):
        pm.registry_config(bad)
    bad = cfg.copy()
    bad.registry.fusion.margin = -1.0
    with pytest.raises(ConfigError, match="'registry.fusion.margin' must be >= 0"):
        pm.registry_config(bad)
    bad = cfg.copy()
    bad.registry.fusion["configs"] = ["A"]  # the configurations are the keys of `configurations`
    with pytest.raises(ConfigError, match="registry.fusion.configs"):
        pm.registry_config(bad)


def test_read_candidate_errors_name_the_file(tmp_path):
    d, rec = tmp_path / "m", tmp_path / "train_m.json"
    d.mkdir()
    with pytest.raises(reg.RegistryError, match="model_meta.json: not found"):
        promotion.read_candidate("m", d, rec)
    (d / "model_meta.json").write_text("{")
    with pytest.raises(reg.RegistryError, match="model_meta.json: not valid JSON"):
        promotion.read_candidate("m", d, rec)
    (d / "model_meta.json").write_text(json.dumps({"label": "x"}))
    with pytest.raises(reg.RegistryError, match="train_m.json: not found .*run record"):
        promotion.read_candidate("m", d, rec)
    rec.write_text("[1]")
    with pytest.raises(reg.RegistryError, match="train_m.json: run record must be a JSON object"):
        promotion.read_candidate("m", d, rec)
    rec.write_text(json.dumps({"stage": "train_m", "seconds": 1.0}))
    with pytest.raises(reg.RegistryError, match="train_m.json: no MLflow run id .*'run_id'"):
        promotion.read_candidate("m", d, rec)
    rec.write_text(json.dumps({"run_id": "r1", "model_uri": "models:/m-1"}))
    c = promotion.read_candidate("m", d, rec)
    assert (c.run_id, c.model_uri, c.meta, c.record_path) == (
        "r1",
        "models:/m-1",
        {"label": "x"},
        rec,
    )
    # the record names the checkpoint it describes: a record of another model is refused
    (d / "model.ckpt").write_bytes(b"weights")
    sha = hashlib.sha256(b"weights").hexdigest()
    rec.write_text(json.dumps({"run_id": "r1", "model_sha256": sha}))
    assert promotion.read_candidate("m", d, rec).run_id == "r1"
    (d / "model.ckpt").write_bytes(b"other weights")
    with pytest.raises(reg.RegistryError, match="run record of another model than .*model.ckpt"):
        promotion.read_candidate("m", d, rec)


def _record(model_dir):
    """The run record of the stage that trained ``model_dir`` (beside it, as reports/timings is)."""
    return model_dir.parent / f"{model_dir.name}.run.json"


def _trained(tmp_path, name: str, weight: float):
    """A model folder and its training run record, which points at a logged MLflow model."""
    run_id = log_linear(weight, in_features=1, experiment="promo")
    d = tmp_path / name
    d.mkdir(exist_ok=True)
    (d / "model_meta.json").write_text(json.dumps({}))
    _record(d).write_text(json.dumps({"run_id": run_id}))
    return d


def _weight(uri: str) -> dict[str, float]:
    return {"test/w": float(reg.load_registered(uri, load_linear).weight.item())}


def test_promote_decides_all_then_applies(tmp_path, mlflow_uri, monkeypatch, capfd):
    monkeypatch.chdir(tmp_path)
    cl = reg.client(mlflow_uri)  # also points the fluent API (model logging) at the temp store
    log = tmp_path / "promotions.jsonl"
    gate = Gate("test/w", "max", 0.1)

    def jobs(**weights):
        return [
            promotion.GateJob(
                name=f"m-{k}",
                gate=gate,
                model_dir=_trained(tmp_path, k, w),
                make_evaluator=lambda cand: (_weight, f"fp:{cand.name}"),
                record_path=_record(tmp_path / k),
                tags={"model_dir": k},
            )
            for k, w in weights.items()
        ]

    settings = promotion.PromotionSettings(log_path=log)
    first = jobs(a=1.0, b=2.0)
    capfd.readouterr()
    ds = promotion.promote(first, promotion.PromotionSettings(dry_run=True))
    assert [d.action for d in ds] == ["first", "first"] and not log.exists()
    assert reg.registered_names(cl) == []  # dry run: nothing registered, no alias moved
    ds = promotion.promote(first, settings)
    # registering a new model says nothing on stderr (mlflow.register_model printed "Registered
    # model 'm-a' already exists" for every version); the versions link back from the logged model
    assert "already exists" not in capfd.readouterr().err
    mv = cl.get_model_version("m-a", "1")
    lm = cl.get_logged_model(mv.source.removeprefix("models:/"))
    assert json.loads(lm.tags["mlflow.modelVersions"]) == [{"name": "m-a", "version": 1}]
    assert mv.run_id == json.loads(_record(tmp_path / "a").read_text())["run_id"]
    assert [d.action for d in ds] == ["first", "first"]
    ds = promotion.promote(first, promotion.PromotionSettings(dry_run=True))  # same runs
    assert [d.challenger_version for d in ds] == ["1", "1"]  # known as their versions
    assert len(cl.search_model_versions("name='m-a'")) == 1
    assert cl.get_model_version("m-a", "1").tags["model_dir"] == "a"
    ds = promotion.promote(jobs(a=1.05, b=3.0), settings)
    assert "already exists" not in capfd.readouterr().err
    assert [d.action for d in ds] == ["rejected", "promoted"]
    header, *rows = promotion.format_table(ds).splitlines()
    assert header.split() == list(promotion.TABLE_COLUMNS)
    assert [re.split(r"\s{2,}", r) for r in rows] == [
        [
            "m-a",
            "v2",
            "rejected",
            "test/w (higher is better)",
            "1.05",
            "1 (v1)",
            "only 0.05 better than champion v1 (margin 0.1)",
        ],
        # promoted: the champion now (the old column said "challenger" here)
        [
            "m-b",
            "v2",
            "champion",
            "test/w (higher is better)",
            "3",
            "2 (v1)",
            "1 better than champion v1 (margin 0.1)",
        ],
    ]
    assert [d.test_fingerprint for d in ds] == ["fp:m-a", "fp:m-b"]
    assert str(reg.get_alias(cl, "m-b", "champion").version) == "2"
    assert [r["action"] for r in reg.read_log(log)] == ["first", "first", "rejected", "promoted"]
    assert "challenger 3" in promotion.format_decision(ds[1])
    assert "champion v1 2" in promotion.format_decision(ds[1])
    # a missing model folder stops the run before anything is registered
    (tmp_path / "c").mkdir()
    missing = promotion.GateJob(
        "m-c", gate, tmp_path / "c", lambda cand: (_weight, ""), _record(tmp_path / "c")
    )
    with pytest.raises(reg.RegistryError, match="model_meta.json: not found"):
        promotion.promote([*jobs(a=5.0), missing], settings)
    assert reg.registered_names(cl, "m-") == ["m-a", "m-b"]
    assert len(cl.search_model_versions("name='m-a'")) == 2


def test_format_decision_without_figures():
    d = Decision("m", "3", "r", "2", "x", "min", 0.0, None, None, "unchanged", "already")
    assert promotion.format_decision(d).split() == ["m", "v", "3", "unchanged"]  # v{version:>3}


def test_before_apply_runs_under_the_lock_and_can_stop_the_apply(tmp_path, mlflow_uri, monkeypatch):
    """The retraining flow's last check: called once every decision is taken, while the registry
    lock is held; an exception there moves no alias."""
    monkeypatch.chdir(tmp_path)
    cl = reg.client(mlflow_uri)
    lock = tmp_path / "gate.lock"
    job = promotion.GateJob(
        "m-a",
        Gate("test/w", "max", 0.0),
        _trained(tmp_path, "a", 1.0),
        lambda c: (_weight, "fp"),
        _record(tmp_path / "a"),
    )
    settings = promotion.PromotionSettings(log_path=tmp_path / "log.jsonl", lock_path=lock)
    seen = []

    def stop(decisions):
        with pytest.raises(reg.LockTimeoutError):  # the gate holds the lock right now
            with reg.gate_lock(lock, timeout_s=0.0):
                pass
        seen.append([d.action for d in decisions])
        raise RuntimeError("injected")

    with pytest.raises(RuntimeError, match="injected"):
        promotion.promote([job], settings, before_apply=stop)
    assert seen == [["first"]] and reg.get_alias(cl, "m-a", "champion") is None
    assert not (tmp_path / "log.jsonl").exists()
    ds = promotion.promote([job], settings, before_apply=seen.append)
    assert [d.action for d in ds] == ["first"] and str(
        reg.get_alias(cl, "m-a", "champion").version
    ) == "1"


def test_jobs_model_cards_read_the_evaluation_metrics_with_intervals():
    """The workflow's card facts: the evaluation stages' numbers (with CIs) for that model."""
    from pipelines._paths import metrics_file

    cfg = load_params(PARAMS)
    rc = pm.registry_config(cfg)
    jobs = pm.build_jobs(cfg, rc)
    cand = promotion.Candidate(jobs[0].name, "r", None, jobs[0].model_dir, {"label": "x"})
    card = jobs[0].card(cand)
    for c in cfg["configurations"]:  # the one network's numbers at every configuration
        fusion = json.loads(metrics_file("fusion").read_text())["test"][c]["dnn"]
        assert card.metrics[f"{c}/kld_fou_mean"] == fusion["kld_fou_mean"]
        assert card.metrics[f"{c}/kld_fou_mean_ci"] == fusion["kld_fou_mean_ci"]
    assert card.metrics_source == "reports/metrics/fusion.json (test split)"
    assert "data/prealigned/mixed" in card.data and card.limits
    risk = jobs[-1].card(cand)
    rm = json.loads(metrics_file("risk").read_text())["models"][rc.risk.variant]
    assert risk.metrics["test/mse_ci"] == rm["test/mse_ci"] and "label x" in risk.data


def _decision(action, version="2", champion="1", ch=0.30, cp=0.31, **kw):
    return Decision("m", version, "r", champion, "val/kld", "min", 0.005, ch, cp, action, "", **kw)


def test_table_says_where_each_version_stands_and_why():
    """The printed table: a header, one row per model; the decision is the version's place after
    the gate (a promoted version is the champion, not a "challenger"), the why a few words."""
    from traffictwin.mlops.gate import outcome, short_reason

    cases = [
        (_decision("first", champion=None, cp=None), "champion", "no champion yet"),
        (_decision("promoted", ch=0.29), "champion", "0.02 better than champion v1 (margin 0.005)"),
        (_decision("rejected", ch=0.308), "rejected", "only 0.002 better than champion v1"),
        (_decision("rejected", ch=0.32), "rejected", "0.01 worse than champion v1"),
        (_decision("rejected", ch=float("nan")), "rejected", "val/kld is not finite"),
        (_decision("unchanged", version="1", ch=None, cp=None), "champion", "already the champion"),
        (
            _decision("unchanged", ch=None, cp=None, earlier="rejected"),
            "rejected",
            "decided before against champion v1 (rejected)",
        ),
        (  # an earlier promotion that a rollback undid: still the challenger
            _decision("unchanged", ch=None, cp=None, earlier="promoted"),
            "challenger",
            "decided before against champion v1 (promoted)",
        ),
        (
            _decision("promoted", cp=None, champion_incompatible="trained on grid 64x48 " * 9),
            "champion",
            "champion v1 skipped, incompatible: trained on grid 64x48 trained",
        ),
    ]
    for d, where, why in cases:
        assert outcome(d) == where, d
        assert short_reason(d).startswith(why), (short_reason(d), why)
        assert len(short_reason(d)) < 100
    text = promotion.format_table([d for d, _, _ in cases], dry_run=True)
    lines = text.splitlines()
    assert lines[0].split() == [
        "model",
        "version",
        "decision",
        "metric",
        "value",
        "champion",
        "why",
    ]
    assert len(lines) == 1 + len(cases) + 1 and lines[-1].startswith("dry run: nothing applied")
    # columns line up: every row's decision starts where the header's does
    col = lines[0].index("decision")
    assert all(ln[col:].split()[0] in ("champion", "challenger", "rejected") for ln in lines[1:-1])
    cells = [re.split(r"\s{2,}", ln) for ln in lines[1:-1]]  # cells are 2+ spaces apart
    assert cells[1][3:6] == ["val/kld (lower is better)", "0.29", "0.31 (v1)"]
    assert cells[0][4:6] == ["0.3", "—"]  # no champion yet
    assert "skipped (v1)" in lines[-2]
    # unchanged decisions are not logged, so the log records keep their keys
    assert "earlier" not in _decision("rejected").to_dict()
    assert _decision("unchanged", earlier="rejected").to_dict()["earlier"] == "rejected"


def test_main_prints_the_table(monkeypatch, capsys):
    ds = [_decision("promoted", ch=0.29), _decision("rejected", ch=0.32)]
    monkeypatch.setattr(pm, "promote", lambda *a, **k: ds)
    assert pm.main([]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].split()[:3] == ["model", "version", "decision"] and len(out) == 3
    assert out[1].split()[2] == "champion" and out[2].split()[2] == "rejected"
    assert pm.main(["--json"]) == 0
    assert [d["action"] for d in json.loads(capsys.readouterr().out)] == ["promoted", "rejected"]


def test_stereo_card_reads_the_flat_intervals_of_stereo_json(tmp_path, monkeypatch):
    """stereo.json stores an interval as ``<key>_lo`` / ``<key>_hi``: the card shows it."""
    (tmp_path / "stereo.json").write_text(
        json.dumps(
            {
                "learned/own/epe": 0.2,
                "learned/own/epe_lo": 0.19,
                "learned/own/epe_hi": 0.21,
                "learned/own/bad1": 0.03,
            }
        )
    )
    monkeypatch.setattr(pm, "metrics_file", lambda name: tmp_path / f"{name}.json")
    metrics, _ = pm._card_metrics("stereo", [], ("learned/own/epe", "learned/own/bad1"))
    assert metrics == {
        "learned/own/epe": 0.2,
        "learned/own/bad1": 0.03,
        "learned/own/epe_ci": {"lo": 0.19, "hi": 0.21},
    }
    text = promotion.model_card(
        promotion.Candidate("traffictwin-stereo", "r", None, tmp_path, {}),
        _decision("promote"),
        promotion.ModelCard(metrics=metrics, metrics_source="stereo.json"),
    )
    assert "| learned/own/epe | 0.2 | [0.19, 0.21] |" in text
    assert "| learned/own/bad1 | 0.03 | — |" in text
