"""Registry operations are all-or-nothing: ``rollback`` and the promotion gate check every
argument (the promotion log: a regular file or absent, writable, not in a model folder, not a
database, not a folder, not a FIFO) before they move an alias, and ``--dry-run`` writes nothing
(no registration, no alias, no tag, no file).
"""

from __future__ import annotations

import json
import os
import sqlite3

import numpy as np
import pytest
from _registry_models import log_linear

from pipelines import promote as pm
from traffictwin import cli
from traffictwin.mlops import promotion
from traffictwin.mlops import registry as reg
from traffictwin.mlops.gate import Gate

NAME = "traffictwin-fusion-A"
GATE = Gate("test/w", "max", 0.0)


def _w(uri: str) -> dict[str, float]:
    """Evaluator: the figure is the model's weight, read back through the checked loader."""
    from _registry_models import load_linear

    m = reg.load_registered(uri, load_linear)
    return {"test/w": float(m.weight.detach().numpy().ravel()[0])}


def _two_champions(cl, log) -> None:
    """v1 then v2 promoted (the rollback stack holds both), logged to ``log``."""
    for w in (1.0, 2.0):
        mv = reg.ensure_version(cl, NAME, log_linear(w))
        reg.apply(cl, reg.decide(cl, NAME, mv, _w, GATE), log_path=log)
    assert str(reg.get_alias(cl, NAME, "champion").version) == "2"


def _bad_logs(tmp_path):
    model = tmp_path / "models" / "fusion" / "network"
    model.mkdir(parents=True)
    (model / "model_meta.json").write_text(json.dumps({"format": "x"}))
    db = tmp_path / "other.db"
    sqlite3.connect(db).execute("create table t (x)").connection.commit()
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    link = tmp_path / "link.jsonl"
    link.symlink_to(tmp_path / "promotions.jsonl")
    return {
        "model_meta": (model / "model_meta.json", "lies in a model folder"),
        "in_model": (model / "log.jsonl", "lies in a model folder"),
        "database": (db, "is a SQLite database"),
        "folder": (tmp_path, "is a folder"),
        "fifo": (fifo, "is a FIFO"),
        "symlink": (link, "is a symlink"),
        "not_jsonl": (tmp_path / "notes.txt", "is not a promotion log"),
        "under_a_file": (tmp_path / "notes.txt" / "log.jsonl", "is not a folder"),
    }


@pytest.mark.parametrize(
    "case",
    [
        "model_meta",
        "in_model",
        "database",
        "folder",
        "fifo",
        "symlink",
        "not_jsonl",
        "under_a_file",
    ],
)
def test_rollback_with_a_bad_log_moves_nothing(cl, tmp_path, capsys, case):
    log = tmp_path / "promotions.jsonl"
    _two_champions(cl, log)
    (tmp_path / "notes.txt").write_text("my notes\n")
    path, needle = _bad_logs(tmp_path)[case]
    before = {p: p.read_bytes() for p in (log, path) if p.is_file() and not p.is_symlink()}
    hist = reg.champion_history(cl, NAME)
    capsys.readouterr()
    for _ in range(2):  # a retry walks no further back
        assert cli.main(["rollback", "--model", NAME, "--log", str(path)]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and needle in err[0] and str(path) in err[0], err
        assert str(reg.get_alias(cl, NAME, "champion").version) == "2"
        assert reg.champion_history(cl, NAME) == hist
    for p, content in before.items():
        assert p.read_bytes() == content
    assert not (tmp_path / "models" / "fusion" / "network" / "log.jsonl").exists()
    # the same rollback with a good log works
    assert cli.main(["rollback", "--model", NAME, "--log", str(log)]) == 0
    assert str(reg.get_alias(cl, NAME, "champion").version) == "1"
    assert reg.read_log(log)[-1]["event"] == "rollback"


def _candidate(tmp_path, w: float):
    run_id = log_linear(w)
    d = tmp_path / "models" / f"m{w:g}"
    d.mkdir(parents=True)
    (d / "model_meta.json").write_text(json.dumps({"w": w}))
    rec = d.parent / f"{d.name}.run.json"
    rec.write_text(json.dumps({"run_id": run_id}))
    return promotion.GateJob(NAME, GATE, d, lambda cand: (_w, "fp"), rec)


def test_promote_with_a_bad_log_registers_and_moves_nothing(cl, tmp_path):
    job = _candidate(tmp_path, 1.0)
    settings = promotion.PromotionSettings(log_path=tmp_path, lock_path=tmp_path / "lock")
    with pytest.raises(reg.RegistryError) as info:
        promotion.promote([job], settings)
    msg = str(info.value)
    assert "promotion log" in msg and "is a folder" in msg and "\n" not in msg
    assert reg.registered_names(cl) == []  # nothing registered
    assert not (tmp_path / "lock").exists()


def test_dry_run_registers_nothing_and_writes_no_file(cl, tmp_path, monkeypatch, capsys):
    log, lock = tmp_path / "promotions.jsonl", tmp_path / "registry.lock"
    job = _candidate(tmp_path, 1.0)

    def settings(rc, **kw):
        return promotion.PromotionSettings(log_path=log, lock_path=lock, **kw)

    monkeypatch.setattr(pm, "build_jobs", lambda cfg, rc: [job])
    monkeypatch.setattr(pm, "settings", settings)
    files_before = sorted(p for p in tmp_path.rglob("*") if "mlruns" not in p.parts)
    assert pm.main(["--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "nothing applied" in out and "v(new)" in out and "no champion yet" in out, out
    assert reg.registered_names(cl) == []  # no registration
    assert not log.exists() and not lock.exists()
    files_after = sorted(p for p in tmp_path.rglob("*") if "mlruns" not in p.parts)
    assert files_after == files_before

    # a candidate already registered is decided as its version, and still nothing moves
    pm.main([])
    champ = str(reg.get_alias(cl, NAME, "champion").version)
    log_before = log.read_bytes()
    job2 = _candidate(tmp_path, 3.0)
    monkeypatch.setattr(pm, "build_jobs", lambda cfg, rc: [job2])
    assert pm.main(["--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "v(new)" in out and f"v{champ}" in out and "nothing applied" in out, out
    assert [str(v.version) for v in cl.search_model_versions(f"name='{NAME}'")] == [champ]
    assert str(reg.get_alias(cl, NAME, "champion").version) == champ
    assert log.read_bytes() == log_before
    assert np.isfinite(_w(reg.version_uri(NAME, champ))["test/w"])


def test_dry_run_creates_no_database(tmp_path, monkeypatch):
    db = tmp_path / "none.db"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{db}")
    with pytest.raises(reg.RegistryError, match="no MLflow database"):
        promotion.promote([], promotion.PromotionSettings(dry_run=True))
    assert not db.exists()
