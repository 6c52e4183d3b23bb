"""A failed, interrupted or killed retraining leaves the repository as before.

The flow (``python -m pipelines.retrain --no-promote``) runs for real in a toy repository: the
project's ``pipelines/`` and ``conf/`` with a two-stage ``dvc.yaml`` (``gen`` writes the seed into
``data/toy``, ``train`` copies it into ``models/toy``) whose ``train`` command fails, or sleeps
after writing its pid, as ``TOY_MODE`` says. So ``dvc repro``, ``dvc checkout`` and ``dvc status``
are the real ones, and nothing trains a network.

Time limits and stopping the process tree are the scheduler's (``pipelines/schedules/``): these
tests stand in for it, running the retraining in its own process group (as ``timeout`` does; a
systemd unit's cgroup) and signalling that group. ``test_retrain_schedules.py`` checks that the
schedules do so.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from pipelines import _checkout as ck
from pipelines import retrain as rt
from traffictwin.mlops.journal import Journal

WT = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent

TOY = """\
import os, pathlib, sys, time
import yaml

seed = yaml.safe_load(open("params.yaml"))["seed"]
if sys.argv[1] in ("reg", "ev"):
    out = pathlib.Path(sys.argv[2])
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(sys.argv[1])
    sys.exit(0)
if sys.argv[1] == "gen":
    pathlib.Path("data/toy").mkdir(parents=True, exist_ok=True)
    pathlib.Path("data/toy/x.txt").write_text(f"data {seed}")
    sys.exit(0)
mode = os.environ.get("TOY_MODE", "ok")
if mode == "fail":
    sys.exit(3)
if mode == "sleep":
    pidfile = pathlib.Path(os.environ["TOY_PIDFILE"])
    pidfile.with_suffix(".tmp").write_text(str(os.getpid()))
    pidfile.with_suffix(".tmp").rename(pidfile)
    time.sleep(600)
pathlib.Path("models/toy").mkdir(parents=True, exist_ok=True)
pathlib.Path("models/toy/model.txt").write_text("model of " + open("data/toy/x.txt").read())
"""

DVC_YAML = {
    "stages": {
        "gen": {
            "cmd": "python toy.py gen",
            "deps": ["toy.py"],
            "params": ["seed"],
            "outs": ["data/toy"],
        },
        "train": {
            "cmd": "python toy.py train",
            "deps": ["toy.py", "data/toy"],
            "outs": ["models/toy"],
        },
        # never run before the retraining: a failed `dvc checkout` must not leave their folders behind
        "reg": {
            "cmd": "python toy.py reg models/registration/A/model.ckpt",
            "deps": ["models/toy"],
            "outs": ["models/registration/A/model.ckpt"],
        },
        "ev": {
            "cmd": "python toy.py ev out/ev",
            "deps": ["models/registration"],
            "outs": ["out/ev"],
        },
    }
}

# each test runs `python -m pipelines.retrain` (and DVC) in a subprocess: process-level integration
pytestmark = pytest.mark.integration


def _env(repo: Path, mode: str = "ok") -> dict[str, str]:
    env = dict(os.environ)
    env.update(
        PATH=f"{BIN}{os.pathsep}{env.get('PATH', '')}",
        PYTHONPATH=os.pathsep.join((str(repo), str(WT / "src"))),  # the toy repo's own pipelines/
        MLFLOW_TRACKING_URI=f"sqlite:///{repo / 'mlflow.db'}",
        PYTHONHASHSEED="0",
        DVC_NO_ANALYTICS="1",
        TQDM_DISABLE="1",
        TOY_MODE=mode,
        TOY_PIDFILE=str(repo.parent / "toy.pid"),
    )
    env.pop(rt.FAIL_ENV, None)
    return env


def _sh(cmd: list[str], repo: Path, **kw) -> subprocess.CompletedProcess:
    proc = subprocess.run(
        cmd, cwd=repo, env=_env(repo), capture_output=True, text=True, timeout=300, **kw
    )
    assert proc.returncode == 0, (cmd, proc.stdout[-2000:], proc.stderr[-2000:])
    return proc


@pytest.fixture(scope="module")
def template(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The toy repository after a first `dvc repro` (seed as in params.yaml, outputs cached)."""
    repo = tmp_path_factory.mktemp("toy") / "repo"
    repo.mkdir()
    shutil.copytree(
        WT / "pipelines", repo / "pipelines", ignore=shutil.ignore_patterns("__pycache__")
    )
    shutil.copytree(WT / "conf", repo / "conf")
    shutil.copy2(WT / "params.yaml", repo / "params.yaml")
    (repo / "toy.py").write_text(TOY)
    (repo / "dvc.yaml").write_text(yaml.safe_dump(DVC_YAML, sort_keys=False))
    (repo / "reports").mkdir()
    (repo / "reports" / "committed.json").write_text('{"kept": true}\n')
    git = ["git", "-c", "user.email=t@t", "-c", "user.name=t", "-c", "commit.gpgsign=false"]
    _sh([*git, "init", "-q"], repo)
    _sh(["dvc", "init", "-q"], repo)
    _sh(["dvc", "repro", "-q", "train"], repo)
    _sh([*git, "add", "-A"], repo)
    _sh([*git, "commit", "-q", "-m", "toy"], repo)
    return repo


