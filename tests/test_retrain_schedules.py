"""The schedulers supervise the retraining: a time limit and a stop of its whole process tree.

``pipelines/retrain.py`` keeps what protects the champion (lock, journal, restore, summary) and
leaves timeouts and process supervision to what runs it: the systemd unit (TimeoutStartSec,
KillMode=control-group, TimeoutStopSec), the crontab line (coreutils ``timeout`` on its process
group) and the GitHub Actions workflow (``timeout-minutes``). These tests read those definitions
and check each carries the settings, and that the systemd unit and the crontab agree.
"""

from __future__ import annotations

import configparser
import re
import shlex
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
SCHEDULES = ROOT / "pipelines" / "schedules"
UNITS = {"s": 1, "sec": 1, "m": 60, "min": 60, "h": 3600, "hr": 3600, "d": 86400}


def _seconds(value: str) -> float:
    """A systemd time span (``6h``, ``15min``, ``1h 30min``) or a ``timeout`` duration (``15m``)."""
    parts = re.findall(r"(\d+(?:\.\d+)?)\s*([a-z]*)", value.strip())
    assert parts and "".join(n + u for n, u in parts) == re.sub(r"\s", "", value), value
    return sum(float(n) * UNITS[u or "s"] for n, u in parts)


def _service() -> configparser.SectionProxy:
    cp = configparser.ConfigParser(strict=False, interpolation=None)
    cp.optionxform = str  # keys as written: KillMode, not killmode
    cp.read_string((SCHEDULES / "traffictwin-retrain.service").read_text())
    return cp["Service"]


def _cron_commands() -> list[list[str]]:
    lines = (SCHEDULES / "crontab").read_text().splitlines()
    return [shlex.split(ln)[5:] for ln in lines if ln.strip() and not ln.startswith("#")]


def _timeout_call(words: list[str]) -> tuple[dict[str, str], str, list[str]]:
    """(options, duration, command) of the ``timeout`` in a crontab command."""
    i = words.index("timeout")
    opts, j = {}, i + 1
    while words[j].startswith("-"):
        key, _, val = words[j].partition("=")
        opts[key] = val
        j += 1
    return opts, words[j], words[j + 1 :]


def test_systemd_unit_bounds_the_run_and_stops_its_whole_cgroup():
    svc = _service()
    assert svc["Type"] == "oneshot"  # RuntimeMaxSec does not apply to oneshot: TimeoutStartSec does
    assert "RuntimeMaxSec" not in svc
    assert 0 < _seconds(svc["TimeoutStartSec"]) <= 24 * 3600
    # SIGTERM to retrain, `dvc repro` and the stage alike (mixed/process would orphan the stage)
    assert svc["KillMode"] == "control-group"
    assert svc.get("KillSignal", "SIGTERM") == "SIGTERM"  # retrain restores on SIGTERM
    assert svc.get("SendSIGKILL", "yes") == "yes"
    assert 60 <= _seconds(svc["TimeoutStopSec"]) < _seconds(svc["TimeoutStartSec"])  # restore time
    assert "75" in svc["SuccessExitStatus"].split()  # the lock was busy: not a failure
    assert "pipelines.retrain" in svc["ExecStart"]


def test_cron_runs_retrain_under_timeout_of_its_process_group_as_the_unit_does():
    svc = _service()
    commands = _cron_commands()
    assert commands
    for words in commands:
        assert "flock" not in words  # a second lock on .retrain.lock would shut the run out
        opts, duration, cmd = _timeout_call(words)
        assert "--foreground" not in opts  # it would spare the children of pipelines.retrain
        assert opts.get("--signal", opts.get("-s", "TERM")) in ("TERM", "SIGTERM")
        assert _seconds(duration) == _seconds(svc["TimeoutStartSec"])
        assert _seconds(opts["--kill-after"]) == _seconds(svc["TimeoutStopSec"])
        assert cmd[-2:] == ["-m", "pipelines.retrain"] or cmd[1:3] == ["-m", "pipelines.retrain"]


def test_github_workflow_limits_the_retrain_step_within_the_job():
    doc = yaml.safe_load((ROOT / ".github" / "workflows" / "retrain.yml").read_text())
    job = doc["jobs"]["retrain"]
    steps = job["steps"]
    i = next(k for k, s in enumerate(steps) if "pipelines.retrain" in s.get("run", ""))
    step_limit, job_limit = steps[i]["timeout-minutes"], job["timeout-minutes"]
    assert 0 < step_limit < job_limit  # the summary steps after it still get time
    assert any(s.get("if") == "always()" for s in steps[i + 1 :])
    assert doc["concurrency"]["cancel-in-progress"] is False  # never cut a running one short


@pytest.mark.parametrize(
    ("text", "seconds"), [("6h", 21600), ("15min", 900), ("15m", 900), ("1h 30min", 5400)]
)
def test_durations_parse(text: str, seconds: float):
    assert _seconds(text) == seconds
