"""`make reset`'s DVC step (pipelines.reset): no error wall on a clone without a DVC cache, one
line on what is missing and what gets it, one line on the registry's champions."""

from __future__ import annotations

import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import ROOT, copy_repo, run

from pipelines import reset


def test_not_as_locked_keeps_only_outputs() -> None:
    status = {
        "generate_risk": [{"changed outs": {"data/risk": "not in cache"}}],
        "disparity": [
            {"changed deps": {"data/risk": "deleted"}},
            {"changed outs": {"data/disparity": "deleted"}},
        ],
        "report": ["always changed"],
    }
    assert reset.not_as_locked(status) == ["data/disparity", "data/risk"]


def test_missing_line_names_a_few_and_what_gets_them() -> None:
    paths = [f"data/d{i}" for i in range(6)]
    line = reset.missing_line(paths)
    assert line.startswith("make reset: 6 outputs of dvc.lock are not in this clone's DVC cache")
    assert "data/d3, …" in line and "data/d4" not in line
    assert "`make run`" in line and "`make pull`" in line and "\n" not in line
    assert "as dvc.lock says" in reset.missing_line([])


def test_champions_read_from_the_registry_database(tmp_path: Path) -> None:
    db = tmp_path / "mlflow.db"
    assert reset.champions(db) == []  # no registry
    with sqlite3.connect(db) as con:
        con.execute("CREATE TABLE registered_model_aliases (alias TEXT, version INT, name TEXT)")
        con.executemany(
            "INSERT INTO registered_model_aliases VALUES (?, ?, ?)",
            [("champion", 2, "traffictwin-risk"), ("challenger", 3, "traffictwin-risk")],
        )
    assert reset.champions(db) == ["traffictwin-risk@champion"]
    line = reset.registry_line(reset.champions(db), models_missing=True)
    assert "1 champions" in line and "`make run` or `make pull` first" in line
    assert reset.registry_line([], models_missing=True) is None


@pytest.mark.slow
def test_reset_on_a_clone_without_dvc_cache_prints_no_error(tmp_path: Path) -> None:
    """A fresh clone: nothing is in the DVC cache, so every output is missing; the step says so
    in one line, exits 0 and prints no ERROR (plain `dvc checkout` prints one and 20 paths)."""
    repo = copy_repo(tmp_path / "repo")
    proc = run([sys.executable, "-m", "pipelines.reset"], repo)
    out = proc.stdout + proc.stderr
    assert "ERROR" not in out
    lines = [ln for ln in out.splitlines() if ln.strip()]
    assert len(lines) == 1, out
    assert "outputs of dvc.lock are not in this clone's DVC cache" in lines[0]
    assert "models/" in lines[0] or "data/" in lines[0]


def test_makefile_reset_runs_the_step_instead_of_a_plain_checkout() -> None:
    text = (ROOT / "Makefile").read_text()
    body = text.split("\nreset:", 1)[1].split("\n\n", 1)[0]
    assert "-m pipelines.reset" in body
    assert "dvc checkout ||" not in body
    # the command exists
    assert (
        subprocess.run([sys.executable, "-c", "import pipelines.reset"], cwd=ROOT).returncode == 0
    )