@pytest.fixture
def repo(template: Path, tmp_path: Path) -> Path:
    dest = tmp_path / "repo"
    shutil.copytree(template, dest, symlinks=True)
    return dest


def _state(repo: Path) -> dict[str, bytes]:
    """Bytes of everything a retraining may change and must restore."""
    files = [repo / "params.yaml", repo / "dvc.lock", *sorted((repo / "conf").rglob("*"))]
    files += sorted((repo / "reports").rglob("committed.json"))
    files += [repo / "data/toy/x.txt", repo / "models/toy/model.txt"]
    return {str(p.relative_to(repo)): p.read_bytes() for p in files if p.is_file()}


def _seed(repo: Path) -> int:
    return yaml.safe_load((repo / "params.yaml").read_text())["seed"]


def _summary(repo: Path) -> dict:
    return json.loads((repo / "reports" / "retrain_summary.json").read_text())


def _retrain(repo: Path, mode: str = "ok", **env) -> subprocess.CompletedProcess:
    e = _env(repo, mode) | env
    cmd = [sys.executable, "-m", "pipelines.retrain", "--no-promote"]
    return subprocess.run(cmd, cwd=repo, env=e, capture_output=True, text=True, timeout=300)


def _start(repo: Path, mode: str) -> subprocess.Popen:
    """A retraining in the background in its own process group, as the scheduler runs it; output
    to files (a pipe would stay open in an orphaned child)."""
    out = open(repo.parent / "retrain.out", "w")  # noqa: SIM115 - closed with the process
    cmd = [sys.executable, "-m", "pipelines.retrain", "--no-promote"]
    return subprocess.Popen(
        cmd,
        cwd=repo,
        env=_env(repo, mode),
        stdout=out,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie counts as gone)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat[stat.rindex(")") + 2] not in "ZXx"


def _kill_group(pgid: int, sig: int) -> None:
    """What the scheduler does on a timeout or stop: signal the run's whole process group."""
    try:
        os.killpg(pgid, sig)
    except ProcessLookupError:
        pass


def _wait(pred, what: str, proc: subprocess.Popen | None = None, limit: float = 180.0) -> None:
    """Poll ``pred`` (a hang guard, not a timing check)."""
    deadline = time.monotonic() + limit
    while not pred():
        if proc is not None and proc.poll() is not None:
            pytest.fail(f"{proc.args} exited {proc.returncode} while waiting for {what}")
        if time.monotonic() > deadline:
            pytest.fail(f"gave up waiting for {what}")
        time.sleep(0.05)


def _running_stage(repo: Path, proc: subprocess.Popen) -> int:
    pidfile = repo.parent / "toy.pid"
    _wait(pidfile.exists, "the train stage to start", proc)
    return int(pidfile.read_text())


# ------------------------------------------------------------------ failure


