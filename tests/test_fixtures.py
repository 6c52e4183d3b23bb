"""The shared test fixtures' own contracts: what lets the ``ci_dag`` readers run beside its
copiers and beside tests with their own MLflow store under pytest-xdist."""

from __future__ import annotations

import os
import sqlite3
from pathlib import Path

import conftest
import pytest
from conftest import _run_order, builds_ci_dag_early, copy_dag, mlflow_uris_kept


def test_copy_dag_leaves_dvc_tmp_and_on_request_the_mlflow_store_behind(tmp_path: Path) -> None:
    src = tmp_path / "src"
    for rel in (
        ".dvc/config",
        ".dvc/tmp/lock",
        ".dvc/cache/files/md5/ab/cd",
        "data/tmp/x.npz",
        "mlartifacts/1/a.txt",
        "dvc.lock",
    ):
        (src / rel).parent.mkdir(parents=True, exist_ok=True)
        (src / rel).write_text(rel)
    sqlite3.connect(src / "mlflow.db").close()  # an empty SQLite store
    full = copy_dag(src, tmp_path / "full")
    assert not (full / ".dvc" / "tmp").exists()
    for rel in (".dvc/config", ".dvc/cache/files/md5/ab/cd", "data/tmp/x.npz"):
        assert (full / rel).read_text() == rel  # only the top .dvc/tmp is left behind
    assert (full / "mlflow.db").exists() and (full / "mlartifacts/1/a.txt").exists()
    bare = copy_dag(src, tmp_path / "bare", mlflow=False)
    assert not (bare / "mlflow.db").exists() and not (bare / "mlartifacts").exists()
    assert (bare / "dvc.lock").exists() and (bare / ".dvc/cache/files/md5/ab/cd").exists()


def test_mlflow_uris_kept_undoes_set_tracking_and_registry_uri(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import mlflow

    mine = f"sqlite:///{tmp_path / 'mine.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", mine)
    monkeypatch.delenv("MLFLOW_REGISTRY_URI", raising=False)
    with mlflow_uris_kept():
        other = f"sqlite:///{tmp_path / 'shared.db'}"
        mlflow.set_tracking_uri(other)  # exports MLFLOW_TRACKING_URI too
        mlflow.set_registry_uri(other)  # exports MLFLOW_REGISTRY_URI too
        assert mlflow.get_tracking_uri() == other
    assert mlflow.get_tracking_uri() == mine
    assert mlflow.get_registry_uri() == mine
    assert os.environ["MLFLOW_TRACKING_URI"] == mine
    assert "MLFLOW_REGISTRY_URI" not in os.environ


def test_copy_dag_points_the_copied_mlflow_store_at_its_own_artifacts(tmp_path: Path) -> None:
    """A stage run in a copy logs beside the copy's store: the copied store's artifact locations
    name the copy, not the source's artifacts (which other tests read meanwhile)."""
    import mlflow

    src = tmp_path / "src"
    src.mkdir()
    with mlflow_uris_kept():
        mlflow.set_tracking_uri(f"sqlite:///{src / 'mlflow.db'}")
        exp = mlflow.create_experiment("fusion", artifact_location=(src / "mlartifacts").as_uri())
        with mlflow.start_run(experiment_id=exp) as run:
            mlflow.log_text("weights", "checkpoints/model.txt")
    dest = copy_dag(src, tmp_path / "dest")
    client = mlflow.MlflowClient(tracking_uri=f"sqlite:///{dest / 'mlflow.db'}")
    got = client.get_run(run.info.run_id).info.artifact_uri
    assert got == (dest / "mlartifacts" / run.info.run_id / "artifacts").as_uri()
    assert client.get_experiment(exp).artifact_location == (dest / "mlartifacts").as_uri()
    # the source store is untouched
    source = mlflow.MlflowClient(tracking_uri=f"sqlite:///{src / 'mlflow.db'}")
    assert source.get_run(run.info.run_id).info.artifact_uri.startswith(src.as_uri())


def _config(
    worker: bool = False, n: int | None = 2, args=pytest.Config.ArgsSource.TESTPATHS, **opt
):
    from types import SimpleNamespace

    option = SimpleNamespace(
        numprocesses=n, markexpr=opt.get("m", ""), keyword=opt.get("k", ""), collectonly=False
    )
    cfg = SimpleNamespace(option=option, args_source=args)
    if worker:
        cfg.workerinput = {}
    return cfg


def test_only_a_whole_parallel_suite_builds_the_ci_dag_early() -> None:
    """`make test` (xdist, no paths, no -k / -m) starts the ci DAG at once on the controller; a
    worker, a serial run, chosen paths and `make test-fast`'s -m never do."""
    assert builds_ci_dag_early(_config())
    assert not builds_ci_dag_early(_config(worker=True))
    assert not builds_ci_dag_early(_config(n=None))
    assert not builds_ci_dag_early(_config(args=pytest.Config.ArgsSource.ARGS))
    assert not builds_ci_dag_early(_config(m="not slow and not integration"))
    assert not builds_ci_dag_early(_config(k="report"))


