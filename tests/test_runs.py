"""`traffictwin runs compare`: the MLflow comparison table (temp SQLite store)."""

from __future__ import annotations

import math

import mlflow
import pytest

from traffictwin.mlops import runs, tracking


def _log(name: str, params: dict, metrics: dict, **tags) -> str:
    with tracking.start_run(
        "cmp", name, profile="ci", stage="train_fusion@A", tags=tags, params=params
    ) as run:
        for k, v in metrics.items():
            mlflow.log_metric(k, v, step=0)
        return run.info.run_id


def test_compare_runs_table(mlflow_uri: str, monkeypatch) -> None:
    monkeypatch.setenv("TRAFFICTWIN_PIPELINE_RUN", "p1")
    monkeypatch.setenv("DVC_EXP_NAME", "exp-one")
    a = _log(
        "fusion-A", {"loss.occupied_weight": 1, "epochs": 2}, {"val/loss": 0.5, "test/kld": 0.1}
    )
    monkeypatch.setenv("DVC_EXP_NAME", "exp-two")
    b = _log("fusion-A", {"loss.occupied_weight": 3, "epochs": 2}, {"val/loss": 0.4})
    # a metric logged twice: the table shows the last value
    with mlflow.start_run(run_id=b):
        mlflow.log_metric("val/loss", 0.3, step=1)

    df = runs.compare_runs("cmp", uri=mlflow_uri)
    assert list(df["run_id"]) == [b, a]  # newest first
    assert list(df["dvc_exp_name"]) == ["exp-two", "exp-one"]
    assert set(df["pipeline_run"]) == {"p1"}
    # only the parameter that differs is shown
    assert "param:loss.occupied_weight" in df and "param:epochs" not in df
    assert list(df["param:loss.occupied_weight"]) == ["3", "1"]
    assert df.loc[df.run_id == b, "val/loss"].item() == 0.3
    assert math.isnan(df.loc[df.run_id == b, "test/kld"].item())
    assert df.loc[df.run_id == a, "test/kld"].item() == 0.1

    sub = runs.compare_runs("cmp", metrics=["test/kld"], uri=mlflow_uri, params=["epochs"])
    assert [c for c in sub.columns if "/" in c] == ["test/kld"] and "param:epochs" in sub

    text = runs.format_runs(df)
    lines = text.splitlines()
    assert len(lines) == 3 and "val/loss" in lines[0] and "param:loss.occupied_weight" in lines[0]
    assert a[:8] in text and b[:8] in text and "0.3" in lines[1] and "-" in lines[1]
    assert a not in text and a in runs.format_runs(df, wide=True)  # full ids only when wide


def test_format_runs_cuts_long_text(mlflow_uri: str) -> None:
    _log("r1", {"data.manifest_hash": "a" * 64}, {"val/loss": 1.0})
    _log("r2", {"data.manifest_hash": "b" * 64}, {"val/loss": 2.0})
    df = runs.compare_runs("cmp", uri=mlflow_uri)
    assert "b" * 12 + "…" in runs.format_runs(df) and "b" * 13 not in runs.format_runs(df)
    assert "b" * 64 in runs.format_runs(df, wide=True)
    # a run's name is never cut: it names the experiment and its overrides
    name = "fusion-network [lr-low: fusion_model.optim.lr=0.002]"
    _log(name, {"data.manifest_hash": "c" * 64}, {"val/loss": 3.0})
    text = runs.format_runs(runs.compare_runs("cmp", uri=mlflow_uri))
    assert name in text and "c" * 13 not in text


def test_compare_runs_errors(mlflow_uri: str) -> None:
    _log("r", {"x": 1}, {"val/loss": 1.0})
    with pytest.raises(runs.RunsError, match="'nope' not found.*cmp"):
        runs.compare_runs("nope", uri=mlflow_uri)
    with pytest.raises(runs.RunsError, match=r"test/missing"):
        runs.compare_runs("cmp", metrics=["test/missing"], uri=mlflow_uri)