def test_failed_stage_gets_its_model_back_and_restored_is_verified(repo: Path):
    before = _state(repo)
    proc = _retrain(repo, mode="fail")
    assert proc.returncode == 1, proc.stderr[-3000:]
    s = _summary(repo)
    assert s["status"] == "failed" and s["failed_step"] == "dvc_repro"
    assert s["restored"] is True, s.get("restore_problems")
    # `train` failed after DVC had deleted models/toy: it is back, as are the data, dvc.lock, conf/
    assert _state(repo) == before
    assert not (
        repo / "models" / "registration"
    ).exists()  # no folder of a never-run stage appeared
    assert not (repo / ".retrain.journal").exists()
    assert "previous data and champions kept" in proc.stderr


def test_restored_is_false_with_the_reason_when_the_restore_cannot_be_verified(repo: Path):
    shutil.rmtree(repo / ".dvc" / "cache")  # nothing to check the old outputs out from
    params0 = (repo / "params.yaml").read_bytes()
    proc = _retrain(repo, mode="fail")
    assert proc.returncode == 1
    s = _summary(repo)
    assert s["status"] == "failed" and s["restored"] is False
    assert any("models/toy" in p for p in s["restore_problems"]), s["restore_problems"]
    assert "NOT restored" in proc.stderr
    assert (repo / ".retrain.journal" / "state.json").exists()  # kept: the next run retries
    # ... and the next run does not start on a state it could not restore
    again = _retrain(repo)
    assert again.returncode == 1
    s2 = _summary(repo)
    assert s2["failed_step"] == "recover" and s2["restored"] is False
    assert s2["recovered"]["restored"] is False
    assert (
        repo / "params.yaml"
    ).read_bytes() == params0  # restored again, not bumped a second time
    assert (repo / ".retrain.journal").exists()


# ------------------------------------------------------------------ signals


@pytest.mark.parametrize("sig", [signal.SIGTERM])
def test_signal_to_the_group_restores_and_the_next_run_works(repo: Path, sig):
    """The scheduler's stop (systemd KillMode=control-group, `timeout`) signals every process of
    the run: `dvc repro` and its stage end, the retraining restores and writes its summary."""
    before, seed0 = _state(repo), _seed(repo)
    proc = _start(repo, "sleep")
    try:
        stage_pid = _running_stage(repo, proc)
        assert _seed(repo) == seed0 + 1 and (repo / ".retrain.journal" / "state.json").exists()

        # a second retraining meanwhile exits 75 at once and leaves the journal to its owner
        busy = _retrain(repo)
        assert busy.returncode == rt.EXIT_LOCKED, busy.stderr
        assert "another retraining run holds the lock" in busy.stderr
        assert (repo / ".retrain.journal" / "state.json").exists() and proc.poll() is None

        _kill_group(proc.pid, sig)
        assert proc.wait(timeout=300) == 128 + sig
    finally:
        if proc.poll() is None:
            _kill_group(proc.pid, signal.SIGKILL)
    assert not _alive(stage_pid)  # the stage stayed in the group the scheduler signals
    s = _summary(repo)
    assert s["status"] == "interrupted" and s["signal"] == sig.name
    assert s["failed_step"] == "dvc_repro" and s["restored"] is True, s.get("restore_problems")
    assert _state(repo) == before
    assert not (repo / ".retrain.journal").exists()

    nxt = _retrain(repo)
    assert nxt.returncode == 0, nxt.stderr[-3000:]
    assert _summary(repo)["status"] == "succeeded" and _seed(repo) == seed0 + 1
    assert (repo / "models/toy/model.txt").read_text() == f"model of data {seed0 + 1}"


