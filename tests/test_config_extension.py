"""Adding a pose-noise configuration is one conf entry: the DAG picks it up from params.yaml.

(The CLI and the report iterate the configurations they are given; see test_cli / test_report.)
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import yaml
from conftest import BIN, run

pytestmark = pytest.mark.slow


def test_extra_configuration_appears_in_every_per_configuration_stage(repo_copy: Path) -> None:
    run(
        [
            sys.executable,
            "-m",
            "pipelines.compose_params",
            "profile=ci",
            "+configurations.E={r:7.5,alpha:25.0}",
        ],
        repo_copy,
    )
    params = yaml.safe_load((repo_copy / "params.yaml").read_text())
    assert list(params["configurations"]) == ["A", "B", "C", "D", "E"]
    stages = run([str(BIN / "dvc"), "stage", "list", "--name-only"], repo_copy).stdout.split()
    for stage in ("prealign", "train_fusion"):
        assert {f"{stage}@{c}" for c in "ABCDE"} <= set(stages), stages
    # evaluate_fusion reads every configuration's prealigned data and model through the folders
    dag = run([str(BIN / "dvc"), "dag", "--outs", "--md"], repo_copy).stdout
    assert "data/prealigned/E" in dag and "models/fusion/E/model.ckpt" in dag
    # nothing in code, conf or dvc.yaml spells the configuration list
    for rel in ("dvc.yaml", "conf"):
        for f in [repo_copy / rel] if rel.endswith(".yaml") else (repo_copy / rel).rglob("*.yaml"):
            text = f.read_text()
            assert "[A, B, C, D]" not in text and "- D\n" not in text, f"{f} lists configurations"
