"""The pure promotion decision: Gate and decide with plain numbers (no MLflow, no models)."""

from __future__ import annotations

import pytest

from traffictwin.mlops import gate as gm
from traffictwin.mlops.gate import Gate, GateError, Version

# ------------------------------------------------------------------ Gate: metric comparison and margin


def test_gate_min_and_max_with_margin():
    g = Gate("test/kld", "min", 0.1)
    assert g.passes(0.5, 0.7)  # 0.2 better > 0.1
    assert not g.passes(0.65, 0.7)  # 0.05 better <= margin
    assert not g.passes(0.6, 0.7 - 1e-12) or g.improvement(0.6, 0.7) > 0.1
    assert not g.passes(0.8, 0.7)  # worse
    assert g.improvement(0.5, 0.7) == pytest.approx(0.2)
    h = Gate("test/acc", "max", 0.0)
    assert h.passes(0.91, 0.90) and not h.passes(0.90, 0.90) and not h.passes(0.8, 0.9)


def test_gate_nonfinite_and_first():
    g = Gate("m", "min", 0.0)
    assert g.passes(1.0, None)  # no champion yet
    assert not g.passes(float("nan"), 1.0)  # NaN challenger never wins
    assert not g.passes(float("inf"), None)
    assert g.passes(1.0, float("nan"))  # broken champion figure is beaten


@pytest.mark.parametrize(
    "kw", [dict(margin=-0.1), dict(margin=float("nan")), dict(mode="lower"), dict(metric="")]
)
def test_gate_rejects_bad_config(kw):
    args = dict(metric="m", mode="min", margin=0.0) | kw
    with pytest.raises(ValueError):
        Gate(**args)


# ------------------------------------------------------------------ decide


def _figures(**by_uri: float):
    """An evaluate() that returns a fixed figure per model URI and counts its calls."""
    calls: list[str] = []

    def evaluate(uri: str) -> dict[str, float]:
        calls.append(uri)
        if isinstance(by_uri[uri], Exception):
            raise by_uri[uri]
        return {"test/kld": by_uri[uri], "test/n": 10.0}

    return evaluate, calls


G = Gate("test/kld", "min", 0.01)
V1, V2 = Version("1", "m1", "run1"), Version("2", "m2", "run2")


def test_first_model_becomes_champion():
    ev, calls = _figures(m2=0.5)
    d = gm.decide("M", V2, None, ev, G, test_fingerprint="fp")
    assert (d.action, d.promotes, d.challenger_value, d.champion_value) == (
        "first",
        True,
        0.5,
        None,
    )
    assert calls == ["m2"] and d.test_fingerprint == "fp" and d.challenger_run_id == "run2"
    ev, _ = _figures(m2=float("nan"))
    d = gm.decide("M", V2, None, ev, G)
    assert d.action == "rejected" and not d.promotes and "not finite" in d.reason


@pytest.mark.parametrize(
    "challenger, champion, action",
    [(0.50, 0.70, "promoted"), (0.695, 0.70, "rejected"), (0.80, 0.70, "rejected")],
)
def test_better_by_more_than_margin_promotes(challenger, champion, action):
    ev, calls = _figures(m2=challenger, m1=champion)
    d = gm.decide("M", V2, V1, ev, G)
    assert d.action == action and calls == ["m2", "m1"]  # both measured by the same callable
    assert (d.challenger_value, d.champion_value, d.champion_version) == (challenger, champion, "1")
    assert d.challenger_metrics["test/n"] == 10.0 and d.champion_metrics["test/kld"] == champion
    assert ("improvement" in d.reason) and (">" if action == "promoted" else "<=") in d.reason


def test_max_mode_compare():
    better, why = gm.compare(Gate("test/acc", "max", 0.0), 0.91, 0.90)
    assert better and "higher is better" in why
    better, why = gm.compare(Gate("test/acc", "max", 0.0), 0.5, float("nan"))
    assert better and "no finite figure for the champion" in why and "nan >" not in why


@pytest.mark.parametrize(
    "error", [FileNotFoundError("model.ckpt"), ValueError("boom"), GateError("no metric")]
)
def test_unevaluable_champion_stops_the_gate(error):
    """A champion that fails to load or evaluate (maybe transiently) is never replaced on it."""
    ev, calls = _figures(m2=1.67, m1=error)
    with pytest.raises(gm.ChampionEvaluationError) as exc:
        gm.decide("M", V2, V1, ev, G)
    msg = str(exc.value)
    assert "M: champion v1 could not be evaluated" in msg and "champion kept" in msg
    assert type(error).__name__ in msg and "\n" not in msg
    assert calls == ["m2", "m1"]


def test_known_incompatible_champion_is_skipped_and_reason_kept():
    ev, _ = _figures(m2=0.9, m1=gm.IncompatibleModelError("trained on a 128x88 grid,\nnot 64x48"))
    d = gm.decide("M", V2, V1, ev, G)
    assert d.action == "promoted" and d.promotes and d.champion_value is None
    assert d.champion_version == "1" and d.challenger_value == 0.9
    assert d.champion_incompatible == "trained on a 128x88 grid, not 64x48"  # one line
    assert "champion v1 skipped, known-incompatible (trained on a 128x88" in d.reason
    assert d.to_dict()["champion_incompatible"] == d.champion_incompatible
    ev, _ = _figures(m2=float("nan"), m1=gm.IncompatibleModelError("old grid"))
    d = gm.decide("M", V2, V1, ev, G)
    assert d.action == "rejected" and d.champion_incompatible == "old grid"


def test_unchanged_when_already_champion_or_already_decided():
    ev, calls = _figures(m1=0.1, m2=0.2)
    assert gm.decide("M", V1, V1, ev, G).action == "unchanged"
    decided = Version(
        "2",
        "m2",
        "run2",
        {"gate.decision": "rejected", "gate.champion_version": "1", "gate.test_fingerprint": "fp"},
    )
    d = gm.decide("M", decided, V1, ev, G, test_fingerprint="fp")
    assert d.action == "unchanged" and "(rejected)" in d.reason and calls == []
    assert gm.already_decided(decided, V1, "fp") and not gm.already_decided(decided, V1, "other")
    assert not gm.already_decided(decided, Version("3", "m3"), "fp")
    assert gm.decide("M", decided, V1, ev, G, test_fingerprint="other").action == "rejected"
    assert (
        gm.decide("M", decided, V1, ev, G, test_fingerprint="fp", force=True).action == "rejected"
    )


def test_missing_metric_is_a_gate_error():
    with pytest.raises(GateError, match="no metric 'test/kld'.*test/other"):
        gm.decide("M", V2, None, lambda uri: {"test/other": 1.0}, G)
    assert gm.metric_value({"a": 1}, "a", "x") == 1.0


def test_decision_to_dict_is_the_log_record():
    ev, _ = _figures(m2=0.5)
    rec = gm.decide("M", V2, None, ev, G).to_dict()
    assert rec["event"] == "promotion" and rec["action"] == "first" and rec["time"].endswith("Z")
