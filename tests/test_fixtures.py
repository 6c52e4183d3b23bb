"""The shared test fixtures' own contracts: what lets the ``ci_dag`` readers run beside its
copiers and beside tests with their own MLflow store under pytest-xdist."""

from __future__ import annotations

import os
import sqlite3
from pathlib import Path

import pytest
from conftest import copy_dag, mlflow_uris_kept


def test_copy_dag_leaves_dvc_tmp_and_on_request_the_mlflow_store_behind(tmp_path: Path) -> None:
    src = tmp_path / "src"
    for rel in (
        ".dvc/config",
        ".dvc/tmp/lock",
        ".dvc/cache/files/md5/ab/cd",
        "data/tmp/x.npz",
        "mlartifacts/1/a.txt",
        "dvc.lock",
    ):
        (src / rel).parent.mkdir(parents=True, exist_ok=True)
        (src / rel).write_text(rel)
    sqlite3.connect(src / "mlflow.db").close()  # an empty SQLite store
    full = copy_dag(src, tmp_path / "full")
    assert not (full / ".dvc" / "tmp").exists()
    for rel in (".dvc/config", ".dvc/cache/files/md5/ab/cd", "data/tmp/x.npz"):
        assert (full / rel).read_text() == rel  # only the top .dvc/tmp is left behind
    assert (full / "mlflow.db").exists() and (full / "mlartifacts/1/a.txt").exists()
    bare = copy_dag(src, tmp_path / "bare", mlflow=False)
    assert not (bare / "mlflow.db").exists() and not (bare / "mlartifacts").exists()
    assert (bare / "dvc.lock").exists() and (bare / ".dvc/cache/files/md5/ab/cd").exists()


def test_mlflow_uris_kept_undoes_set_tracking_and_registry_uri(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import mlflow

    mine = f"sqlite:///{tmp_path / 'mine.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", mine)
    monkeypatch.delenv("MLFLOW_REGISTRY_URI", raising=False)
    with mlflow_uris_kept():
        other = f"sqlite:///{tmp_path / 'shared.db'}"
        mlflow.set_tracking_uri(other)  # exports MLFLOW_TRACKING_URI too
        mlflow.set_registry_uri(other)  # exports MLFLOW_REGISTRY_URI too
        assert mlflow.get_tracking_uri() == other
    assert mlflow.get_tracking_uri() == mine
    assert mlflow.get_registry_uri() == mine
    assert os.environ["MLFLOW_TRACKING_URI"] == mine
    assert "MLFLOW_REGISTRY_URI" not in os.environ


def test_copy_dag_points_the_copied_mlflow_store_at_its_own_artifacts(tmp_path: Path) -> None:
    """A stage run in a copy logs beside the copy's store: the copied store's artifact locations
    name the copy, not the source's artifacts (which other tests read meanwhile)."""
    import mlflow

    src = tmp_path / "src"
    src.mkdir()
    with mlflow_uris_kept():
        mlflow.set_tracking_uri(f"sqlite:///{src / 'mlflow.db'}")
        exp = mlflow.create_experiment("fusion", artifact_location=(src / "mlartifacts").as_uri())
        with mlflow.start_run(experiment_id=exp) as run:
            mlflow.log_text("weights", "checkpoints/model.txt")
    dest = copy_dag(src, tmp_path / "dest")
    client = mlflow.MlflowClient(tracking_uri=f"sqlite:///{dest / 'mlflow.db'}")
    got = client.get_run(run.info.run_id).info.artifact_uri
    assert got == (dest / "mlartifacts" / run.info.run_id / "artifacts").as_uri()
    assert client.get_experiment(exp).artifact_location == (dest / "mlartifacts").as_uri()
    # the source store is untouched
    source = mlflow.MlflowClient(tracking_uri=f"sqlite:///{src / 'mlflow.db'}")
    assert source.get_run(run.info.run_id).info.artifact_uri.startswith(src.as_uri())
