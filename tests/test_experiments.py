"""DVC experiments and MLflow: a queued `dvc exp run --queue -S ...` experiment on the ci profile
(run by `--run-all` in a temp copy under .dvc/tmp/exps) appears in `dvc exp show` / `dvc exp diff`
and as an MLflow run in the repository's own database, with its artifacts beside it.

Cheap on purpose: it starts from the finished ci DAG (`ci_dag`, copied so the shared fixture stays
untouched) and re-runs a single training stage. Workspace experiments are checked by
tests/test_readme.py, in the clone where it has just run the docs' two experiments as the docs
write them (:func:`check_documented_experiments`): each experiment runs once per test session.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest
from conftest import copy_dag, run, stage_env

from traffictwin.mlops.runs import compare_runs, format_runs

STAGE = "train_risk@headline"
PARAM = "risk_model.train.lr"


def clone_dag(src: Path, dest: Path, *, mlflow: bool = False) -> Path:
    """Copy a repo with its DVC cache, data and models; commit everything git tracks; its MLflow
    store only with ``mlflow`` (the runs a user has after the Quick start)."""
    copy_dag(src, dest, mlflow=mlflow)
    # no run cache: a stage restored from it would not train, hence log no MLflow run
    shutil.rmtree(dest / ".dvc" / "cache" / "runs", ignore_errors=True)
    git = ["git", "-c", "user.email=t@t", "-c", "user.name=t", "-c", "commit.gpgsign=false"]
    subprocess.run([*git, "add", "-A"], cwd=dest, check=True)
    subprocess.run(
        [*git, "commit", "-q", "--allow-empty", "-m", "ci DAG done"], cwd=dest, check=True
    )
    return dest


def user_env(repo: Path) -> dict[str, str]:
    """A user's shell: no MLFLOW_TRACKING_URI / TRAFFICTWIN_REPO_ROOT, so the default store must be found."""
    env = stage_env(repo)
    for var in (
        "MLFLOW_TRACKING_URI",
        "TRAFFICTWIN_REPO_ROOT",
        "TRAFFICTWIN_PIPELINE_RUN",
        "DVC_ROOT",
        "DVC_EXP_NAME",
    ):
        env.pop(var, None)
    return env


def _exps(show: list[dict]) -> dict[str, dict]:
    out = {}
    for base in show:
        for exp in base.get("experiments") or []:
            for rev in exp["revs"]:
                out[rev["name"]] = rev
    return out


@pytest.mark.slow
def test_a_queued_experiment_reaches_dvc_and_mlflow(ci_dag: Path, tmp_path: Path) -> None:
    repo = clone_dag(ci_dag, tmp_path / "exp_repo")
    env = user_env(repo)
    head = run(["git", "rev-parse", "HEAD"], repo, env=env).stdout.strip()

    run(
        [
            "dvc",
            "exp",
            "run",
            "--queue",
            "-n",
            "exp-q",
            "-S",
            "profile=ci",
            "-S",
            f"{PARAM}=0.003",
            STAGE,
        ],
        repo,
        env=env,
    )
    run(["dvc", "exp", "run", "--run-all"], repo, env=env)

    # --- DVC: the experiment, with its parameter
    exps = _exps(json.loads(run(["dvc", "exp", "show", "--json"], repo, env=env).stdout))
    assert "exp-q" in exps, sorted(exps)
    params = exps["exp-q"]["data"]["params"]["params.yaml"]["data"]
    assert params["risk_model"]["train"]["lr"] == 0.003 and params["profile"]["name"] == "ci"
    diff = json.loads(run(["dvc", "exp", "diff", "HEAD", "exp-q", "--json"], repo, env=env).stdout)
    assert diff["params"]["params.yaml"][PARAM]["new"] == 0.003, diff["params"]

    # --- MLflow: the run in the repository's own database (it ran under .dvc/tmp/exps)
    db = repo / "mlflow.db"
    assert db.exists()
    assert not list((repo / ".dvc").rglob("mlflow.db"))
    df = compare_runs(
        "risk",
        uri=f"sqlite:///{db}",
        filter_string=f"tags.dvc_stage = '{STAGE}'",
        params=[PARAM],  # one run: no parameter differs, so name the one to show
    )
    exp_rows = df[df["dvc_exp_name"] == "exp-q"].set_index("dvc_exp_name")
    assert list(exp_rows.index) == ["exp-q"], df[["run_name", "dvc_exp_name"]]
    row = exp_rows.loc["exp-q"]
    assert row[f"param:{PARAM}"] == "0.003"
    assert row["git_commit"] == head[:8]  # the baseline commit, not the temp copy's
    assert row["pipeline_run"].startswith(head[:8]) and row["profile"] == "ci"
    q_run = row["run_id"]

    # artifacts (checkpoint) beside the database, not in the deleted temp copy
    from mlflow.tracking import MlflowClient

    client = MlflowClient(f"sqlite:///{db}")
    art = client.get_run(q_run).info.artifact_uri
    assert art.startswith((repo / "mlartifacts").resolve().as_uri()), art
    files = [p for p in (repo / "mlartifacts").rglob("*") if q_run in str(p) and p.is_file()]
    assert files, "queued experiment's artifacts missing"

    # the CLI-facing formatter shows both experiments
    assert "exp-q" in format_runs(df)