def test_tests_waiting_for_the_ci_dag_run_last_the_longest_first() -> None:
    from types import SimpleNamespace

    def item(nodeid: str, dag: bool):
        return SimpleNamespace(nodeid=nodeid, fixturenames=["ci_dag"] if dag else [])

    items = [
        item("tests/test_a.py::test_unit", False),
        item("tests/test_b.py::test_on_dag", True),
        item("tests/test_readme.py::test_readme_ci_blocks_run_as_written", True),
        item("tests/test_retrain.py::test_retrain_end_to_end_lock_and_failure_restore", False),
    ]
    got = [i.nodeid.split("::")[1] for i in sorted(items, key=_run_order)]
    assert got == [
        "test_retrain_end_to_end_lock_and_failure_restore",
        "test_unit",
        "test_readme_ci_blocks_run_as_written",
        "test_on_dag",
    ]


def _items(*specs: tuple[str, list[str]]):
    from types import SimpleNamespace

    def item(nodeid: str, fixtures: list[str]):
        it = SimpleNamespace(nodeid=nodeid, fixturenames=fixtures, marks=[])
        it.add_marker = lambda mark: it.marks.append(mark.name)
        return it

    return [item(n, f) for n, f in specs]


def test_long_tests_are_marked_from_the_recorded_durations(tmp_path, monkeypatch) -> None:
    """A test whose recorded time reaches LONG_S is `long` (make test-fast leaves it out); a
    quicker one or one not recorded yet is not; the fixture rules still mark slow and
    integration tests."""
    durations = tmp_path / "durations.json"
    durations.write_text(
        '{"tests/t.py::test_slowish": 0.5, "tests/t.py::test_quick": 0.49, "tests/t.py::test_dag": 9}'
    )
    monkeypatch.setattr(conftest, "DURATIONS", durations)
    items = _items(
        ("tests/t.py::test_slowish", []),
        ("tests/t.py::test_quick", []),
        ("tests/t.py::test_new", []),
        ("tests/t.py::test_dag", ["ci_dag"]),
        ("tests/t.py::test_db", ["mlflow_uri"]),
    )
    conftest.pytest_collection_modifyitems(None, items)
    marks = {i.nodeid.split("::")[1]: i.marks for i in items}
    assert marks == {
        "test_slowish": ["long"],
        "test_quick": [],
        "test_new": [],
        "test_dag": ["slow", "long"],
        "test_db": ["integration"],
    }


def test_recorded_durations_add_the_phases_and_keep_earlier_entries(tmp_path, monkeypatch) -> None:
    """--record-durations: setup + call + teardown of each test of this run; a partial run (paths,
    -k or -m) merges them over the file's entries for tests it did not run, a whole run replaces
    the file (a removed test leaves it); without the option nothing is recorded; a bad file is
    named."""
    from types import SimpleNamespace

    out = tmp_path / "durations.json"
    earlier = '{"tests/t.py::test_other": 3.0, "tests/t.py::test_a": 9.0}'
    monkeypatch.setattr(conftest, "_TIMES", {})
    monkeypatch.setattr(conftest, "_RECORDING", [])
    report = SimpleNamespace(nodeid="tests/t.py::test_a", when="call", duration=5.0)
    conftest.pytest_runtest_logreport(report)
    assert conftest._TIMES == {}  # not recording: nothing kept
    monkeypatch.setattr(conftest, "_RECORDING", [True])
    for phase, seconds in (("setup", 0.25), ("call", 1.0), ("teardown", 0.004)):
        conftest.pytest_runtest_logreport(
            SimpleNamespace(nodeid="tests/t.py::test_a", when=phase, duration=seconds)
        )

    def config(source: pytest.Config.ArgsSource, markexpr: str = "") -> SimpleNamespace:
        return SimpleNamespace(
            getoption=lambda name, default=None: str(out),
            args_source=source,
            option=SimpleNamespace(markexpr=markexpr, keyword=""),
        )

    for partial in (config(pytest.Config.ArgsSource.ARGS), config(None, markexpr="not slow")):
        out.write_text(earlier)
        conftest._write_durations(partial)
        assert conftest.recorded_durations(out) == {
            "tests/t.py::test_a": 1.25,
            "tests/t.py::test_other": 3.0,
        }
    out.write_text(earlier)
    conftest._write_durations(config(pytest.Config.ArgsSource.TESTPATHS))
    assert conftest.recorded_durations(out) == {"tests/t.py::test_a": 1.25}
    out.write_text('["not", "an object"]')
    with pytest.raises(pytest.UsageError, match="durations.json: expected a JSON object"):
        conftest.recorded_durations(out)


def test_the_committed_durations_file_is_well_formed() -> None:
    """tests/durations.json is a JSON object of node ids under tests/ and seconds >= 0."""
    recorded = conftest.recorded_durations()
    assert recorded, "tests/durations.json is missing or empty: record it (docs/testing.md)"
    assert all(k.startswith("tests/") and "::" in k for k in recorded)
    assert all(v >= 0 for v in recorded.values())
