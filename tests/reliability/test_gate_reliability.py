"""The promotion gate never leaves a worse champion.

- A champion that cannot be evaluated (a transient load error, a replaced file) stops the gate:
  error, champion kept, nothing applied. Only a champion known to be incompatible (recorded
  grid/architecture meta that does not fit, a pickled model of an older version) is skipped, and
  the reason is recorded on it and in the decision.
- Gates hold one registry-wide lock from their decisions to their alias moves: a second gate
  waits, then decides against the champion the first one left; a champion moved behind the
  lock's back between decision and apply makes the gate decide again.
"""

from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest
import torch
from _registry_models import load_linear, log_linear
from _tamper import artifact_dir

from pipelines import promote as pm
from traffictwin.mlops import model_artifact as art
from traffictwin.mlops import promotion
from traffictwin.mlops import registry as reg
from traffictwin.mlops.gate import Gate

NAME = "traffictwin-risk"
W_TRUE = np.array([[2.0, -1.0]], dtype=np.float32)
X = np.random.default_rng(0).normal(size=(64, 2)).astype(np.float32)
Y = X @ W_TRUE.T
GATE = Gate("test/mse", "min", 1e-4)
GRID = {"rows": 4, "cols": 4, "cell": 0.32}


def _mse(model) -> float:
    with torch.no_grad():
        return float(np.mean((model(torch.from_numpy(X)).numpy() - Y) ** 2))


def _grid_check(meta) -> str | None:
    g = meta.get("grid", GRID)
    return None if g == GRID else f"trained on grid {g}, the test set is {GRID}"


def evaluate(uri: str) -> dict[str, float]:
    """The gate's evaluator: checked load, then MSE on the fixed test set."""
    return {"test/mse": _mse(reg.load_registered(uri, load_linear, check=_grid_check))}


def _model_dir(tmp_path, key: str, error: float, grid=None):
    """A trained-model folder (model_meta.json) and its training run record (``_record``: its
    MLflow run) whose weights are off by ``error``."""
    run_id = log_linear(W_TRUE + error, meta={"grid": grid or GRID}, experiment="risk")
    d = tmp_path / "models" / key
    d.mkdir(parents=True)
    (d / "model_meta.json").write_text(json.dumps({"grid": grid or GRID}))
    _record(d).write_text(json.dumps({"run_id": run_id}))
    return d


def _record(model_dir):
    """The run record of the stage that trained ``model_dir`` (beside it, as reports/timings is)."""
    return model_dir.parent / f"{model_dir.name}.run.json"


def _job(model_dir, ev=evaluate) -> promotion.GateJob:
    return promotion.GateJob(NAME, GATE, model_dir, lambda cand: (ev, "fp"), _record(model_dir))


def _settings(tmp_path, **kw) -> promotion.PromotionSettings:
    return promotion.PromotionSettings(log_path=tmp_path / "promotions.jsonl", **kw)


def _champion(cl) -> str | None:
    mv = reg.get_alias(cl, NAME, "champion")
    return None if mv is None else str(mv.version)


def _first_champion(cl, tmp_path, error: float = 0.01) -> str:
    (d,) = promotion.promote([_job(_model_dir(tmp_path, "champ", error))], _settings(tmp_path))
    assert d.action == "first"
    return d.challenger_version


# ------------------------------------------------------------------ a champion that fails to load


