"""An identical re-run of a stage leaves dvc.lock byte-identical.

Wall times, throughput and MLflow run ids go to the run records (reports/timings, outside DVC);
checkpoints are serialised with a fixed archive name. A copy of the ci_dag repository (data,
models, DVC cache, its own MLflow database) re-runs representative stages with
`dvc repro -f -s`: a data stage, a training, an evaluation and the report (each stage writes its
outputs through the same writers, so these stand for the rest; re-running the whole DAG cost five
minutes); every hash in dvc.lock must stay, and no DVC output of the whole DAG may hold one of the
volatile keys.
"""

from __future__ import annotations

import csv
import json
import os
import sys
from pathlib import Path
from typing import Any

import pytest
import torch
import yaml
from conftest import copy_dag, run, run_record

# keys that held timings, run ids or absolute paths in DVC outputs before
VOLATILE_KEYS = {
    "train_seconds",
    "train_samples_per_s",
    "mlflow_run_id",
    "mlflow_model_uri",
    "data_root",
    "ms_per_pair",
    "runtime_ms_per_pair",
    "learned_runtime_ms",
    "all/ms_per_frame",
    "step_ms_median",
    "fusion_data/pairs_per_s",
}
VOLATILE_COLUMNS = {"ms", "step_ms", "seconds"}
# the report's former timing table and columns (the report is a DVC output)
REPORT_TIMING_HEADINGS = ("Stage wall times", "ms / pair", "train time [s]", "ms per update")


def _keys(obj: Any) -> set[str]:
    if isinstance(obj, dict):
        return set(obj) | {k for v in obj.values() for k in _keys(v)}
    if isinstance(obj, list):
        return {k for v in obj for k in _keys(v)}
    return set()


def _out_files(repo: Path) -> list[Path]:
    """Every file of every DVC output recorded in dvc.lock (entries of foreach items another
    profile ran, kept in dvc.lock by DVC, have no files here)."""
    lock = yaml.safe_load((repo / "dvc.lock").read_text())
    files = []
    for st in lock["stages"].values():
        for out in st.get("outs", []):
            p = repo / out["path"]
            files += sorted(f for f in p.rglob("*") if f.is_file()) if p.is_dir() else [p]
    return [f for f in files if f.exists()]


def _moved(before: bytes, after: bytes) -> list[tuple[str, str]]:
    """(stage, path) of every dvc.lock dependency or output entry of ``before`` not in ``after``."""
    a, b = yaml.safe_load(before)["stages"], yaml.safe_load(after)["stages"]
    return [
        (stage, e["path"])
        for stage in a
        for kind in ("deps", "outs")
        for e in a[stage].get(kind, [])
        if e not in b.get(stage, {}).get(kind, [])
    ]


def _first_differences(old_repo: Path, new_repo: Path, moved: list[tuple[str, str]]) -> str:
    """The first differing line of each moved text output (old vs new run), so a failure shows
    which rows and numbers moved, not only which files."""
    lines = []
    for _, rel in moved:
        a, b = old_repo / rel, new_repo / rel
        if not (a.is_file() and b.is_file()) or a.suffix not in (".csv", ".json", ".md"):
            continue
        old, new = a.read_text().splitlines(), b.read_text().splitlines()
        i = next((i for i, (x, y) in enumerate(zip(old, new)) if x != y), min(len(old), len(new)))
        head = old[0][:300] if a.suffix == ".csv" and old else ""
        lines.append(
            f"{rel} line {i + 1} (header: {head}):\n"
            f"  before: {old[i][:300] if i < len(old) else '<end>'}\n"
            f"  after:  {new[i][:300] if i < len(new) else '<end>'}"
        )
    return "\n".join(lines)


# a data stage, a training, an evaluation and the report: one of each kind of writer
RERUN_STAGES = ("generate_fusion", "train_fusion", "evaluate_risk", "report")


@pytest.mark.slow
def test_identical_rerun_leaves_dvc_lock_unchanged(ci_dag: Path, tmp_path: Path) -> None:
    repo = tmp_path / "repo"
    copy_dag(ci_dag, repo)
    before = (repo / "dvc.lock").read_bytes()
    records = sorted((repo / "reports" / "timings").glob("*.json"))
    assert records, "the stages wrote no run records"
    run(["dvc", "repro", "-f", "-s", *RERUN_STAGES], repo, timeout=1800)
    for stage in RERUN_STAGES:  # each did run again (a new run record)
        assert run_record(repo, stage)["started"] != run_record(ci_dag, stage)["started"], stage
    after = (repo / "dvc.lock").read_bytes()
    if after != before:
        moved = _moved(before, after)
        pytest.fail(
            f"dvc.lock changed on an identical rerun: {moved}\n"
            + _first_differences(ci_dag, repo, moved)
        )
    # the run records did change (new run ids, new times): they are where the noise went
    rec = json.loads((repo / "reports/timings/train_fusion.json").read_text())
    old = json.loads((ci_dag / "reports/timings/train_fusion.json").read_text())
    assert rec["run_id"] and rec["run_id"] != old["run_id"]
    assert rec["model_sha256"] == old["model_sha256"]  # the same weights, the same bytes
    assert "up to date" in run(["dvc", "status"], repo).stdout.lower()


