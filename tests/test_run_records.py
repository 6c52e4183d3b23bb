"""Run records (reports/timings/<stage>.json): what differs between identical runs of a stage
(wall time, MLflow run id, throughput) is written there, never into a DVC output."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from types import SimpleNamespace

import pytest
import yaml

from pipelines import _common, _paths

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def timings(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setattr(_paths, "TIMINGS", tmp_path / "timings")
    return tmp_path / "timings"


def test_run_record_file_names_the_stage() -> None:
    assert _paths.run_record_file("train_fusion@A") == _paths.TIMINGS / "train_fusion-A.json"
    assert _paths.run_record_file("report") == _paths.REPORTS / "timings" / "report.json"


def test_stage_timer_writes_what_the_stage_recorded(timings: Path) -> None:
    with _common.stage_timer("train_risk@headline") as record:
        assert record == {}
        record.update(run_id="abc", train_seconds=1.5, stage="not this", seconds=-1)
    got = json.loads((timings / "train_risk-headline.json").read_text())
    # stage and seconds are the timer's own: a stage cannot overwrite them
    assert set(got) == {
        "run_id",
        "train_seconds",
        "stage",
        "seconds",
        "machine",
        "started",
        "finished",
    }
    assert got["started"] <= got["finished"] and got["started"].endswith("Z")
    # the machine, so a wall time can be judged: CPU, cores, load average at start and end
    assert set(got["machine"]) == {"cpu", "cpu_count", "load_start", "load_end"}
    assert got["machine"]["cpu_count"] >= 1 and got["machine"]["cpu"]
    for k in ("load_start", "load_end"):
        assert got["machine"][k] is None or (len(got["machine"][k]) == 3)
    assert (got["run_id"], got["train_seconds"], got["stage"]) == (
        "abc",
        1.5,
        "train_risk@headline",
    )
    assert got["seconds"] >= 0
    assert _common.read_run_record("train_risk@headline") == got


def test_a_failed_stage_leaves_the_previous_record(timings: Path) -> None:
    with _common.stage_timer("disparity") as record:
        record["ms_per_frame"] = 2.0
    before = (timings / "disparity.json").read_bytes()
    with pytest.raises(RuntimeError, match="boom"):
        with _common.stage_timer("disparity") as record:
            record["ms_per_frame"] = 99.0
            raise RuntimeError("boom")
    assert (timings / "disparity.json").read_bytes() == before
    with pytest.raises(RuntimeError):
        with _common.stage_timer("orb_filter"):
            raise RuntimeError("boom")
    assert not (timings / "orb_filter.json").exists()


def test_read_run_record_missing_and_bad_files(timings: Path) -> None:
    assert _common.read_run_record("train_fusion@B") == {}  # never ran: no record
    timings.mkdir()
    (timings / "train_fusion-B.json").write_text("{")
    with pytest.raises(ValueError, match=r"train_fusion-B\.json: run record is not valid JSON"):
        _common.read_run_record("train_fusion@B")
    (timings / "train_fusion-B.json").write_text("[1, 2]")
    with pytest.raises(ValueError, match=r"train_fusion-B\.json: run record must be a JSON object"):
        _common.read_run_record("train_fusion@B")


def test_training_record_from_fit_results(tmp_path: Path) -> None:
    ckpt = tmp_path / "model.ckpt"
    ckpt.write_bytes(b"weights")
    sha = hashlib.sha256(b"weights").hexdigest()
    fusion = SimpleNamespace(
        run_id="r1", model_uri="models:/m-1", train_seconds=12.345, samples_per_s=3.5
    )
    assert _common.training_record(fusion, ckpt) == {
        "run_id": "r1",
        "model_uri": "models:/m-1",
        "train_seconds": 12.35,  # hundredths, as every timing here
        "train_samples_per_s": 3.5,
        "model_sha256": sha,
    }
    # the risk trainer's result names its wall time `seconds`; no tracking: no run
    risk = SimpleNamespace(run_id=None, model_uri=None, seconds=2.0)
    assert _common.training_record(risk, ckpt) == {
        "run_id": None,
        "model_uri": None,
        "train_seconds": 2.0,
        "model_sha256": sha,
    }


def _paths_of(entries) -> list[str]:
    out = []
    for e in entries or []:
        out.append(next(iter(e)) if isinstance(e, dict) else str(e))
    return out


def test_run_records_are_never_dvc_outputs_or_dependencies() -> None:
    """A record inside a DVC output or dependency would put timings back into dvc.lock."""
    stages = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]
    for name, st in stages.items():
        st = st.get("do", st)
        for kind in ("deps", "outs", "metrics", "plots"):
            for p in _paths_of(st.get(kind)):
                p = p.strip().rstrip("/")
                assert p not in ("reports", "reports/timings"), (name, kind, p)
                assert not p.startswith("reports/timings/"), (name, kind, p)