def check_documented_experiments(repo: Path, env: dict[str, str]) -> None:
    """After the docs' two experiments ran in ``repo`` (the fusion network's learning rate on the
    ci profile, up to evaluate_fusion, as docs/experiments.md runs them; tests/test_readme.py runs
    that page's block in a clone of the ci DAG and then calls this): `dvc exp show --only-changed`
    (as the docs run it) fits in 120 columns and shows the changed parameter and the summary
    metrics it moved; `dvc exp diff` compares only the summary; `dvc plots diff` draws two
    learning curves named by the experiments; MLflow's run is named after the experiment and its
    override, holds the same numbers as DVC's summary and records the baseline commit, the profile
    and a pipeline run of its own."""
    # the docs page's table (and its printed example) holds its own two experiments: an earlier
    # one (the README's Quick start, named at random by DVC) is removed first
    names = _exps(json.loads(run(["dvc", "exp", "show", "--json"], repo, env=env).stdout))
    others = sorted(set(names) - {"lr-low", "lr-high"})
    if others:
        run(["dvc", "exp", "remove", *others], repo, env=env)
    summary = "reports/metrics/summary_fusion.json"
    diff = json.loads(
        run(["dvc", "exp", "diff", "lr-low", "lr-high", "--json"], repo, env=env).stdout
    )
    assert set(diff["metrics"]) == {summary}, sorted(diff["metrics"])
    changed = diff["metrics"][summary]
    assert "val/kld_full" in changed and changed["val/kld_full"]["diff"] != 0, changed
    # the docs' table: without the Created, params.yaml (check_params' file dependency) and
    # reports/ file-dependency columns (evaluate_fusion's training record)
    cmd = ["dvc", "exp", "show", "--only-changed", "--drop", "Created|^params.yaml$|^reports/"]
    table = run(cmd, repo, env=env).stdout
    width = max(len(line) for line in table.splitlines())
    assert width <= 120, table
    assert "fusion_model.optim.lr" in table and "val/kld_full" in table, table
    assert "lr-low" in table and "lr-high" in table and "0.002" in table, table
    shown = _exps(json.loads(run(["dvc", "exp", "show", "--json"], repo, env=env).stdout))
    vals = {n: shown[n]["data"]["metrics"][summary]["data"] for n in ("lr-low", "lr-high")}
    assert vals["lr-low"]["val/kld_full"] != vals["lr-high"]["val/kld_full"]

    # MLflow: the same numbers under the same names, in a run named by the experiment
    df = compare_runs(
        "fusion",
        uri=f"sqlite:///{repo / 'mlflow.db'}",
        filter_string="tags.dvc_stage = 'train_fusion'",
    )
    row = df[df["dvc_exp_name"] == "lr-low"].iloc[0]
    assert row["run_name"] == "fusion-network [lr-low: fusion_model.optim.lr=0.002]"
    for key in ("val/kld_full", "val/dice_occ", "test/D/kld_fou_mean", "test/D/dice_occ"):
        assert row[key] == vals["lr-low"][key], key
    # workspace experiments: each its own pipeline run, of the baseline commit, on the ci profile
    head = run(["git", "rev-parse", "HEAD"], repo, env=env).stdout.strip()
    ws = df[df["dvc_exp_name"].isin(["lr-low", "lr-high"])].set_index("dvc_exp_name")
    assert sorted(ws.index) == ["lr-high", "lr-low"], df[["run_name", "dvc_exp_name"]]
    assert (ws["git_commit"] == head[:8]).all() and (ws["profile"] == "ci").all(), ws
    assert ws["pipeline_run"].str.startswith(head[:8]).all()
    assert ws.loc["lr-low", "pipeline_run"] != ws.loc["lr-high", "pipeline_run"]

    curves = "reports/plots/train_fusion_network.csv"
    plots = json.loads(
        run(
            ["dvc", "plots", "diff", "lr-low", "lr-high", "--json", "--targets", curves],
            repo,
            env=env,
        ).stdout
    )
    (entry,) = plots["data"][curves]
    assert entry["revisions"] == ["lr-low", "lr-high"]  # the revisions name the curves
    rows = entry["content"]["data"]["values"]
    by_rev = {
        rev: [float(r["val/loss"]) for r in rows if r["rev"] == rev] for rev in entry["revisions"]
    }
    assert by_rev["lr-low"] and by_rev["lr-low"] != by_rev["lr-high"]
