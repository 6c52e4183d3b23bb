"""MLflow Model Registry: challenger/champion quality gate, decision log, rollback.

Names (DESIGN.md "Tracking"): ``traffictwin-fusion-<cfg>`` and ``traffictwin-risk``; aliases
``champion`` and ``challenger`` (lowercase).

Promotion protocol (:func:`decide` then :func:`apply`):

1. The newly trained model (its MLflow run's logged model) is registered as a new version of
   its registered model (:func:`ensure_version`; a run that is already registered reuses its
   version, so re-running promotion after a no-op ``dvc repro`` registers nothing new).
2. Both the challenger and the version behind ``champion`` are **re-evaluated** on the same
   fixed held-out test set (the test split of the current data) by one ``evaluate`` callable
   that uses the evaluation stages' metric code. Stored figures are never compared across
   versions: a stored figure may come from a different test set (a retrain draws new data)
   or older metric code. The test-set fingerprint (dataset manifest hash + split) is recorded
   with every decision so that the figures can be traced to the data they were measured on.
3. ``champion`` moves to the challenger only if it is better by more than ``margin`` on the
   configured metric (:class:`Gate`); the first version of a model becomes champion.
   ``challenger`` always points to the newest candidate. Old versions stay registered.
4. Every decision is recorded on the challenger's model version as ``gate.*`` tags and as
   one JSON line in the promotion log, with both figures.

:func:`rollback` moves ``champion`` back to the previous champion (a stack kept in the
registered model's ``traffictwin.champion_history`` tag) or to an explicit version.

This module takes explicit arguments only (never params.yaml).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Literal, Mapping, Sequence

from .io.atomic import write_text_atomic

CHAMPION = "champion"
CHALLENGER = "challenger"
HISTORY_TAG = "traffictwin.champion_history"
HISTORY_MAX = 100
FUSION_PREFIX = "traffictwin-fusion"
RISK_NAME = "traffictwin-risk"

Action = Literal["first", "promoted", "rejected", "unchanged"]


class RegistryError(RuntimeError):
    """A registry operation cannot be done (missing model, alias, version or run)."""


def fusion_name(cfg: str, prefix: str = FUSION_PREFIX) -> str:
    """Registered-model name of fusion configuration ``cfg`` (e.g. ``traffictwin-fusion-D``)."""
    return f"{prefix}-{cfg}"


# --------------------------------------------------------------------------- gate (pure)


@dataclass(frozen=True)
class Gate:
    """Quality gate on one metric.

    ``metric``: key in the evaluation result (e.g. ``test/kld``); ``mode``: ``min`` (lower is
    better) or ``max``; ``margin``: absolute improvement (in the metric's units) the
    challenger must exceed to replace the champion (``>= 0``).
    """

    metric: str
    mode: Literal["min", "max"] = "min"
    margin: float = 0.0

    def __post_init__(self) -> None:
        if self.mode not in ("min", "max"):
            raise ValueError(f"gate mode must be 'min' or 'max', got {self.mode!r}")
        if not (isinstance(self.margin, (int, float)) and math.isfinite(self.margin) and self.margin >= 0):
            raise ValueError(f"gate margin must be a finite number >= 0, got {self.margin!r}")
        if not self.metric:
            raise ValueError("gate metric must be a non-empty metric name")

    def improvement(self, challenger: float, champion: float) -> float:
        """How much better the challenger is (positive = better), in metric units."""
        return (champion - challenger) if self.mode == "min" else (challenger - champion)

    def passes(self, challenger: float, champion: float | None) -> bool:
        """True if ``challenger`` should replace ``champion`` (``None``: no champion yet).

        A non-finite challenger figure never passes; a non-finite champion figure is beaten
        by any finite challenger.
        """
        if not math.isfinite(challenger):
            return False
        if champion is None or not math.isfinite(champion):
            return True
        return self.improvement(challenger, champion) > self.margin


# --------------------------------------------------------------------------- decisions


@dataclass
class Decision:
    """One gate decision (JSON-serialisable via :meth:`to_dict`)."""

    name: str
    challenger_version: str
    challenger_run_id: str
    champion_version: str | None
    metric: str
    mode: str
    margin: float
    challenger_value: float | None
    champion_value: float | None
    action: Action
    reason: str
    test_fingerprint: str = ""
    challenger_metrics: dict[str, float] = field(default_factory=dict)
    champion_metrics: dict[str, float] = field(default_factory=dict)
    timestamp: float = field(default_factory=time.time)

    @property
    def promotes(self) -> bool:
        return self.action in ("first", "promoted")

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["event"] = "promotion"
        d["time"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(self.timestamp))
        return d


def client(uri: str | None = None):
    """An ``MlflowClient`` on ``uri`` (default: :func:`traffictwin.tracking.tracking_uri`).

    Also points the fluent API (model loading, registration) at the same URI.
    """
    import mlflow
    from mlflow import MlflowClient

    from .tracking import tracking_uri

    uri = uri or tracking_uri()
    mlflow.set_tracking_uri(uri)
    mlflow.set_registry_uri(uri)
    return MlflowClient(tracking_uri=uri, registry_uri=uri)


def version_uri(name: str, version: str | int) -> str:
    return f"models:/{name}/{version}"


def alias_uri(name: str, alias: str) -> str:
    return f"models:/{name}@{alias}"


def get_alias(cl, name: str, alias: str):
    """The model version behind ``name@alias``, or ``None`` if the model or alias does not exist."""
    from mlflow.exceptions import MlflowException

    try:
        return cl.get_model_version_by_alias(name, alias)
    except MlflowException:
        return None


def require_alias(cl, name: str, alias: str):
    """Like :func:`get_alias` but raises :class:`RegistryError` naming the model and alias."""
    mv = get_alias(cl, name, alias)
    if mv is None:
        known = _registered_names(cl)
        hint = f"registered models: {', '.join(known)}" if known else "no models are registered yet (run `traffictwin promote`)"
        raise RegistryError(f"model '{name}' has no version with alias '{alias}' ({hint})")
    return mv


def _registered_names(cl) -> list[str]:
    try:
        return sorted(m.name for m in cl.search_registered_models())
    except Exception:  # noqa: BLE001 - only for an error message
        return []


def ensure_version(cl, name: str, run_id: str, model_uri: str | None = None, tags: Mapping[str, Any] | None = None):
    """The model version of ``name`` registered from ``run_id``; registers it if there is none.

    ``model_uri``: the logged model to register (default ``runs:/<run_id>/model``).
    Raises :class:`RegistryError` if the run does not exist.
    """
    import mlflow
    from mlflow.exceptions import MlflowException

    try:
        cl.get_run(run_id)
    except MlflowException:
        raise RegistryError(f"MLflow run '{run_id}' (for model '{name}') not found at {mlflow.get_tracking_uri()}") from None
    try:
        existing = cl.search_model_versions(f"name='{name}' and run_id='{run_id}'")
    except MlflowException:
        existing = []
    if existing:
        return max(existing, key=lambda v: int(v.version))
    try:
        cl.get_registered_model(name)
    except MlflowException:
        cl.create_registered_model(name, description=f"traffictwin model '{name}' (promotion gate: traffictwin.registry)")
    try:
        mv = mlflow.register_model(model_uri or f"runs:/{run_id}/model", name, tags={k: str(v) for k, v in (tags or {}).items()})
    except MlflowException as exc:
        raise RegistryError(f"cannot register run '{run_id}' as '{name}' from {model_uri or f'runs:/{run_id}/model'}: {exc}") from None
    return cl.get_model_version(name, mv.version)


def _metric(result: Mapping[str, float], metric: str, who: str) -> float:
    if metric not in result:
        raise RegistryError(f"evaluation of {who} returned no metric '{metric}' (got {sorted(result)})")
    return float(result[metric])


def decide(
    cl,
    name: str,
    challenger,
    evaluate: Callable[[str], Mapping[str, float]],
    gate: Gate,
    *,
    test_fingerprint: str = "",
    champion_alias: str = CHAMPION,
    force: bool = False,
) -> Decision:
    """Evaluate ``challenger`` (a ModelVersion) and the current champion with ``evaluate``; decide.

    ``evaluate(model_uri) -> {metric: value}`` must load the model and score it on the fixed
    held-out test set; it is called for both versions so their figures are comparable.
    Nothing in the registry changes here (see :func:`apply`). A challenger already decided
    against the same champion on the same test set is not re-evaluated (``unchanged``) unless
    ``force``.
    """
    champ = get_alias(cl, name, champion_alias)
    common = dict(
        name=name, challenger_version=str(challenger.version), challenger_run_id=challenger.run_id or "",
        metric=gate.metric, mode=gate.mode, margin=float(gate.margin), test_fingerprint=test_fingerprint,
    )
    if champ is not None and str(champ.version) == str(challenger.version):
        return Decision(**common, champion_version=str(champ.version), challenger_value=None, champion_value=None,
                        action="unchanged", reason="challenger is already the champion")
    tags = challenger.tags or {}
    if (not force and "gate.decision" in tags and champ is not None
            and tags.get("gate.champion_version") == str(champ.version)
            and tags.get("gate.test_fingerprint", "") == test_fingerprint):
        return Decision(**common, champion_version=str(champ.version), challenger_value=None, champion_value=None,
                        action="unchanged",
                        reason=f"already decided against champion v{champ.version} on this test set "
                               f"({tags['gate.decision']})")
    ch_metrics = {k: float(v) for k, v in evaluate(version_uri(name, challenger.version)).items()}
    ch_val = _metric(ch_metrics, gate.metric, f"{name} v{challenger.version}")
    if champ is None:
        ok = math.isfinite(ch_val)
        return Decision(**common, champion_version=None, challenger_value=ch_val, champion_value=None,
                        action="first" if ok else "rejected",
                        reason="no champion yet: first model becomes champion" if ok else f"{gate.metric} is not finite",
                        challenger_metrics=ch_metrics)
    cp_metrics = {k: float(v) for k, v in evaluate(version_uri(name, champ.version)).items()}
    cp_val = _metric(cp_metrics, gate.metric, f"{name} v{champ.version} (champion)")
    better = gate.passes(ch_val, cp_val)
    word = "lower" if gate.mode == "min" else "higher"
    imp = gate.improvement(ch_val, cp_val) if math.isfinite(ch_val) and math.isfinite(cp_val) else float("nan")
    reason = (f"{gate.metric}: challenger {ch_val:.6g} vs champion {cp_val:.6g} ({word} is better; "
              f"improvement {imp:.3g} {'>' if better else '<='} margin {gate.margin:g})")
    return Decision(**common, champion_version=str(champ.version), challenger_value=ch_val, champion_value=cp_val,
                    action="promoted" if better else "rejected", reason=reason,
                    challenger_metrics=ch_metrics, champion_metrics=cp_metrics)


def champion_history(cl, name: str) -> list[str]:
    """Versions that became champion, oldest first (the rollback stack)."""
    try:
        tags = cl.get_registered_model(name).tags or {}
    except Exception:  # noqa: BLE001
        return []
    try:
        hist = json.loads(tags.get(HISTORY_TAG, "[]"))
    except json.JSONDecodeError:
        return []
    return [str(v) for v in hist]


def _set_history(cl, name: str, hist: Sequence[str]) -> None:
    cl.set_registered_model_tag(name, HISTORY_TAG, json.dumps(list(hist)[-HISTORY_MAX:]))


def apply(
    cl,
    decision: Decision,
    *,
    log_path: str | Path | None = None,
    champion_alias: str = CHAMPION,
    challenger_alias: str = CHALLENGER,
) -> None:
    """Record ``decision`` (tags + log line), set ``challenger``, and move ``champion`` if it promotes.

    An ``unchanged`` decision changes nothing and is not logged.
    """
    if decision.action == "unchanged":
        return
    name, ver = decision.name, decision.challenger_version
    tags = {
        "gate.decision": decision.action,
        "gate.metric": decision.metric,
        "gate.mode": decision.mode,
        "gate.margin": repr(decision.margin),
        "gate.challenger_value": repr(decision.challenger_value),
        "gate.champion_value": repr(decision.champion_value),
        "gate.champion_version": str(decision.champion_version or ""),
        "gate.test_fingerprint": decision.test_fingerprint,
        "gate.reason": decision.reason[:4000],
        "gate.time": decision.to_dict()["time"],
    }
    for k, v in tags.items():
        cl.set_model_version_tag(name, ver, k, v)
    cl.set_registered_model_alias(name, challenger_alias, ver)
    if decision.promotes:
        cl.set_registered_model_alias(name, champion_alias, ver)
        _set_history(cl, name, [*champion_history(cl, name), ver])
    if log_path is not None:
        append_log(log_path, decision.to_dict())


def rollback(
    cl,
    name: str,
    version: str | int | None = None,
    *,
    log_path: str | Path | None = None,
    champion_alias: str = CHAMPION,
) -> dict[str, Any]:
    """Move ``champion`` of ``name`` back: to ``version`` if given, else to the previous champion.

    Without ``version`` the current champion is popped off the history stack, so repeated
    rollbacks walk further back. Returns the logged record. Raises :class:`RegistryError` if the
    model, version or a previous champion does not exist.
    """
    from mlflow.exceptions import MlflowException

    try:
        cl.get_registered_model(name)
    except MlflowException:
        known = _registered_names(cl)
        raise RegistryError(f"no registered model '{name}'" + (f" (registered: {', '.join(known)})" if known else "")) from None
    current = get_alias(cl, name, champion_alias)
    cur = str(current.version) if current is not None else None
    hist = champion_history(cl, name)
    if version is None:
        while hist and hist[-1] == cur:
            hist.pop()
        if not hist:
            raise RegistryError(f"model '{name}': no previous champion to roll back to (current champion: v{cur}); "
                                f"pass --version")
        target = hist[-1]
    else:
        target = str(version)
        try:
            cl.get_model_version(name, target)
        except MlflowException:
            raise RegistryError(f"model '{name}' has no version {target}") from None
        hist.append(target)
    cl.set_registered_model_alias(name, champion_alias, target)
    _set_history(cl, name, hist)
    now = time.time()
    cl.set_model_version_tag(name, target, "gate.rollback_from", str(cur or ""))
    record = {
        "event": "rollback", "name": name, "from_version": cur, "to_version": target,
        "timestamp": now, "time": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(now)),
    }
    if log_path is not None:
        append_log(log_path, record)
    return record


def append_log(path: str | Path, record: Mapping[str, Any]) -> None:
    """Append one JSON line to ``path`` (the whole file is rewritten atomically)."""
    path = Path(path)
    old = path.read_text() if path.exists() else ""
    if old and not old.endswith("\n"):
        old += "\n"
    write_text_atomic(path, old + json.dumps(dict(record), sort_keys=True, default=_json_default) + "\n")


def read_log(path: str | Path) -> list[dict[str, Any]]:
    """All records of a promotion log (empty if it does not exist)."""
    path = Path(path)
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def _json_default(o: Any) -> Any:
    try:
        import numpy as np

        if isinstance(o, np.generic):
            return o.item()
    except ImportError:  # pragma: no cover
        pass
    return str(o)


def status(cl, names: Sequence[str], champion_alias: str = CHAMPION, challenger_alias: str = CHALLENGER) -> list[dict[str, Any]]:
    """Champion/challenger version and their last recorded figures for each registered model."""
    rows = []
    for n in names:
        row: dict[str, Any] = {"name": n}
        for alias in (champion_alias, challenger_alias):
            mv = get_alias(cl, n, alias)
            row[alias] = None if mv is None else {
                "version": str(mv.version), "run_id": mv.run_id,
                "value": (mv.tags or {}).get("gate.challenger_value"), "decision": (mv.tags or {}).get("gate.decision"),
            }
        row["history"] = champion_history(cl, n)
        rows.append(row)
    return rows
