"""Clean interrupts and restarts: Ctrl-C ends a stage (worker pool included) and the CLI with one
line and status 130, and a writer's temp file left by a kill never enters a DVC hash."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from traffictwin import cli
from traffictwin.io.atomic import atomic_path
from traffictwin.io.outputs import OutputSet

ROOT = Path(__file__).resolve().parents[2]
ENV = {
    **os.environ,
    "PYTHONPATH": f"{ROOT / 'src'}{os.pathsep}{ROOT}",
    "TQDM_DISABLE": "1",  # no progress bar lines on stderr
}


def _ctrl_c_as_a_terminal_sends_it() -> None:
    """In the stage's process: SIGINT's default disposition, as under a terminal. A runner started
    in the background by a non-interactive shell (``cmd &``) ignores SIGINT, and its children
    would inherit that (Python then installs no KeyboardInterrupt handler)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _lines(err: str) -> list[str]:
    return [ln for ln in err.strip().splitlines() if ln.strip()]


def test_ctrl_c_in_a_stage_is_one_line_and_130(capsys):
    from pipelines._common import run_stage

    def main() -> None:
        raise KeyboardInterrupt

    try:
        with pytest.raises(SystemExit) as exc:
            run_stage(main, "demo")
    except KeyboardInterrupt:
        pytest.fail("Ctrl-C escaped run_stage as KeyboardInterrupt")
    assert exc.value.code == 130
    assert _lines(capsys.readouterr().err) == ["demo: interrupted (Ctrl-C)"]


STAGE = textwrap.dedent(
    """
    import sys, time
    from pipelines._common import map_shards, run_stage

    def work(i):
        print("started", flush=True)
        time.sleep(60)
        return i

    def main():
        for _ in map_shards(work, range(4), workers=2, state={}, desc="demo"):
            pass

    if __name__ == "__main__":
        run_stage(main, "demo")
    """
)


def test_ctrl_c_during_a_worker_pool_is_one_line_and_130(tmp_path):
    """SIGINT to the whole process group (as a terminal's Ctrl-C): the workers ignore it, the
    parent ends the pool; no traceback from any process."""
    script = tmp_path / "stage.py"
    script.write_text(STAGE)
    proc = subprocess.Popen(
        [sys.executable, str(script)],
        cwd=ROOT,
        env=ENV,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        preexec_fn=_ctrl_c_as_a_terminal_sends_it,
    )
    try:
        assert "started" in proc.stdout.readline()  # a worker is in its task
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=30)
    assert proc.returncode == 130, err
    assert _lines(err) == ["demo: interrupted (Ctrl-C)"], err


def test_ctrl_c_in_the_cli_is_one_line_and_130(monkeypatch, capsys):
    from traffictwin.cli import runs

    def interrupted(args):  # noqa: ANN001, ANN202
        raise KeyboardInterrupt

    monkeypatch.setattr(runs, "cmd_runs_compare", interrupted)
    assert cli.main(["runs", "compare", "--experiment", "x"]) == 130
    assert _lines(capsys.readouterr().err) == ["traffictwin runs: interrupted (Ctrl-C)"]


