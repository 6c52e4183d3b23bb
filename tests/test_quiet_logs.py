"""Stages write no progress bars into a pipe: tqdm and MLflow's artifact bars only on a terminal;
the whole ci DAG's piped log stays short, says no warning and repeats nothing."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from collections import Counter
from pathlib import Path

from conftest import ROOT, ci_dag_log


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


#: DVC's own lines around every stage (they repeat by design)
_DVC_LINES = re.compile(
    r"^(Updating lock file '.*'|Running stage '.*':|> .*|Stage '.*' didn't change, skipping)?$"
)
_TIMESTAMP = re.compile(r"^\d{4}-\d\d-\d\d[ T]\d\d:\d\d:\d\d[,.]?\d* ?")
_DICT = re.compile(r"\{[^{}]*\}")


def test_the_ci_runs_log_is_short_and_quiet(ci_dag: Path) -> None:
    """The whole ci DAG's `dvc repro`, piped (the `ci_dag` build's log, TQDM_DISABLE unset): at most
    200 lines, no line mentioning a warning (`grep -ci warning` = 0), no carriage-return progress
    bars, no line written three times, no dictionary of more than a few keys."""
    log = ci_dag_log(ci_dag).read_text()
    lines = log.splitlines()
    assert len(lines) <= 200, f"{len(lines)} lines:\n" + "\n".join(lines[:40])
    warned = [ln for ln in lines if "warning" in ln.lower()]
    assert not warned, "\n".join(warned[:10])
    assert "\r" not in log
    said = Counter(_TIMESTAMP.sub("", ln) for ln in lines if not _DVC_LINES.match(ln))
    assert max(said.values(), default=0) < 3, [k for k, n in said.items() if n >= 3]
    dumps = [d for ln in lines for d in _DICT.findall(ln) if d.count(":") > 6]
    assert not dumps, dumps[:3]
