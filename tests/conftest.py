"""Shared fixtures: repository copies for stage/DAG tests, a temp MLflow database.

``ci_dag`` runs the whole DVC pipeline once per test session on the ``ci`` profile in a
temp copy of the repository; stage tests inspect its outputs instead of re-running stages.
"""

from __future__ import annotations

import copy
import functools
import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from traffictwin.threads import passive_omp_wait  # imports no torch

# OpenMP threads sleep instead of spinning while they wait, in the test processes and every
# stage or CLI process they start (they inherit OMP_WAIT_POLICY; OpenMP reads it when torch
# loads, so before any torch import): the suite runs two xdist workers, the ci DAG's build and
# their subprocesses on the same cores, where spinning threads made torch work 3-60x slower
passive_omp_wait()

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
_ANYWHERE = shutil.ignore_patterns(
    ".venv",
    ".git",
    "mlflow.db*",
    "mlartifacts",
    "mlruns",
    "__pycache__",
    ".pytest_cache",
    "*.egg-info",
)
# generated or local-only folders, ignored only at the repository root (src/traffictwin/models must be copied)
_TOP_LEVEL = {
    "data",
    "models",
    "outputs",
    "multirun",
    ".benchmarks",
    "incoming",
    ".gl",
    ".whl",
    ".retrain.lock",
    ".retrain.journal",
    ".retrain.journal.tmp",
    "logs",
}
_DVC_LOCAL = {"cache", "tmp"}


def _ignore(folder: str, names: list[str]) -> set[str]:
    here = Path(folder).resolve()
    skip = set(_ANYWHERE(folder, names))
    if here == ROOT:
        skip |= _TOP_LEVEL & set(names)
    elif here == ROOT / ".dvc":
        skip |= _DVC_LOCAL & set(names)
    return skip


def committed(rel: str) -> str:
    """The committed text of ``rel`` (``git show HEAD:<rel>``): what the repository shows, whatever
    a run in this checkout left in the workspace (the Quick start leaves params.yaml, dvc.lock and
    reports/ on the ci profile). Outside a git checkout (or for a file not yet committed): the
    workspace file."""
    proc = subprocess.run(
        ["git", "show", f"HEAD:{rel}"], cwd=ROOT, capture_output=True, text=True, check=False
    )
    return proc.stdout if proc.returncode == 0 else (ROOT / rel).read_text()


def committed_tree(rel: str, dest: Path) -> Path:
    """The committed folder ``rel`` extracted under ``dest`` (``git archive HEAD``); the workspace
    folder outside a git checkout. Returns the folder to read."""
    proc = subprocess.run(
        ["git", "archive", "--format=tar", "HEAD", rel], cwd=ROOT, capture_output=True, check=False
    )
    if proc.returncode != 0:
        return ROOT / rel
    import io
    import tarfile

    with tarfile.open(fileobj=io.BytesIO(proc.stdout)) as tar:
        tar.extractall(dest, filter="data")
    return dest / rel


@functools.cache
def _composed(overrides: tuple[str, ...]) -> dict:
    from traffictwin.config import compose_config

    return compose_config(ROOT / "conf", list(overrides))


def composed(*overrides: str) -> dict:
    """The repository's conf/ composed with ``overrides`` (Hydra, as ``compose_config``), made once
    per test process for each set of overrides (a composition takes ~0.4 s); a deep copy each call,
    so a test may change it."""
    return copy.deepcopy(_composed(overrides))


def stage_env(repo: Path, mlflow_db: Path | None = None) -> dict[str, str]:
    """Environment for running stages in ``repo``: venv on PATH, its own MLflow database."""
    env = dict(os.environ)
    env["PATH"] = f"{BIN}{os.pathsep}{env.get('PATH', '')}"
    env["PYTHONPATH"] = os.pathsep.join(
        (str(repo / "src"), str(repo))
    )  # the copy's own library code
    env["MLFLOW_TRACKING_URI"] = f"sqlite:///{mlflow_db or repo / 'mlflow.db'}"
    env["TRAFFICTWIN_REPO_ROOT"] = str(repo)
    env["PYTHONHASHSEED"] = "0"
    env.setdefault("TQDM_DISABLE", "1")
    return env