def test_unfinished_runs_left_out(mlflow_uri: str) -> None:
    _log("ok", {}, {"val/loss": 1.0})
    tracking.setup()
    with pytest.raises(RuntimeError):
        with tracking.start_run("cmp", "broken", profile="ci", stage="s"):
            raise RuntimeError("boom")
    assert list(runs.compare_runs("cmp", uri=mlflow_uri)["run_name"]) == ["ok"]
    assert len(runs.compare_runs("cmp", uri=mlflow_uri, include_unfinished=True)) == 2
    assert (
        runs.format_runs(
            runs.compare_runs("cmp", uri=mlflow_uri, filter_string="tags.profile = 'paper'")
        )
        == "(no finished runs)"
    )


def test_compare_runs_reads_the_names_users_see(mlflow_uri: str) -> None:
    """`test/kld_fou_mean` is logged per configuration (`test/<cfg>/kld_fou_mean`): with a
    configuration it picks that one, without it one column per configuration."""
    _log(
        "fusion-network",
        {},
        {"test/A/kld_fou_mean": 0.1, "test/D/kld_fou_mean": 0.4, "val/kld_full": 0.9},
    )
    df = runs.compare_runs(
        "cmp", metrics=["test/kld_fou_mean", "val/kld_full"], uri=mlflow_uri, configuration="D"
    )
    assert [c for c in df.columns if "/" in c] == ["test/D/kld_fou_mean", "val/kld_full"]
    assert df["test/D/kld_fou_mean"].item() == 0.4
    every = runs.compare_runs("cmp", metrics=["test/kld_fou_mean"], uri=mlflow_uri)
    assert [c for c in every.columns if "/" in c] == ["test/A/kld_fou_mean", "test/D/kld_fou_mean"]
    full = runs.compare_runs("cmp", metrics=["test/D/kld_fou_mean"], uri=mlflow_uri)
    assert [c for c in full.columns if "/" in c] == ["test/D/kld_fou_mean"]


def test_unknown_metric_error_is_one_short_line_with_close_matches(mlflow_uri: str) -> None:
    many = {f"test/{c}/registered_network/kld_fou_mean_ci_{s}": 1.0 for c in "ABCD" for s in "lh"}
    _log("r", {}, {**many, "test/D/kld_fou_mean": 0.4, "val/kld_full": 0.9})
    with pytest.raises(runs.RunsError) as err:
        runs.compare_runs("cmp", metrics=["test/kld_fu_mean"], uri=mlflow_uri, configuration="D")
    msg = str(err.value)
    assert "\n" not in msg and len(msg) < 300, msg
    assert "'test/kld_fu_mean'" in msg and "test/D/kld_fou_mean" in msg
    with pytest.raises(runs.RunsError) as err:
        runs.compare_runs("cmp", metrics=["val/kld_ful"], uri=mlflow_uri)
    assert "val/kld_full" in str(err.value) and len(str(err.value)) < 300
    with pytest.raises(runs.RunsError, match="no close match"):
        runs.compare_runs("cmp", metrics=["zzz"], uri=mlflow_uri)


def test_runs_compare_cli_configuration_and_short_error(mlflow_uri: str, capsys) -> None:
    from traffictwin.cli import main

    _log("fusion-network", {}, {"test/D/kld_fou_mean": 0.4, "val/kld_full": 0.9})
    argv = ["runs", "compare", "--experiment", "cmp", "--tracking-uri", mlflow_uri]
    assert main([*argv, "--metrics", "test/kld_fou_mean", "--configuration", "D"]) == 0
    assert "test/D/kld_fou_mean" in capsys.readouterr().out
    code = main([*argv, "--metrics", "test/kld_fou_mea"])
    err = capsys.readouterr().err.strip()
    assert code != 0 and "\n" not in err and len(err) < 300 and "test/D/kld_fou_mean" in err
