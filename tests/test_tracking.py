"""MLflow tracking: URI resolution, tags, a round trip through a temp SQLite store.

Provenance (git commit, params hash) is computed by the workflow layer (pipelines._provenance)
and reaches the library through the environment.
"""

from __future__ import annotations

from pathlib import Path

import mlflow
import pandas as pd
import pytest

from pipelines import _provenance as prov
from traffictwin.mlops import tracking


def test_default_uri_is_absolute_sqlite_at_repo_root(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    uri = tracking.tracking_uri(tmp_path)
    assert uri == f"sqlite:///{tmp_path.resolve()}/mlflow.db"
    assert Path(uri.removeprefix("sqlite:///")).is_absolute()


def test_env_overrides(monkeypatch) -> None:
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "http://mlflow.example:5000")
    assert tracking.tracking_uri() == "http://mlflow.example:5000"


def test_run_round_trip(mlflow_uri: str, monkeypatch) -> None:
    monkeypatch.delenv("DVC_EXP_BASELINE_REV", raising=False)
    for k, v in prov.provenance_env().items():  # what pipelines._common.run_stage exports
        monkeypatch.setenv(k, v)
    with tracking.start_run(
        "unit", "unit-run", profile="ci", stage="test", params={"a.b": 1}
    ) as run:
        mlflow.log_metric("val/loss", 0.5, step=1)
        rid = run.info.run_id
    got = mlflow.get_run(rid)
    assert got.data.params["a.b"] == "1"
    assert got.data.metrics["val/loss"] == 0.5
    assert got.data.tags["profile"] == "ci" and got.data.tags["dvc_stage"] == "test"
    assert len(got.data.tags["git_commit"]) > 0


def test_repo_root_precedence(tmp_path: Path, monkeypatch) -> None:
    """TRAFFICTWIN_REPO_ROOT > DVC_ROOT (the parent repo even in a queued exp's temp copy) > cwd walk."""
    parent = tmp_path / "repo"
    temp_copy = parent / ".dvc" / "tmp" / "exps" / "tmpabc"
    temp_copy.mkdir(parents=True)
    (parent / "dvc.yaml").write_text("stages: {}\n")
    (temp_copy / "dvc.yaml").write_text("stages: {}\n")
    monkeypatch.chdir(temp_copy)
    monkeypatch.delenv("TRAFFICTWIN_REPO_ROOT", raising=False)
    monkeypatch.delenv("DVC_ROOT", raising=False)
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    assert tracking.repo_root() == temp_copy.resolve()  # no DVC: the checkout we are in
    monkeypatch.setenv("DVC_ROOT", str(parent))
    assert tracking.repo_root() == parent.resolve()
    assert tracking.work_root() == temp_copy.resolve()
    assert tracking.tracking_uri() == f"sqlite:///{parent.resolve()}/mlflow.db"
    other = tmp_path / "elsewhere"
    monkeypatch.setenv("TRAFFICTWIN_REPO_ROOT", str(other))
    assert tracking.repo_root() == other.resolve()
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "http://server:5000")
    assert tracking.tracking_uri() == "http://server:5000"


def test_artifact_location_beside_sqlite(tmp_path: Path) -> None:
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    assert (
        tracking.artifact_location("fusion", uri)
        == (tmp_path.resolve() / "mlartifacts" / "fusion").as_uri()
    )
    assert tracking.artifact_location("fusion", "http://server:5000") is None
    assert tracking.sqlite_path("postgresql://x") is None


def test_git_commit_prefers_dvc_baseline(monkeypatch) -> None:
    monkeypatch.setenv("DVC_EXP_BASELINE_REV", "a" * 40)
    monkeypatch.setenv("TRAFFICTWIN_GIT_COMMIT", "c" * 40)
    assert tracking.git_commit() == "a" * 40
    assert prov.git_commit() == "a" * 40
    monkeypatch.delenv("DVC_EXP_BASELINE_REV")
    assert tracking.git_commit() == "c" * 40  # the workflow layer's commit
    monkeypatch.delenv("TRAFFICTWIN_GIT_COMMIT")
    assert tracking.git_commit() == ""  # no git in the library: empty when not provided