def copy_repo(dest: Path) -> Path:
    """Copy the working tree (no venv, data, models, MLflow db) into ``dest`` as a fresh git+DVC repo."""
    shutil.copytree(ROOT, dest, ignore=_ignore, symlinks=True)
    for rel in ("reports/metrics", "reports/figures", "reports/plots", "reports/timings"):
        shutil.rmtree(dest / rel, ignore_errors=True)
    git = ["git", "-c", "user.email=t@t", "-c", "user.name=t", "-c", "commit.gpgsign=false"]
    subprocess.run([*git, "init", "-q"], cwd=dest, check=True)
    subprocess.run([*git, "add", "-A"], cwd=dest, check=True)
    subprocess.run([*git, "commit", "-q", "-m", "test copy"], cwd=dest, check=True)
    return dest


def run(
    cmd: list[str] | str, repo: Path, check: bool = True, timeout: int = 900, **kw
) -> subprocess.CompletedProcess:
    """Run ``cmd`` in ``repo`` with :func:`stage_env`; on failure show its output."""
    env = kw.pop("env", None) or stage_env(repo)
    proc = subprocess.run(
        cmd,
        cwd=repo,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
        shell=isinstance(cmd, str),
        **kw,
    )
    if check and proc.returncode != 0:
        raise AssertionError(
            f"command failed ({proc.returncode}): {cmd}\n--- stdout\n{proc.stdout[-6000:]}\n--- stderr\n{proc.stderr[-6000:]}"
        )
    return proc


@contextmanager
def pipelines_of(repo: Path) -> Iterator[None]:
    """Inside the block ``import pipelines.<stage>`` imports ``repo``'s stage scripts (their
    ROOT, params.yaml and output folders are ``repo``'s), with ``TRAFFICTWIN_REPO_ROOT`` set to
    ``repo``; afterwards this process's own ``pipelines`` modules, ``sys.path`` and environment
    (which a stage's ``run_stage`` extends) are back."""

    def loaded() -> dict:
        return {k: m for k, m in sys.modules.items() if k.split(".")[0] == "pipelines"}

    own, path, env = loaded(), list(sys.path), dict(os.environ)
    for k in own:
        del sys.modules[k]
    sys.path.insert(0, str(repo))
    os.environ["TRAFFICTWIN_REPO_ROOT"] = str(repo)
    try:
        yield
    finally:
        for k in loaded():
            del sys.modules[k]
        sys.modules.update(own)
        sys.path[:] = path
        os.environ.clear()
        os.environ.update(env)


def stage_in_process(
    repo: Path, stage: str, args: list[str] | tuple[str, ...] = ()
) -> tuple[int, str]:
    """``python -m pipelines.<stage> *args`` of ``repo`` run in this process, the way its
    ``__main__`` runs it (``run_stage(main, <stage>)``): (exit status, what it wrote to stderr).

    For argument and parameter checks, which end before a stage's work begins: no interpreter
    start and torch / Lightning / MLflow imports per check. The stage's log records go to
    pytest's log capture (``caplog``), not to the returned stderr."""
    import contextlib
    import importlib
    import io

    err = io.StringIO()
    with pipelines_of(repo):
        module = importlib.import_module(f"pipelines.{stage}")
        common = importlib.import_module("pipelines._common")
        argv = sys.argv
        sys.argv = [f"pipelines.{stage}", *args]
        try:
            with contextlib.redirect_stderr(err):
                common.run_stage(module.main, stage)
            code = 0
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 1
        finally:
            sys.argv = argv
    return code, err.getvalue()


def run_record(repo: Path, stage: str) -> dict:
    """The run record ``reports/timings/<stage>.json`` of ``stage`` in ``repo`` (MLflow run id,
    model URI, timings: what stages keep out of their DVC outputs)."""
    import json

    return json.loads(
        (repo / "reports" / "timings" / f"{stage.replace('@', '-')}.json").read_text()
    )


