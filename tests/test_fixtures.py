"""The shared test fixtures' own contracts: what lets the ``ci_dag`` readers run beside its
copiers and beside tests with their own MLflow store under pytest-xdist."""

from __future__ import annotations

import os
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
        "mlflow.db",
        "mlartifacts/1/a.txt",
        "dvc.lock",
    ):
        (src / rel).parent.mkdir(parents=True, exist_ok=True)
        (src / rel).write_text(rel)
    full = copy_dag(src, tmp_path / "full")
    assert not (full / ".dvc" / "tmp").exists()
    for rel in (".dvc/config", ".dvc/cache/files/md5/ab/cd", "data/tmp/x.npz", "mlflow.db"):
        assert (full / rel).read_text() == rel  # only the top .dvc/tmp is left behind
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