@pytest.mark.parametrize("fault", ["transient FileNotFoundError", "artifact file deleted"])
def test_champion_that_fails_to_load_stops_the_gate_and_keeps_the_alias(cl, tmp_path, fault):
    """The reported case: champion MSE ~1e-4, challenger MSE ~1.7, the champion's load fails."""
    champ = _first_champion(cl, tmp_path, error=0.01)
    log_before = (tmp_path / "promotions.jsonl").read_text()
    champ_uri = reg.version_uri(NAME, champ)

    def flaky(uri: str) -> dict[str, float]:
        if uri == champ_uri:
            raise FileNotFoundError(f"[Errno 2] No such file or directory: '{uri}/model.ckpt'")
        return evaluate(uri)

    ev = evaluate
    if fault == "artifact file deleted":
        (artifact_dir(cl, NAME, champ) / art.CKPT).unlink()
    else:
        ev = flaky
    worse = _job(_model_dir(tmp_path, "worse", 1.3), ev)
    with pytest.raises(reg.ChampionEvaluationError) as exc:
        promotion.promote([worse], _settings(tmp_path))
    msg = str(exc.value)
    assert f"champion v{champ} could not be evaluated" in msg and "champion kept" in msg
    assert "\n" not in msg
    assert _champion(cl) == champ
    assert str(reg.get_alias(cl, NAME, "challenger").version) == champ  # challenger not moved
    challenger = cl.get_model_version(NAME, str(int(champ) + 1))
    assert not any(k.startswith("gate.") for k in challenger.tags)  # nothing recorded
    assert (tmp_path / "promotions.jsonl").read_text() == log_before


def test_promote_command_exits_1_with_one_line_when_the_champion_fails(
    cl, tmp_path, monkeypatch, capsys
):
    champ = _first_champion(cl, tmp_path)
    (artifact_dir(cl, NAME, champ) / art.CKPT).unlink()
    worse = _job(_model_dir(tmp_path, "worse", 1.3))
    monkeypatch.setattr(pm, "build_jobs", lambda cfg, rc: [worse])
    monkeypatch.setattr(pm, "settings", lambda rc, **kw: _settings(tmp_path, **kw))
    assert pm.main(["--only", NAME]) == 1
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("promote:")]
    assert len(err) == 1 and f"champion v{champ} could not be evaluated" in err[0]
    assert "artifact file model.ckpt is missing" in err[0] and "champion kept" in err[0]
    assert _champion(cl) == champ


def test_tampered_champion_stops_the_gate(cl, tmp_path):
    champ = _first_champion(cl, tmp_path)
    meta = artifact_dir(cl, NAME, champ) / art.META
    meta.write_text(meta.read_text() + " ")
    with pytest.raises(reg.ChampionEvaluationError, match="TamperedArtifactError"):
        promotion.promote([_job(_model_dir(tmp_path, "c", 0.5))], _settings(tmp_path))
    assert _champion(cl) == champ


# ------------------------------------------------------------------ known-incompatible champion


def test_known_incompatible_champion_is_recorded_and_skipped(cl, tmp_path):
    old = log_linear(W_TRUE, meta={"grid": {"rows": 8, "cols": 8, "cell": 0.32}}, experiment="r")
    v_old = reg.ensure_version(cl, NAME, old).version  # the champion of an earlier grid
    with pytest.raises(reg.IncompatibleModelError):
        evaluate(reg.version_uri(NAME, v_old))
    cl.set_registered_model_alias(NAME, "champion", v_old)
    (d,) = promotion.promote([_job(_model_dir(tmp_path, "new", 0.3))], _settings(tmp_path))
    assert d.action == "promoted" and d.champion_version == "1" and d.champion_value is None
    assert "trained on grid {'cell': 0.32, 'cols': 8" in d.champion_incompatible
    assert "champion v1 skipped, known-incompatible" in d.reason
    assert "skipped: model 'traffictwin-risk' v1: trained on grid" in promotion.format_decision(d)
    assert _champion(cl) == "2"
    tags = cl.get_model_version(NAME, "1").tags
    assert tags["gate.incompatible"] == d.champion_incompatible
    (rec,) = reg.read_log(tmp_path / "promotions.jsonl")
    assert rec["champion_incompatible"] == d.champion_incompatible