def copy_dag(src: Path, dest: Path, *, mlflow: bool = True) -> Path:
    """Copy a finished DAG repository (data, models, DVC cache, git history) to ``dest``.

    Its ``.dvc/tmp`` (DVC's repo lock, rwlock and experiment queue) stays behind: a DVC command
    running in ``src`` meanwhile (another xdist worker's ``dvc status`` in the shared ``ci_dag``)
    creates and deletes files there, which would break or poison the copy. The copied MLflow
    store's paths point into the copy (its artifacts stay its own); ``mlflow=False`` leaves the
    store (``mlflow.db*``, ``mlartifacts``, ``mlruns``) behind."""
    src = src.resolve()
    skip_mlflow = shutil.ignore_patterns("mlflow.db*", "mlartifacts", "mlruns")

    def ignore(folder: str, names: list[str]) -> set[str]:
        skip = {"tmp"} & set(names) if Path(folder).resolve() == src / ".dvc" else set()
        return skip if mlflow else skip | set(skip_mlflow(folder, names))

    shutil.copytree(src, dest, symlinks=True, ignore=ignore)
    if mlflow and (dest / "mlflow.db").is_file():
        _repoint_mlflow_store(dest / "mlflow.db", src, dest.resolve())
    return dest


def _repoint_mlflow_store(db: Path, src: Path, dest: Path) -> None:
    """Rewrite every ``src/...`` path the copied SQLite MLflow store ``db`` holds (experiments'
    artifact locations, runs' artifact URIs, model sources) to ``dest/...``: a stage run in the
    copy then writes its artifacts beside the copy's store, not into ``src``'s (which other
    tests read at the same time)."""
    import sqlite3

    old, new = f"{src}/", f"{dest}/"
    with sqlite3.connect(db) as con:
        tables = [r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type='table'")]
        for table in tables:
            for col in con.execute(f'PRAGMA table_info("{table}")').fetchall():
                if "CHAR" in col[2].upper() or "TEXT" in col[2].upper():
                    con.execute(
                        f'UPDATE "{table}" SET "{col[1]}" = replace("{col[1]}", ?, ?) '
                        f'WHERE instr("{col[1]}", ?) > 0',
                        (old, new, old),
                    )
    con.close()


@contextmanager
def mlflow_uris_kept() -> Iterator[None]:
    """Restore MLflow's process-wide tracking and registry URIs, and the environment variables
    that ``mlflow.set_tracking_uri`` / ``set_registry_uri`` export, to what they were on entry."""
    env = {k: os.environ.get(k) for k in ("MLFLOW_TRACKING_URI", "MLFLOW_REGISTRY_URI")}
    uris = (None, None)
    if "mlflow" in sys.modules:
        from mlflow.tracking._model_registry import utils as registry_utils
        from mlflow.tracking._tracking_service import utils as tracking_utils

        uris = (tracking_utils._tracking_uri, registry_utils._registry_uri)
    try:
        yield
    finally:
        if "mlflow" in sys.modules:
            import mlflow
            from mlflow.tracking._model_registry import utils as registry_utils
            from mlflow.tracking._tracking_service import utils as tracking_utils

            if tracking_utils._tracking_uri != uris[0]:
                mlflow.set_tracking_uri(uris[0])
            registry_utils._registry_uri = uris[1]
        for k, v in env.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


@pytest.fixture(autouse=True)
def _mlflow_uris_restored() -> Iterator[None]:
    """Every test leaves MLflow's URIs as it found them (:func:`mlflow_uris_kept`): a test that
    points MLflow at the shared ``ci_dag`` store would otherwise send the next test's runs there
    (the next in its worker: under pytest-xdist any test), and ``ci_dag``'s readers would see a
    run that no stage logged."""
    with mlflow_uris_kept():
        yield


@pytest.fixture
def repo_copy(tmp_path: Path) -> Path:
    """A fresh copy of the repository with params.yaml composed for the ``ci`` profile."""
    repo = copy_repo(tmp_path / "repo")
    run([sys.executable, "-m", "pipelines.compose_params", "profile=ci"], repo)
    return repo


@pytest.fixture(scope="session")
def ci_dag(tmp_path_factory: pytest.TempPathFactory, worker_id: str) -> Path:
    """The whole DAG run once with `dvc repro` on the ci profile; returns the repo copy.

    Under pytest-xdist every worker gets the same copy: the first to ask builds it under a file
    lock in the run's shared temp folder, the others wait for it (a failed build fails them too)."""
    if worker_id == "master":  # not under xdist
        return _build_ci_dag(tmp_path_factory.mktemp("ci_dag") / "repo")
    return _shared_ci_dag(tmp_path_factory.getbasetemp().parent / "ci_dag")


def _shared_ci_dag(shared: Path) -> Path:
    """The ci DAG under ``shared`` (built by the first caller, under a file lock; the others
    wait), for the xdist workers and for the controller's early build (:func:`pytest_sessionstart`)."""
    from filelock import FileLock

    shared.mkdir(parents=True, exist_ok=True)
    failed = shared / "FAILED"
    with FileLock(str(shared / "build.lock")):
        if failed.exists():
            raise AssertionError(f"the shared ci DAG failed to build: {failed.read_text()[-3000:]}")
        repo = shared / "repo"
        if not (shared / "DONE").exists():
            shutil.rmtree(repo, ignore_errors=True)
            try:
                _build_ci_dag(repo)
            except BaseException as exc:
                failed.write_text(str(exc))
                raise
            (shared / "DONE").touch()
    return repo


def whole_suite(config: pytest.Config) -> bool:
    """Whether this run selects the whole suite: no paths, ``-k`` or ``-m`` given (``make test``)."""
    return config.args_source != pytest.Config.ArgsSource.ARGS and not (
        config.option.markexpr or config.option.keyword
    )


def builds_ci_dag_early(config: pytest.Config) -> bool:
    """Whether this process starts the shared ci DAG at the session's start: the pytest-xdist
    controller of a whole-suite run (:func:`whole_suite`), where the DAG is certainly needed and
    the workers run every other test while it builds."""
    return (
        not hasattr(config, "workerinput")
        and bool(getattr(config.option, "numprocesses", None))
        and whole_suite(config)
        and not config.option.collectonly
    )


_EARLY: dict[str, subprocess.Popen] = {}  # the early build's `dvc repro`, stopped at session end


def pytest_sessionstart(session: pytest.Session) -> None:
    """Start building the ci DAG in the background on the xdist controller of a whole-suite run
    (:func:`builds_ci_dag_early`); the ``ci_dag`` fixture then finds it built (or waits for it)
    instead of one worker building it while the other idles. A failed early build is left to the
    fixture, which reports it."""
    if not builds_ci_dag_early(session.config):
        return
    import threading

    shared = session.config._tmp_path_factory.getbasetemp() / "ci_dag"

    def build() -> None:
        try:
            _shared_ci_dag(shared)
        except BaseException:  # noqa: BLE001 - the workers' fixture raises it with the log
            pass

    threading.Thread(target=build, name="ci_dag early build", daemon=True).start()


def pytest_sessionfinish(session: pytest.Session) -> None:
    """Stop an early ci DAG build still running (a run that ended early, e.g. ``-x``); write the
    recorded durations (``--record-durations``)."""
    _write_durations(session.config)
    proc = _EARLY.pop("repro", None)
    if proc is not None and proc.poll() is None:
        import signal

        os.killpg(proc.pid, signal.SIGTERM)


def ci_dag_log(repo: Path) -> Path:
    """The log of the ``ci_dag`` build's ``dvc repro`` (stdout and stderr in order, as a pipe gets
    them), kept beside the repository (outside it: no DVC or git command sees it)."""
    return repo.parent / "dvc_repro.log"


def _build_ci_dag(repo: Path) -> Path:
    copy_repo(repo)
    run([sys.executable, "-m", "pipelines.compose_params", "profile=ci"], repo)
    env = stage_env(repo)
    env.pop(
        "TQDM_DISABLE", None
    )  # a user's piped run: the stages must keep a pipe quiet themselves
    log = ci_dag_log(repo)
    with log.open("w") as out:
        proc = subprocess.Popen(
            ["dvc", "repro"],
            cwd=repo,
            env=env,
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,  # its own process group: pytest_sessionfinish can stop it
        )
        _EARLY["repro"] = proc
        try:
            proc.wait(timeout=1800)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, 9)
            raise
        finally:
            _EARLY.pop("repro", None)
    if proc.returncode != 0:
        raise AssertionError(f"dvc repro failed ({proc.returncode}):\n{log.read_text()[-6000:]}")
    return repo


