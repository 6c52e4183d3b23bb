"""MLflow tracking: URI resolution, tags, a round trip through a temp SQLite store."""

from __future__ import annotations

from pathlib import Path

import mlflow

from traffictwin import tracking


def test_default_uri_is_absolute_sqlite_at_repo_root(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    uri = tracking.tracking_uri(tmp_path)
    assert uri == f"sqlite:///{tmp_path.resolve()}/mlflow.db"
    assert Path(uri.removeprefix("sqlite:///")).is_absolute()


def test_env_overrides(monkeypatch) -> None:
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "http://mlflow.example:5000")
    assert tracking.tracking_uri() == "http://mlflow.example:5000"


def test_run_round_trip(mlflow_uri: str) -> None:
    with tracking.start_run("unit", "unit-run", profile="ci", stage="test", params={"a.b": 1}) as run:
        mlflow.log_metric("val/loss", 0.5, step=1)
        rid = run.info.run_id
    got = mlflow.get_run(rid)
    assert got.data.params["a.b"] == "1"
    assert got.data.metrics["val/loss"] == 0.5
    assert got.data.tags["profile"] == "ci" and got.data.tags["dvc_stage"] == "test"
    assert len(got.data.tags["git_commit"]) > 0
