"""CI workflows never paste untrusted text into a shell; least privilege.

Also the schedules: their logs stay outside reports/ (a failed retraining restores reports/).
"""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]
WORKFLOWS = sorted((ROOT / ".github" / "workflows").glob("*.y*ml"))
SCHEDULES = ROOT / "pipelines" / "schedules"


def _load(path: Path) -> dict:
    return yaml.safe_load(path.read_text())


def _steps(doc: dict):
    for job_id, job in doc["jobs"].items():
        for step in job.get("steps", []):
            yield job_id, step


def _refs(obj) -> str:
    """Every expression (`${{ ... }}`) anywhere in ``obj``, joined."""
    return " ".join(re.findall(r"\$\{\{(.*?)\}\}", yaml.safe_dump(obj)))


def test_there_are_workflows():
    assert WORKFLOWS, "no workflow found under .github/workflows"


@pytest.mark.parametrize("path", WORKFLOWS, ids=lambda p: p.name)
def test_no_expression_inside_a_run_script(path: Path):
    """`${{ inputs.x }}` (or any expression) in `run:` is pasted into the script before bash parses it."""
    for job_id, step in _steps(_load(path)):
        if "run" in step:
            assert "${{" not in step["run"], (
                f"{path.name} job {job_id} step {step.get('name')!r}: an expression inside run:, "
                "pass it through env: instead"
            )


@pytest.mark.parametrize("path", WORKFLOWS, ids=lambda p: p.name)
def test_permissions_none_by_default_and_least_privilege_per_job(path: Path):
    doc = _load(path)
    assert doc.get("permissions") == {}, f"{path.name}: top-level `permissions: {{}}` expected"
    for job_id, job in doc["jobs"].items():
        perms = job.get("permissions")
        assert isinstance(perms, dict), f"{path.name} job {job_id}: no explicit permissions"
        assert set(perms.values()) <= {"read", "write", "none"}, perms
        refs = _refs(job)
        untrusted = "secrets." in refs or "inputs." in refs or "github.event" in refs
        writes = [k for k, v in perms.items() if v == "write"]
        assert not (writes and untrusted), (
            f"{path.name} job {job_id}: holds {writes} write permission and sees secrets or "
            "user input: split it"
        )


# ------------------------------------------------------------------ the seed check, executed


def _seed_script() -> str:
    doc = _load(ROOT / ".github" / "workflows" / "retrain.yml")
    found = [s for _, s in _steps(doc) if "SEED" in (s.get("env") or {})]
    assert len(found) == 1, "one step gets the seed input through env: SEED"
    step = found[0]
    assert re.fullmatch(
        r"\$\{\{\s*(inputs|github\.event\.inputs)\.seed\s*\}\}", step["env"]["SEED"]
    )
    return step["run"]


def _run_seed_step(
    tmp_path: Path, seed: str
) -> tuple[subprocess.CompletedProcess, list[str] | None]:
    """The step's script as GitHub runs it (bash -e -o pipefail), with a stand-in for the venv's python."""
    fake = tmp_path / ".venv" / "bin" / "python"
    fake.parent.mkdir(parents=True, exist_ok=True)
    fake.write_text('#!/bin/sh\nprintf "%s\\n" "$@" > "$ARGS_OUT"\n')
    fake.chmod(0o755)
    args_out = tmp_path / "args"
    args_out.unlink(missing_ok=True)
    script = tmp_path / "step.sh"
    script.write_text(_seed_script())
    env = {"PATH": os.environ["PATH"], "SEED": seed, "ARGS_OUT": str(args_out), "LC_ALL": "C"}
    proc = subprocess.run(
        ["bash", "--noprofile", "--norc", "-eo", "pipefail", str(script)],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    return proc, (args_out.read_text().splitlines() if args_out.exists() else None)


@pytest.mark.parametrize(
    ("seed", "expected"),
    [
        ("", []),
        ("42", ["--seed", "42"]),
        ("0", ["--seed", "0"]),
        ("123456789", ["--seed", "123456789"]),
    ],
)
def test_valid_seed_reaches_retrain_as_one_argument(tmp_path: Path, seed: str, expected: list[str]):
    proc, args = _run_seed_step(tmp_path, seed)
    assert proc.returncode == 0, proc.stderr
    assert args == ["-m", "pipelines.retrain", *expected]


@pytest.mark.parametrize(
    "seed",
    [
        "1234567890",  # 10 digits
        "-1",
        "1 2",
        "1;touch pwned",
        "$(touch pwned)",
        "`touch pwned`",
        "1\ntouch pwned",
        "42 --targets x",
        "::set-output name=x::y",
    ],
)
def test_bad_seed_is_refused_without_running_anything(tmp_path: Path, seed: str):
    proc, args = _run_seed_step(tmp_path, seed)
    assert proc.returncode != 0
    assert args is None  # pipelines.retrain never started
    assert not (tmp_path / "pwned").exists()
    assert "must be 1 to 9 digits" in proc.stderr and seed not in proc.stderr + proc.stdout


# ------------------------------------------------------------------ schedules: logs outside reports/


def test_cron_log_is_outside_reports():
    lines = [
        ln
        for ln in (SCHEDULES / "crontab").read_text().splitlines()
        if ln.strip() and not ln.startswith("#")
    ]
    assert lines
    for ln in lines:
        targets = re.findall(r">>?\s*(\S+)", ln)
        assert targets, f"crontab line without a log redirection: {ln}"
        for t in targets:
            if t.startswith("&"):
                continue
            assert not t.startswith(("reports/", "./reports/")) and "/reports/" not in t, ln
        assert "pipelines.retrain" in ln


def test_systemd_unit_logs_outside_reports():
    unit = (SCHEDULES / "traffictwin-retrain.service").read_text()
    settings = dict(
        ln.split("=", 1) for ln in unit.splitlines() if "=" in ln and not ln.startswith("#")
    )
    for key in ("StandardOutput", "StandardError"):
        assert "reports" not in settings.get(key, "journal")
    # how the unit stops the run (KillMode=control-group): tests/test_retrain_schedules.py