def test_sigkill_leaves_a_journal_that_the_next_run_recovers_from(repo: Path):
    """SIGKILL of the retraining alone leaves its `dvc repro` running, which keeps the inherited
    lock: the next run exits 75 and touches nothing. Once the scheduler has killed the rest of the
    group (systemd's final SIGKILL to the cgroup, `timeout --kill-after`), the next run recovers."""
    before, seed0 = _state(repo), _seed(repo)
    proc = _start(repo, "sleep")
    try:
        stage_pid = _running_stage(repo, proc)
        proc.kill()
        proc.wait(timeout=60)
        journal = json.loads((repo / ".retrain.journal" / "state.json").read_text())
        assert journal["pid"] == proc.pid and journal["step"] == "dvc_repro"
        assert _alive(stage_pid) and _seed(repo) == seed0 + 1  # as the killed run left them

        busy = _retrain(repo)  # its `dvc repro` still holds the lock: no restore under it
        assert busy.returncode == rt.EXIT_LOCKED, busy.stderr[-3000:]
        assert "another retraining run holds the lock" in busy.stderr
        assert _seed(repo) == seed0 + 1 and (repo / ".retrain.journal" / "state.json").exists()
    finally:
        _kill_group(proc.pid, signal.SIGKILL)
    _wait(lambda: not _alive(stage_pid), "the killed group to go")

    nxt = _retrain(repo)
    assert nxt.returncode == 0, nxt.stderr[-3000:]
    s = _summary(repo)
    assert s["status"] == "succeeded"
    assert s["recovered"]["pid"] == proc.pid and s["recovered"]["restored"] is True
    assert s["seeds"] == {"seed": [seed0, seed0 + 1]}  # bumped from the restored params, not twice
    assert (repo / "models/toy/model.txt").read_text() == f"model of data {seed0 + 1}"
    assert (repo / "conf").exists() and _state(repo)["conf/config.yaml"] == before[
        "conf/config.yaml"
    ]
    assert not (repo / ".retrain.journal").exists()


def test_unfinished_journal_is_dropped_without_a_restore(repo: Path):
    """A run killed while writing its journal had changed nothing: the half-written copy goes."""
    tmp = repo / ".retrain.journal.tmp"
    (tmp / "snapshot" / "conf").mkdir(parents=True)
    journal = Journal(repo / ".retrain.journal")
    assert ck.recover(repo, journal, logging.getLogger("t")) is None
    assert not tmp.exists()


# ------------------------------------------------------------------ building blocks, in-process


def test_signals_raise_once_then_are_only_noted():
    with rt.Signals() as guard:
        with pytest.raises(rt.Interrupted) as err:
            os.kill(os.getpid(), signal.SIGHUP)
            time.sleep(5)  # the handler raises at the next bytecode: never reached
        assert err.value.signum == signal.SIGHUP
        os.kill(os.getpid(), signal.SIGTERM)  # after it was raised once: only noted
        assert guard.received == signal.SIGHUP
    with rt.Signals() as guard:
        guard.hold()  # the gate moves aliases: a signal must not cut it short
        os.kill(os.getpid(), signal.SIGTERM)
        assert guard.received == signal.SIGTERM


def test_targets_that_consume_no_seed_are_refused_before_anything_changes(repo: Path) -> None:
    """`--targets environment` once wrote a new seed into params.yaml and reported success with
    the data unchanged."""
    doc = yaml.safe_load((repo / "dvc.yaml").read_text())
    doc["stages"]["environment"] = {
        "cmd": "python toy.py ev out/environment",
        "deps": ["toy.py"],
        "outs": ["out/environment"],
    }
    (repo / "dvc.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    before, seed = _state(repo), _seed(repo)
    e = _env(repo)
    cmd = [sys.executable, "-m", "pipelines.retrain", "--no-promote", "--targets", "environment"]
    proc = subprocess.run(cmd, cwd=repo, env=e, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 1, proc.stdout[-2000:] + proc.stderr[-2000:]
    err = [ln for ln in proc.stderr.splitlines() if ln.startswith("retrain:")]
    assert len(err) == 1 and "--targets environment: neither the stage nor" in err[0], proc.stderr
    assert "consumes the data seed key(s) seed" in err[0]
    assert _state(repo) == before and _seed(repo) == seed
    assert not (repo / "out" / "environment").exists()
    assert not (repo / "reports" / "retrain_summary.json").exists()
    # a target downstream of the seeded stage passes the check
    assert rt.seedless_targets(repo, ["train", "environment"], ["seed"]) == ["environment"]
    assert rt.seedless_targets(repo, ["gen"], ["seed.sub"]) == []