@pytest.mark.slow
def test_no_dvc_output_holds_a_volatile_field(ci_dag: Path) -> None:
    files = _out_files(ci_dag)
    assert any(f.suffix == ".ckpt" for f in files) and any(f.suffix == ".csv" for f in files)
    for f in files:
        if f.suffix == ".json":
            found = _keys(json.loads(f.read_text())) & VOLATILE_KEYS
        elif f.suffix == ".csv":
            with open(f) as fh:
                found = set(next(csv.reader(fh), [])) & VOLATILE_COLUMNS
        elif f.suffix == ".ckpt":
            found = _keys(torch.load(f, weights_only=True).get("traffictwin", {})) & VOLATILE_KEYS
        elif f.suffix in (".md", ".html"):
            text = f.read_text()
            found = {k for k in REPORT_TIMING_HEADINGS if k in text}
        else:
            continue
        assert not found, f"{f.relative_to(ci_dag)}: {sorted(found)}"


EVALUATION_STAGES = ("evaluate_fusion", "evaluate_twin", "evaluate_risk")
# the evaluation re-run on one CPU: the cheapest of them (every one pins its threads the same way,
# through evaluation.num_threads; the ci DAG's run records show that each did)
PINNED_STAGE = "evaluate_risk"


@pytest.mark.slow
@pytest.mark.skipif(
    len(os.sched_getaffinity(0)) < 2, reason="one CPU: no other CPU count to compare with"
)
def test_evaluation_numbers_do_not_follow_the_cpu_count(ci_dag: Path, tmp_path: Path) -> None:
    """The evaluation stages run their networks on ``evaluation.num_threads`` torch threads, so on
    one CPU they write what the ci_dag run wrote on all of them (torch's default thread count
    follows the CPU affinity, and the learned registration's and the networks' numbers moved in
    their last digits with it)."""
    pinned = yaml.safe_load((ci_dag / "params.yaml").read_text())["evaluation"]["num_threads"]
    for stage in EVALUATION_STAGES:
        assert run_record(ci_dag, stage)["torch_threads"] == pinned, stage
    repo = tmp_path / "repo"
    copy_dag(ci_dag, repo)
    before = (repo / "dvc.lock").read_bytes()
    one_cpu = min(os.sched_getaffinity(0))
    argv = ["dvc", "repro", "-f", "-s", PINNED_STAGE]
    # pin to one CPU in the child itself (no preexec_fn: unsafe in a process with threads), then exec dvc
    pin = f"import os; os.sched_setaffinity(0, {{{one_cpu}}}); os.execvp('dvc', {argv!r})"
    run([sys.executable, "-c", pin], repo, timeout=1800)
    after = (repo / "dvc.lock").read_bytes()
    if after != before:
        moved = _moved(before, after)
        pytest.fail(f"moved on one CPU: {moved}\n" + _first_differences(ci_dag, repo, moved))
    record = run_record(repo, PINNED_STAGE)
    assert record["started"] != run_record(ci_dag, PINNED_STAGE)["started"]  # it did run again
    assert record["torch_threads"] == pinned


@pytest.mark.slow
def test_report_rendered_inside_an_experiment_leaves_dvc_lock_unchanged(
    ci_dag: Path, tmp_path: Path
) -> None:
    """After ``dvc exp run -S profile=ci``, ``dvc repro -f`` changed
    dvc.lock because the report carried the experiment's name and pipeline run id. The report
    rendered under an experiment's environment is now the same bytes as outside one."""
    from conftest import stage_env

    repo = tmp_path / "repo"
    copy_dag(ci_dag, repo)
    before = (repo / "dvc.lock").read_bytes()
    env = stage_env(repo) | {"DVC_EXP_NAME": "weepy-main", "TRAFFICTWIN_PIPELINE_RUN": "other-id"}
    run(["dvc", "repro", "-f", "-s", "report"], repo, env=env, timeout=900)
    assert _moved(before, (repo / "dvc.lock").read_bytes()) == []
    record = json.loads((repo / "reports/timings/report.json").read_text())
    assert record["dvc_exp_name"] == "weepy-main"  # the volatile values went to the run record
    assert record["pipeline_run"] == "other-id"
    run(["dvc", "repro", "-f", "-s", "report"], repo, timeout=900)  # and back outside
    assert (repo / "dvc.lock").read_bytes() == before