def test_legacy_pickled_champion_is_known_incompatible(cl, tmp_path):
    """A champion registered as an mlflow.pytorch pickle (older version) is never loaded; the
    gate records why and judges the challenger alone."""
    import mlflow

    mlflow.set_experiment("legacy")
    with mlflow.start_run() as run:
        mlflow.pytorch.log_model(
            torch.nn.Linear(2, 1), name="model", serialization_format="pickle", pip_requirements=[]
        )
    mv = mlflow.register_model(f"runs:/{run.info.run_id}/model", NAME)
    cl.set_registered_model_alias(NAME, "champion", mv.version)
    (d,) = promotion.promote([_job(_model_dir(tmp_path, "new", 0.3))], _settings(tmp_path))
    assert d.action == "promoted" and "pickled mlflow.pytorch" in d.champion_incompatible
    assert "pickled" in cl.get_model_version(NAME, mv.version).tags["gate.incompatible"]


# ------------------------------------------------------------------ concurrent gates


@pytest.mark.parametrize("better_first", [True, False])
def test_concurrent_gates_never_leave_a_worse_champion(cl, tmp_path, better_first):
    """Two gates at once (threads, one lock file): the second waits for the first to apply, then
    decides against the champion the first left. The reported case: champion 0.005, two
    challengers; the worse one's gate must not undo the better one's promotion."""
    _first_champion(cl, tmp_path, error=0.3)
    dirs = {"good": _model_dir(tmp_path, "good", 0.02), "bad": _model_dir(tmp_path, "bad", 0.2)}
    versions = {k: str(int("1") + i + 1) for i, k in enumerate(dirs)}  # registered in this order
    for k in dirs:  # register both up front (as two trainings would have logged them)
        reg.ensure_version(cl, NAME, json.loads(_record(dirs[k]).read_text())["run_id"])
    order = ["good", "bad"] if better_first else ["bad", "good"]
    events: list[tuple[str, str]] = []
    second_started = threading.Event()

    def evaluator(who: str):
        def ev(uri: str) -> dict[str, float]:
            events.append((who, uri))
            if who == order[0] and not second_started.is_set():
                # give the second gate every chance to run now; only the lock holds it back
                second_started.wait(5.0)
                time.sleep(0.3)
            return evaluate(uri)

        return ev

    results: dict[str, object] = {}

    def gate(who: str) -> None:
        try:
            (results[who],) = promotion.promote(
                [_job(dirs[who], evaluator(who))], _settings(tmp_path)
            )
        except Exception as exc:  # noqa: BLE001 - reported below
            results[who] = exc

    first = threading.Thread(target=gate, args=(order[0],))
    first.start()
    while not events:  # the first gate holds the lock and is evaluating
        time.sleep(0.01)
    second = threading.Thread(target=gate, args=(order[1],))
    second.start()
    second_started.set()
    first.join(60)
    second.join(60)
    assert not first.is_alive() and not second.is_alive()
    d1, d2 = results[order[0]], results[order[1]]
    assert not isinstance(d1, Exception) and not isinstance(d2, Exception), results
    # the second gate evaluated only after the first had applied: its champion is the first's
    # result, and none of its evaluations fell between the first's
    assert d1.champion_version == "1" and d1.action == "promoted"
    assert d2.champion_version == versions[order[0]]
    whos = [w for w, _ in events]
    assert whos == sorted(whos, key=order.index), events
    assert _champion(cl) == versions["good"]
    assert d2.action == ("rejected" if better_first else "promoted")
    assert reg.champion_history(cl, NAME)[-1] == versions["good"]


def test_champion_moved_between_decision_and_apply_is_decided_again(cl, tmp_path):
    """Someone moves the champion without the lock (a rollback, the MLflow UI) while the gate
    evaluates: apply sees it, and the gate decides again against the new champion."""
    _first_champion(cl, tmp_path, error=0.5)
    best = reg.ensure_version(cl, NAME, log_linear(W_TRUE + 0.001, experiment="risk"))
    moved = []

    def ev(uri: str) -> dict[str, float]:
        out = evaluate(uri)
        if not moved:
            cl.set_registered_model_alias(NAME, "champion", best.version)  # behind the gate's back
            moved.append(uri)
        return out

    (d,) = promotion.promote([_job(_model_dir(tmp_path, "mid", 0.1), ev)], _settings(tmp_path))
    assert d.champion_version == str(best.version) and d.action == "rejected"
    assert _champion(cl) == str(best.version)
    (rec,) = reg.read_log(tmp_path / "promotions.jsonl")[1:]
    assert rec["champion_version"] == str(best.version) and rec["action"] == "rejected"


