"""Adding a pose-noise configuration is one conf entry: the DAG, the CLI and the report pick it up."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import yaml
from conftest import BIN, run


@pytest.mark.slow
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
    assert {f"prealign@{c}" for c in "ABCDE"} <= set(stages), stages
    # one model per task: the one network trains on every configuration's noise (E included)
    assert "train_fusion" in stages and "train_fusion@E" not in stages
    tn = params["training_noise"]
    assert tn["configurations"] is None  # null = every configuration
    # evaluate_fusion reads every configuration's prealigned data through the folders
    dag = run([str(BIN / "dvc"), "dag", "--outs", "--md"], repo_copy).stdout
    assert "data/prealigned/E" in dag and "models/fusion/network/model.ckpt" in dag
    # nothing in code, conf or dvc.yaml spells the configuration list
    for rel in ("dvc.yaml", "conf"):
        for f in [repo_copy / rel] if rel.endswith(".yaml") else (repo_copy / rel).rglob("*.yaml"):
            text = f.read_text()
            assert "[A, B, C, D]" not in text and "- D\n" not in text, f"{f} lists configurations"


def test_cli_and_report_take_any_configuration(tmp_path: Path) -> None:
    """The report shows E's row, with r/alpha from the params, when fusion.json has it (the CLI
    needs no configuration: one network serves every pose-noise level)."""
    import json

    from pipelines.report import providers
    from traffictwin.config import typed
    from traffictwin.fusion.report_section import fusion_tables
    from traffictwin.report.config import ReportParams
    from traffictwin.report.model import ReportInputs, Sources

    p = typed(
        {
            "seed": 1,
            "profile": {"name": "ci"},
            "configurations": {"A": {"r": 0.0, "alpha": 0.0}, "E": {"r": 7.5, "alpha": 25.0}},
        },
        ReportParams,
    )
    assert p.pose_noise == {"A": (0.0, 0.0), "E": (7.5, 25.0)}
    assert len(providers(p.pose_noise)) == 4  # fusion, risk, stereo, twin
    (tmp_path / "metrics").mkdir()
    methods = {"naive": {"kld_fo_mean": 0.2}, "dnn": {"kld_fo_mean": 0.1}}
    fusion = {"test": {"A": methods, "E": methods}}
    (tmp_path / "metrics" / "fusion.json").write_text(json.dumps(fusion))
    src = Sources(ReportInputs(reports_dir=tmp_path, profile="ci", seed=1, git_commit="x"))
    kld = fusion_tables(src, p.pose_noise)[0]
    rows = {str(r[0].text if hasattr(r[0], "text") else r[0]): r for r in kld.rows}
    assert set(rows) >= {"A", "E"}, rows
    assert [str(getattr(c, "text", c)) for c in rows["E"][1:3]] == ["7.5", "25"]
