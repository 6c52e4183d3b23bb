"""Fixtures of the reliability/security tests: a temp MLflow registry and artifact surgery."""

from __future__ import annotations

import pytest

from traffictwin.mlops import registry as reg


@pytest.fixture
def cl(mlflow_uri, tmp_path, monkeypatch):
    """A client on a temp SQLite registry; MLflow artifacts (./mlruns) go to the temp folder."""
    monkeypatch.chdir(tmp_path)
    return reg.client(mlflow_uri)