@pytest.fixture(scope="session")
def mlflow_store_template(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An empty SQLite MLflow store, made once per worker: a new store's tables and schema
    migrations take seconds, a copy of it milliseconds (:func:`mlflow_uri` copies it). Made in a
    process of its own, so this process's MLflow state is untouched."""
    folder = tmp_path_factory.mktemp("mlflow_template")
    db = folder / "mlflow.db"
    code = "import sys; from mlflow import MlflowClient; MlflowClient(sys.argv[1]).search_experiments()"
    subprocess.run(
        [sys.executable, "-c", code, f"sqlite:///{db}"],
        cwd=folder,  # the Default experiment's artifacts: <folder>/mlruns/0, repointed by each copy
        check=True,
        capture_output=True,
        timeout=300,
    )
    return db


@pytest.fixture
def mlflow_uri(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, mlflow_store_template: Path) -> str:
    """A temp SQLite MLflow backend (a copy of :func:`mlflow_store_template`, its Default
    experiment's artifacts under ``tmp_path/mlruns``), exported as MLFLOW_TRACKING_URI."""
    shutil.copyfile(mlflow_store_template, tmp_path / "mlflow.db")
    _repoint_mlflow_store(
        tmp_path / "mlflow.db", mlflow_store_template.parent.resolve(), tmp_path.resolve()
    )
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    monkeypatch.setenv("TRAFFICTWIN_MODEL_CACHE", str(tmp_path / "model_cache"))  # per test
    return uri


@pytest.fixture
def cl(mlflow_uri: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """An MLflow client on the temp SQLite registry; MLflow artifacts (./mlruns) go to the temp folder."""
    from traffictwin.mlops import registry as reg

    monkeypatch.chdir(tmp_path)
    return reg.client(mlflow_uri)


@pytest.fixture(scope="module")
def single_torch_thread():
    """One torch intra-op thread for a module: on the shared 2-core machine OpenMP spinning makes 2 threads far slower under load."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


# fixtures that stand for an MLflow database: tests using them are integration tests
_INTEGRATION_FIXTURES = {"mlflow_uri", "cl"}
# fixtures that run stages or the whole DAG in a repository copy: tests using them are slow, so
# `make test-fast` (-m "not slow and not integration and not long") never runs a DAG
_SLOW_FIXTURES = {"ci_dag", "repo_copy", "ci_repo"}


# the longest tests (minutes each on 2 cores): started first among their kind so that none is
# left to run alone at the end of a parallel run (`make test`'s --durations list shows them)
_LONGEST = (
    "tests/test_readme.py::test_readme_ci_blocks_run_as_written",
    "tests/test_retrain.py::test_retrain_end_to_end_lock_and_failure_restore",
    "tests/reliability/test_rerun_identical.py::",
    "tests/test_experiments.py::",
    "tests/test_ddp.py::test_ddp_",  # one worker's group (xdist_group): the DDP stage tests
)


def _run_order(item: pytest.Item) -> tuple[bool, int]:
    """Sort key: tests that wait for the shared ``ci_dag`` last, so that under pytest-xdist the
    other workers run everything else while one builds it; the longest tests first of each kind,
    in the order of :data:`_LONGEST`."""
    waits = "ci_dag" in getattr(item, "fixturenames", ())
    rank = next((i for i, p in enumerate(_LONGEST) if item.nodeid.startswith(p)), len(_LONGEST))
    return waits, rank


#: the recorded time of every test (setup + call + teardown, s), written by a whole run with
#: ``--record-durations tests/durations.json`` (docs/testing.md); read to mark the ``long`` tests
DURATIONS = ROOT / "tests" / "durations.json"
#: a test whose recorded time is at least this (s) is ``long``: `make test-fast` leaves it out
LONG_S = 0.5


def recorded_durations(path: Path | None = None) -> dict[str, float]:
    """``{node id: seconds}`` from ``path`` (default :data:`DURATIONS`); empty when there is none."""
    import json

    path = DURATIONS if path is None else path
    if not path.is_file():
        return {}
    data = json.loads(path.read_text())
    if not isinstance(data, dict) or not all(isinstance(v, int | float) for v in data.values()):
        raise pytest.UsageError(f"{path}: expected a JSON object {{node id: seconds}}")
    return data


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--record-durations",
        metavar="PATH",
        default=None,
        help="write every test's time (setup + call + teardown, s) to PATH as JSON at the end "
        "of the run; tests/durations.json is what marks the `long` tests",
    )


@pytest.hookimpl(tryfirst=True)  # before the -m deselection of the mark plugin
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    recorded = recorded_durations()
    for item in items:
        names = set(getattr(item, "fixturenames", ()))
        if _INTEGRATION_FIXTURES & names:
            item.add_marker(pytest.mark.integration)
        if _SLOW_FIXTURES & names:
            item.add_marker(pytest.mark.slow)
        if recorded.get(item.nodeid, 0.0) >= LONG_S:
            item.add_marker(pytest.mark.long)
    items.sort(key=_run_order)  # stable: collection order within each kind
    if hasattr(config, "workerinput") and config.getvalue("loadgroup"):  # set by xdist
        for item in items:
            _join_xdist_group(item)


def _join_xdist_group(item: pytest.Item) -> None:
    """Give a test marked ``xdist_group(NAME)`` the node id ``<id>@NAME``, by which
    pytest-xdist's ``--dist loadgroup`` sends a group to one worker. pytest-xdist 3.8 writes that
    suffix to ``item._nodeid``, which pytest 9 no longer reads (a node's id is ``item._id``): the
    groups were silently ignored (the DDP tests' repository was built on both workers, and the
    ``ci_dag_dvc`` group's DVC commands ran at the same time)."""
    names = {
        str(m.args[0] if m.args else m.kwargs.get("name", "default"))
        for m in item.iter_markers("xdist_group")
    }
    suffix = "@" + "_".join(sorted(names))
    if not names or item.nodeid.endswith(suffix):
        return
    from _pytest.nodeid import coerce_node_id

    item._id = coerce_node_id(item.nodeid + suffix)


def plain_nodeid(nodeid: str) -> str:
    """``nodeid`` without the ``@group`` suffix :func:`_join_xdist_group` adds (the suffix follows
    the last ``]`` of a parametrized id, as pytest-xdist splits it)."""
    at = nodeid.rfind("@")
    return nodeid[:at] if at > nodeid.rfind("]") else nodeid


_TIMES: dict[str, float] = {}  # node id -> seconds of this run (--record-durations)


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    """Add up each test's phases (under pytest-xdist the controller gets every worker's reports),
    when the run records them (``--record-durations``)."""
    if _RECORDING:
        nodeid = plain_nodeid(report.nodeid)
        _TIMES[nodeid] = _TIMES.get(nodeid, 0.0) + report.duration


_RECORDING: list[bool] = []  # non-empty when this run records durations (pytest_configure)


def pytest_configure(config: pytest.Config) -> None:
    if config.getoption("--record-durations", None):
        _RECORDING.append(True)
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0"))
    if hasattr(config, "workerinput") and workers > 1:
        # a worker's share of the cores for its in-process torch work (the workers run at once;
        # more threads than cores only wait on each other). Subprocesses keep their own count.
        import torch

        torch.set_num_threads(max(1, (os.cpu_count() or 1) // workers))


def _write_durations(config: pytest.Config) -> None:
    """``--record-durations PATH``: this run's times, written atomically, two decimals, sorted. A
    whole-suite run (no paths, ``-k`` or ``-m``) replaces the file, so tests that no longer exist
    leave it; a partial run's times are merged over the file's entries for the tests it ran."""
    target = config.getoption("--record-durations", None)
    if not target or hasattr(config, "workerinput") or not _TIMES:
        return
    import json

    from traffictwin.io.atomic import write_text_atomic

    path = Path(target)
    merged = {} if whole_suite(config) else recorded_durations(path)
    merged.update({k: round(v, 2) for k, v in _TIMES.items()})
    write_text_atomic(path, json.dumps(merged, indent=0, sort_keys=True) + "\n")


@pytest.hookimpl(wrapper=True)
def pytest_runtest_call(item: pytest.Item):
    """Every test under ``tests/reliability/`` runs under a time limit (``tests/_time_limit.py``):
    a hang fails that test with the limit named."""
    from _time_limit import limit_for, time_limit

    if "reliability" not in item.path.relative_to(ROOT).parts:
        return (yield)
    seconds = limit_for({m.name for m in item.iter_markers()})
    with time_limit(seconds, what=item.nodeid):
        return (yield)