@pytest.mark.skipif(shutil.which("git") is None, reason="needs git for a DVC repository")
def test_a_writers_temp_file_never_enters_a_dvc_hash(tmp_path):
    """A stage depends on a folder; a temp file of either writer (as a kill leaves it) in that
    folder: ``dvc status`` still says up to date (the project's ``.dvcignore``)."""
    repo = tmp_path / "r"
    (repo / "figs").mkdir(parents=True)
    (repo / "figs" / "a.png").write_bytes(b"png")
    (repo / "dvc.yaml").write_text(
        "stages:\n  report:\n    cmd: ls figs > out.txt\n    deps: [figs]\n    outs: [out.txt]\n"
    )
    shutil.copy(ROOT / ".dvcignore", repo / ".dvcignore")

    def dvc(*argv: str) -> str:
        res = subprocess.run(
            [sys.executable, "-m", "dvc", *argv],
            cwd=repo,
            env=ENV,
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert res.returncode == 0, res
        return res.stdout

    subprocess.run(["git", "init", "-q"], cwd=repo, check=True, timeout=60)
    dvc("init", "-q")
    dvc("repro", "-q")
    target = repo / "figs" / "b.png"
    lock = (repo / "dvc.lock").read_bytes()
    with atomic_path(target) as tmp, OutputSet([repo / "figs" / "c.png"]) as outs:
        outs.write_bytes(repo / "figs" / "c.png", b"x")
        tmp.write_bytes(b"half")
        (repo / "figs" / ".x.png.tmp").touch()  # as `touch reports/figures/.x.png.tmp`
        temps = sorted(p.name for p in (repo / "figs").iterdir() if p.name.endswith(".tmp"))
        assert len(temps) == 3, temps
        status = dvc("status")
        repro = dvc("repro")
        assert "didn't change, skipping" in repro, repro
        assert (repo / "dvc.lock").read_bytes() == lock
        # without the ignore rule the same temp files change the folder's hash
        (repo / ".dvcignore").write_text("")
        changed = dvc("status")
    assert "up to date" in status, status
    assert "changed deps" in changed, changed


REGISTRATION_STAGE = textwrap.dedent(
    """
    import numpy as np
    from pipelines._common import run_stage
    from traffictwin.fusion.registration_batches import register_many
    from traffictwin.grid import GridSpec

    def main():
        rng = np.random.default_rng(0)
        n = 400  # minutes of work on two workers: Ctrl-C comes while they are busy
        m = rng.uniform(0, 0.5, (n, 2, 2, 96, 96)).astype(np.float32)
        poses = rng.normal(0, 1, (n, 3))
        print("pool", flush=True)
        register_many(m[:, 0], m[:, 1], poses, GridSpec(rows=96, cols=96, cell=0.5), workers=2)

    if __name__ == "__main__":
        run_stage(main, "evaluate_fusion")
    """
)


def test_ctrl_c_during_evaluate_fusions_registration_pool_is_one_line_and_130(tmp_path):
    """evaluate_fusion's classical registration pool (fork-server workers): SIGINT to the whole
    process group while both workers are busy ends the stage with one line and 130, no
    traceback from the parent, the fork server or any worker."""
    import psutil

    script = tmp_path / "stage.py"
    script.write_text(REGISTRATION_STAGE)
    proc = subprocess.Popen(
        [sys.executable, str(script)],
        cwd=ROOT,
        env=ENV,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        preexec_fn=_ctrl_c_as_a_terminal_sends_it,
    )
    try:
        assert "pool" in proc.stdout.readline()
        parent = psutil.Process(proc.pid)
        for _ in range(600):  # the fork server and its two workers, then a moment of work
            if len(parent.children(recursive=True)) >= 3:
                break
            time.sleep(0.1)
        time.sleep(2.0)
        assert len(parent.children(recursive=True)) >= 3
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=30)
    assert proc.returncode == 130, err
    assert _lines(err) == ["evaluate_fusion: interrupted (Ctrl-C)"], err


def test_registration_pool_workers_leave_ctrl_c_to_the_parent():
    """``evaluate_fusion``'s registration pool (a fork server's workers, set up by
    :func:`traffictwin.processes.map_indexed`): the worker set-up ignores SIGINT, so Ctrl-C
    prints no traceback per worker (the parent ends the pool)."""
    import cv2

    from traffictwin.fusion.registration import RegistrationParams
    from traffictwin.fusion.registration_batches import _POOL_STATE, _pool_init
    from traffictwin.grid import GridSpec
    from traffictwin.processes import _worker_init

    before, threads = signal.getsignal(signal.SIGINT), cv2.getNumThreads()
    try:
        _worker_init(_pool_init, (GridSpec(rows=8, cols=8, cell=0.5), RegistrationParams()))
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, before)
        cv2.setNumThreads(threads)
        _POOL_STATE.clear()