def test_provenance_env_of_a_checkout(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.delenv("DVC_EXP_BASELINE_REV", raising=False)
    (tmp_path / "params.yaml").write_text("seed: 5\n")
    env = prov.provenance_env(tmp_path, tmp_path / "params.yaml")
    assert set(env) == {
        "TRAFFICTWIN_GIT_COMMIT",
        "TRAFFICTWIN_PARAMS_HASH",
        "TRAFFICTWIN_PARAMS_OVERRIDES",
    }
    assert env["TRAFFICTWIN_PARAMS_OVERRIDES"] == "{}"  # nothing committed to differ from
    assert env["TRAFFICTWIN_PARAMS_HASH"] == __import__("hashlib").sha256(b"seed: 5\n").hexdigest()
    assert env["TRAFFICTWIN_GIT_COMMIT"] == "unknown"  # not a git checkout
    head = prov.git_commit(prov.ROOT)
    assert len(head) == 40 or head == "unknown"
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    assert tracking.params_hash() == env["TRAFFICTWIN_PARAMS_HASH"]
    monkeypatch.delenv("TRAFFICTWIN_PARAMS_HASH")
    assert tracking.params_hash() == ""


def test_pipeline_run_id_shared_and_distinct(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.delenv("TRAFFICTWIN_PIPELINE_RUN", raising=False)
    p = tmp_path / "params.yaml"
    p.write_text("seed: 1\n")
    h1 = prov.params_hash(p)
    assert h1 == __import__("hashlib").sha256(b"seed: 1\n").hexdigest()
    a = tracking.pipeline_run_id("0123456789abcdef", h1, "")
    assert a == tracking.pipeline_run_id(
        "0123456789abcdef", h1, ""
    )  # every stage of one run agrees
    assert a.startswith("01234567-") and len(a) == 17
    p.write_text("seed: 2\n")
    assert (
        tracking.pipeline_run_id("0123456789abcdef", prov.params_hash(p), "") != a
    )  # other params
    assert tracking.pipeline_run_id("0123456789abcdef", h1, "exp-1") != a  # other DVC experiment
    assert prov.params_hash(tmp_path / "missing.yaml") == ""
    monkeypatch.setenv("TRAFFICTWIN_PIPELINE_RUN", "nightly-42")
    assert tracking.pipeline_run_id("0123456789abcdef", h1, "") == "nightly-42"


def test_base_tags_from_dvc_env(tmp_path: Path, monkeypatch) -> None:
    (tmp_path / "dvc.yaml").write_text("stages: {}\n")
    (tmp_path / "params.yaml").write_text("seed: 3\n")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("DVC_EXP_NAME", "brisk-lark")
    monkeypatch.setenv("DVC_EXP_BASELINE_REV", "b" * 40)
    monkeypatch.delenv("TRAFFICTWIN_PIPELINE_RUN", raising=False)
    for k, v in prov.provenance_env(tmp_path, tmp_path / "params.yaml").items():
        monkeypatch.setenv(k, v)
    tags = tracking.base_tags("ci", "train_risk", {"data_manifest": "xyz"})
    assert set(tracking.TAG_KEYS) <= set(tags)
    assert tags["dvc_exp_name"] == "brisk-lark" and tags["git_commit"] == "b" * 40
    assert tags["params_hash"] == prov.params_hash(tmp_path / "params.yaml")
    assert tags["pipeline_run"] == tracking.pipeline_run_id(
        "b" * 40, tags["params_hash"], "brisk-lark"
    )
    assert tags["data_manifest"] == "xyz"


def test_experiment_created_with_artifacts_beside_db(tmp_path: Path, monkeypatch) -> None:
    """A run started from a temp copy keeps its artifacts beside the database, not in the copy."""
    db_dir = tmp_path / "repo"
    db_dir.mkdir()
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{db_dir}/mlflow.db")
    work = tmp_path / "temp_copy"
    work.mkdir()
    monkeypatch.chdir(work)
    with tracking.start_run("artexp", "r1", profile="ci", stage="test") as run:
        mlflow.log_text("hello", "note.txt")
        rid = run.info.run_id
    exp = mlflow.get_experiment_by_name("artexp")
    assert exp.artifact_location == (db_dir.resolve() / "mlartifacts" / "artexp").as_uri()
    assert (
        db_dir / "mlartifacts" / "artexp" / rid / "artifacts" / "note.txt"
    ).read_text() == "hello"
    assert not any(work.iterdir())
    with tracking.start_run(
        "artexp", "r2", profile="ci", stage="test"
    ) as run2:  # existing experiment reused
        assert run2.info.experiment_id == exp.experiment_id


def test_dataset_input_carries_the_manifest_hash(mlflow_uri: str, tmp_path: Path) -> None:
    data = tmp_path / "prealigned" / "A"
    data.mkdir(parents=True)
    h = "0123456789abcdef" * 4
    with tracking.start_run("unit", "unit-data", profile="ci", stage="test") as run:
        tracking.log_dataset(data, h)
        rid = run.info.run_id
    got = mlflow.get_run(rid)
    (inp,) = got.inputs.dataset_inputs
    assert inp.dataset.name == "prealigned/A" and inp.dataset.digest == h[:16]
    assert {t.key: t.value for t in inp.tags}[tracking.DATA_TAG] == h
    assert str(data.resolve()) in inp.dataset.source


@pytest.mark.slow
def test_ci_dag_training_runs_carry_data_inputs_curves_and_pyfunc_models(ci_dag: Path) -> None:
    """Every training run of the ci DAG (fusion, registration, risk): the one data tag, a dataset
    input with the same hash, a logged model with a pyfunc flavour; the fusion run its validation
    loss at every epoch of its learning curve (reports/plots)."""
    import yaml

    client = mlflow.MlflowClient(tracking_uri=f"sqlite:///{ci_dag / 'mlflow.db'}")
    seen = set()
    for exp in ("fusion", "risk"):
        e = client.get_experiment_by_name(exp)
        for run in client.search_runs([e.experiment_id]):
            stage = run.data.tags["dvc_stage"]
            if not stage.startswith("train_"):
                continue
            seen.add(stage.split("@")[0])
            h = run.data.tags[tracking.DATA_TAG]
            assert "data_manifest" not in run.data.tags and len(h) == 64
            hashes = [
                {t.key: t.value for t in i.tags}[tracking.DATA_TAG]
                for i in run.inputs.dataset_inputs
            ]
            assert h in hashes, stage
            (out,) = run.outputs.model_outputs
            lm = client.get_logged_model(out.model_id)
            mlmodel = yaml.safe_load(
                Path(
                    mlflow.artifacts.download_artifacts(
                        f"{lm.artifact_location}/MLmodel", tracking_uri=client.tracking_uri
                    )
                ).read_text()
            )
            assert mlmodel["flavors"]["python_function"]["loader_module"] == (
                "traffictwin.mlops.serving"
            )
            if stage == "train_fusion":  # the UI charts the per-epoch metrics: the curves
                curve = pd.read_csv(ci_dag / "reports" / "plots" / "train_fusion_network.csv")
                steps = {m.step for m in client.get_metric_history(run.info.run_id, "val/loss")}
                assert sorted(steps) == list(curve.epoch), stage
    assert {"train_fusion", "train_risk"} <= seen


def test_params_overrides_against_the_committed_file(tmp_path: Path, monkeypatch) -> None:
    """What a DVC experiment's `-S` changed: the params file against the same file at the commit."""
    import subprocess

    monkeypatch.delenv("DVC_EXP_BASELINE_REV", raising=False)
    git = ["git", "-c", "user.email=t@t", "-c", "user.name=t", "-c", "commit.gpgsign=false"]
    subprocess.run(["git", "init", "-q"], cwd=tmp_path, check=True)
    params = tmp_path / "params.yaml"
    params.write_text("seed: 1\nfusion_model:\n  optim: {lr: 0.001, wd: 0.0}\n")
    subprocess.run([*git, "add", "params.yaml"], cwd=tmp_path, check=True)
    subprocess.run([*git, "commit", "-qm", "p"], cwd=tmp_path, check=True)
    assert prov.params_overrides(tmp_path, params) == {}
    params.write_text("seed: 1\nfusion_model:\n  optim: {lr: 0.002, wd: 0.0}\nnew: x\n")
    assert prov.params_overrides(tmp_path, params) == {
        "fusion_model.optim.lr": ["0.001", "0.002"],
        "new": [None, "x"],
    }
    env = prov.provenance_env(tmp_path, params)
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    assert tracking.params_overrides()["fusion_model.optim.lr"] == ["0.001", "0.002"]


def test_another_profile_is_one_override_and_its_composition_is_reused(
    tmp_path: Path, monkeypatch
) -> None:
    """A run on another profile than the committed params.yaml's is one override `profile` plus
    what differs from conf/ composed with that profile; the composition is made once per state of
    conf/ and profile (Hydra takes ~0.5 s a stage), and a change to conf/ makes it again."""
    import subprocess

    import yaml

    from traffictwin.config import compose_config

    monkeypatch.delenv("DVC_EXP_BASELINE_REV", raising=False)
    conf = tmp_path / "conf"
    (conf / "profile").mkdir(parents=True)
    (conf / "config.yaml").write_text("defaults:\n  - _self_\n  - profile: default\n\nseed: 1\n")
    (conf / "profile" / "default.yaml").write_text("name: default\n")
    (conf / "profile" / "ci.yaml").write_text("name: ci\n")
    git = ["git", "-c", "user.email=t@t", "-c", "user.name=t", "-c", "commit.gpgsign=false"]
    subprocess.run(["git", "init", "-q"], cwd=tmp_path, check=True)
    params = tmp_path / "params.yaml"
    params.write_text(yaml.safe_dump(compose_config(conf)))
    subprocess.run([*git, "add", "-A"], cwd=tmp_path, check=True)
    subprocess.run([*git, "commit", "-qm", "p"], cwd=tmp_path, check=True)
    params.write_text(yaml.safe_dump({**compose_config(conf, ["profile=ci"]), "seed": 2}))
    calls = []

    def counted(conf_dir, overrides=()):
        calls.append(list(overrides))
        return compose_config(conf_dir, overrides)

    monkeypatch.setattr("traffictwin.config.compose_config", counted)
    want = {"profile": ["default", "ci"], "seed": ["1", "2"]}
    assert prov.params_overrides(tmp_path, params) == want
    assert prov.params_overrides(tmp_path, params) == want  # the second stage: from the cache
    assert calls == [["profile=ci"]]
    (conf / "profile" / "ci.yaml").write_text("name: ci\nextra: 3\n")  # conf/ changed
    assert prov.params_overrides(tmp_path, params) == {**want, "profile.extra": ["3", None]}
    assert len(calls) == 2 and len(list((tmp_path / prov.COMPOSED).iterdir())) == 2


def test_run_name_and_description_carry_the_experiment_and_its_overrides(
    mlflow_uri: str, monkeypatch
) -> None:
    import json

    monkeypatch.setenv("DVC_EXP_NAME", "lr-low")
    changed = {"fusion_model.optim.lr": ["0.001", "0.002"], "risk_model.train.lr": ["1", "2"]}
    monkeypatch.setenv("TRAFFICTWIN_PARAMS_OVERRIDES", json.dumps(changed))
    params = {"fusion_model.optim.lr": 0.002, "seed": 1}
    with tracking.start_run(
        "fusion", "fusion-network", profile="ci", stage="train_fusion", params=params
    ) as run:
        rid = run.info.run_id
    got = mlflow.get_run(rid)
    # only the override this run's params hold (the risk one belongs to other runs)
    assert got.info.run_name == "fusion-network [lr-low: fusion_model.optim.lr=0.002]"
    note = got.data.tags["mlflow.note.content"]
    assert "`train_fusion`" in note and "`lr-low`" in note and "(was 0.001)" in note
    many = {f"k{i}": ["0", str(i)] for i in range(5)}
    monkeypatch.setenv("TRAFFICTWIN_PARAMS_OVERRIDES", json.dumps(many))
    name, note = tracking.run_label("risk-headline", "train_risk@headline", "ci", {"seed": 1})
    assert name == "risk-headline [lr-low: k0=0, k1=1, k2=2 +2 more]" and "`k4` = 4" in note
    monkeypatch.delenv("DVC_EXP_NAME")
    monkeypatch.delenv("TRAFFICTWIN_PARAMS_OVERRIDES")
    assert tracking.run_label("registration", "s", "ci")[0] == "registration"  # a committed run


def test_the_project_leaves_no_empty_default_experiment(mlflow_uri: str) -> None:
    """MLflow gives every new store an experiment `Default` (id 0); the project marks it deleted
    while it is empty, so the UI opens on the project's experiments."""
    with tracking.start_run("fusion", "r", profile="ci", stage="s"):
        pass
    client = mlflow.MlflowClient(mlflow_uri)
    assert [e.name for e in client.search_experiments()] == ["fusion"]
    assert client.get_experiment("0").lifecycle_stage == "deleted"
    with tracking.start_run("risk", "r", profile="ci", stage="s"):  # a later run: no error
        pass
    assert sorted(e.name for e in client.search_experiments()) == ["fusion", "risk"]
    assert tracking.retire_empty_default("http://server:5000") is False  # a server: left alone


def test_experiments_open_on_the_runs_table(mlflow_uri: str) -> None:
    """The project's experiments say they hold model training (MLflow's experiment-kind tag), so
    the UI opens on the runs table instead of its GenAI overview; an experiment created without
    the tag (an older store) gets it on the next run."""
    client = mlflow.MlflowClient(mlflow_uri)
    old = client.create_experiment("registration")
    with tracking.start_run("fusion", "r", profile="ci", stage="s"):
        pass
    with tracking.start_run("registration", "r", profile="ci", stage="s"):
        pass
    for exp in client.search_experiments():
        assert exp.tags.get("mlflow.experimentKind") == "custom_model_development", exp.name
        assert exp.tags.get("mlflow.note.content"), exp.name
    assert client.get_experiment(old).tags["mlflow.experimentKind"] == "custom_model_development"


def test_another_profile_is_one_override(tmp_path: Path, monkeypatch) -> None:
    """`-S profile=ci -S fusion_model.optim.lr=...` against a committed default: `profile` and
    the learning rate, not the dozens of keys the ci profile sets."""
    import shutil
    import subprocess

    from traffictwin.config import compose_config, dump_params

    monkeypatch.delenv("DVC_EXP_BASELINE_REV", raising=False)
    shutil.copytree(prov.ROOT / "conf", tmp_path / "conf")
    params = tmp_path / "params.yaml"
    dump_params(compose_config(tmp_path / "conf"), params)
    git = ["git", "-c", "user.email=t@t", "-c", "user.name=t", "-c", "commit.gpgsign=false"]
    subprocess.run(["git", "init", "-q"], cwd=tmp_path, check=True)
    subprocess.run([*git, "add", "-A"], cwd=tmp_path, check=True)
    subprocess.run([*git, "commit", "-qm", "p"], cwd=tmp_path, check=True)
    ci = compose_config(tmp_path / "conf", ["profile=ci", "fusion_model.optim.lr=0.002"])
    dump_params(ci, params)
    got = prov.params_overrides(tmp_path, params)
    assert got == {
        "profile": ["default", "ci"],
        "fusion_model.optim.lr": [
            str(compose_config(tmp_path / "conf", ["profile=ci"])["fusion_model"]["optim"]["lr"]),
            "0.002",
        ],
    }