def test_champion_that_keeps_moving_aborts_without_applying(cl, tmp_path):
    _first_champion(cl, tmp_path, error=0.5)
    others = [
        reg.ensure_version(cl, NAME, log_linear(W_TRUE + e, experiment="risk")).version
        for e in (0.4, 0.45)
    ]
    moves = iter(others)

    def ev(uri: str) -> dict[str, float]:
        out = evaluate(uri)
        if uri.endswith(f"/{int(others[-1]) + 1}"):  # after each evaluation of the challenger
            v = next(moves, None)
            if v is not None:
                cl.set_registered_model_alias(NAME, "champion", v)
        return out

    with pytest.raises(reg.ChampionChangedError, match="champion moved"):
        promotion.promote([_job(_model_dir(tmp_path, "c", 0.05), ev)], _settings(tmp_path))
    assert _champion(cl) == str(others[-1])  # the outsider's move, not the gate's
    assert len(reg.read_log(tmp_path / "promotions.jsonl")) == 1  # only the first champion


def test_apply_refuses_a_decision_taken_against_another_champion(cl, tmp_path):
    _first_champion(cl, tmp_path, error=0.5)
    mv = reg.ensure_version(cl, NAME, log_linear(W_TRUE + 0.1, experiment="risk"))
    d = reg.decide(cl, NAME, mv, evaluate, GATE)
    other = reg.ensure_version(cl, NAME, log_linear(W_TRUE + 0.3, experiment="risk"))
    cl.set_registered_model_alias(NAME, "champion", other.version)
    with pytest.raises(reg.ChampionChangedError, match=f"from v1 to v{other.version}"):
        reg.apply(cl, d)
    assert _champion(cl) == str(other.version)
    assert "gate.decision" not in cl.get_model_version(NAME, mv.version).tags


# ------------------------------------------------------------------ the lock itself


def test_gate_lock_excludes_and_times_out(tmp_path):
    path = tmp_path / "reg.gate.lock"
    with reg.gate_lock(path):
        assert "pid" in path.read_text()
        t0 = time.monotonic()
        with pytest.raises(reg.LockTimeoutError, match="still held after 0.3 s"):
            with reg.gate_lock(path, timeout_s=0.3, poll_s=0.05):
                pass
        assert time.monotonic() - t0 >= 0.3
    with reg.gate_lock(path, timeout_s=0.0):  # released on exit
        pass


def test_promote_waits_for_the_lock(cl, tmp_path):
    lock = tmp_path / "held.lock"
    settings = _settings(tmp_path, lock_path=lock, lock_timeout_s=0.3)
    job = _job(_model_dir(tmp_path, "a", 0.1))
    with reg.gate_lock(lock):
        with pytest.raises(reg.LockTimeoutError):
            promotion.promote([job], settings)
    assert reg.get_alias(cl, NAME, "champion") is None
    assert [d.action for d in promotion.promote([job], settings)] == ["first"]


def test_default_lock_path_is_next_to_the_registry(tmp_path):
    db = tmp_path / "x" / "mlflow.db"
    assert reg.default_lock_path(f"sqlite:///{db}") == db.with_name("mlflow.db.gate.lock")
    assert reg.default_lock_path(f"file://{tmp_path}/mlruns") == tmp_path / "mlruns" / ".gate.lock"
    a = reg.default_lock_path("http://tracking:5000")
    assert a == reg.default_lock_path("http://tracking:5000") != reg.default_lock_path("http://b")
