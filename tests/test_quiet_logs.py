"""Stages write no progress bars into a pipe: tqdm and MLflow's artifact bars only on a terminal."""

from __future__ import annotations

import os
import subprocess
import sys

from conftest import ROOT


def _piped(code: str, **env: str) -> subprocess.CompletedProcess:
    e = {k: v for k, v in os.environ.items() if k not in ("TQDM_DISABLE",)}
    e.pop("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", None)
    e.update(env)
    return subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, env=e, capture_output=True, text=True, check=True
    )


def test_mlflow_artifact_bars_are_off_when_stderr_is_piped() -> None:
    code = (
        "import os; from pipelines._common import setup_logging; setup_logging(); "
        "print(os.environ.get('MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR'))"
    )
    assert _piped(code).stdout.strip() == "false"
    # a choice of the user's stands
    assert _piped(code, MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR="true").stdout.strip() == "true"


def test_stage_progress_bars_are_off_when_stderr_is_piped() -> None:
    """pipelines._common.map_shards (tqdm) draws nothing into a pipe, TQDM_DISABLE unset."""
    code = (
        "from pipelines._common import map_shards\n"
        "print(sum(map_shards(int, range(5), workers=1, state={}, desc='bar')))"
    )
    proc = _piped(code)
    assert proc.stdout.strip() == "10"
    assert "bar" not in proc.stderr and "\r" not in proc.stderr
