"""MLflow Model Registry adapter: versions, aliases, champion history, apply/rollback, log.

Names (DESIGN.md "Tracking"): ``traffictwin-fusion-<cfg>`` and ``traffictwin-risk``; aliases
``champion`` and ``challenger`` (lowercase). The decision itself is pure and lives in
:mod:`traffictwin.mlops.gate`; this module looks up what it needs in the registry and applies it:

1. :func:`ensure_version` registers a trained model (its MLflow run's logged model) as a new
   version of its registered model (a run that is already registered reuses its version, so
   re-running promotion after a no-op ``dvc repro`` registers nothing new).
2. :func:`decide` reads the current ``champion`` and the challenger's ``gate.*`` tags and calls
   :func:`traffictwin.mlops.gate.decide`, which re-evaluates both versions on the same test set.
3. :func:`apply` records the decision on the challenger's version as ``gate.*`` tags and as one
   JSON line in the promotion log, points ``challenger`` at the newest candidate and moves
   ``champion`` if the decision promotes. Old versions stay registered.

:func:`rollback` moves ``champion`` back to the previous champion (a stack kept in the
registered model's ``traffictwin.champion_history`` tag) or to an explicit version. The
promotion log a model's decisions go to is kept in its ``traffictwin.promotion_log`` tag, so a
rollback from the command line logs to the same file without knowing the project layout.

This module takes explicit arguments only (never params.yaml).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from traffictwin.io.atomic import write_text_atomic
from traffictwin.mlops import gate as _gate
from traffictwin.mlops.gate import Decision, Evaluator, Gate, GateError

__all__ = [
    "Decision",
    "Gate",
    "GateError",
    "RegistryError",
]  # re-exported for callers of the adapter

CHAMPION = "champion"
CHALLENGER = "challenger"
HISTORY_TAG = "traffictwin.champion_history"
HISTORY_MAX = 100
LOG_TAG = "traffictwin.promotion_log"
FUSION_PREFIX = "traffictwin-fusion"
RISK_NAME = "traffictwin-risk"


class RegistryError(GateError):
    """A registry operation cannot be done (missing model, alias, version or run)."""


def fusion_name(cfg: str, prefix: str = FUSION_PREFIX) -> str:
    """Registered-model name of fusion configuration ``cfg`` (``<prefix>-<cfg>``)."""
    return f"{prefix}-{cfg}"


def registered_names(cl, prefix: str = "") -> list[str]:
    """Names of the registered models that start with ``prefix`` (sorted)."""
    return sorted(m.name for m in cl.search_registered_models() if m.name.startswith(prefix))


def client(uri: str | None = None):
    """An ``MlflowClient`` on ``uri`` (default: :func:`traffictwin.mlops.tracking.tracking_uri`).

    Also points the fluent API (model loading, registration) at the same URI.
    """
    import mlflow
    from mlflow import MlflowClient

    from traffictwin.mlops.tracking import tracking_uri

    uri = uri or tracking_uri()
    mlflow.set_tracking_uri(uri)
    mlflow.set_registry_uri(uri)
    return MlflowClient(tracking_uri=uri, registry_uri=uri)


def version_uri(name: str, version: str | int) -> str:
    return f"models:/{name}/{version}"


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
        hint = (
            f"registered models: {', '.join(known)}"
            if known
            else "no models are registered yet (run the promotion gate: `python -m pipelines.promote`)"
        )
        raise RegistryError(f"model '{name}' has no version with alias '{alias}' ({hint})")
    return mv


def _registered_names(cl) -> list[str]:
    try:
        return registered_names(cl)
    except Exception:  # noqa: BLE001 - only for an error message
        return []


def ensure_version(
    cl, name: str, run_id: str, model_uri: str | None = None, tags: Mapping[str, Any] | None = None
):
    """The model version of ``name`` registered from ``run_id``; registers it if there is none.

    ``model_uri``: the logged model to register (default ``runs:/<run_id>/model``).
    Raises :class:`RegistryError` if the run does not exist.
    """
    import mlflow
    from mlflow.exceptions import MlflowException

    try:
        cl.get_run(run_id)
    except MlflowException:
        raise RegistryError(
            f"MLflow run '{run_id}' (for model '{name}') not found at {mlflow.get_tracking_uri()}"
        ) from None
    try:
        existing = cl.search_model_versions(f"name='{name}' and run_id='{run_id}'")
    except MlflowException:
        existing = []
    if existing:
        return max(existing, key=lambda v: int(v.version))
    try:
        cl.get_registered_model(name)
    except MlflowException:
        cl.create_registered_model(
            name,
            description=f"traffictwin model '{name}' (promotion gate: traffictwin.mlops.registry)",
        )
    try:
        mv = mlflow.register_model(
            model_uri or f"runs:/{run_id}/model",
            name,
            tags={k: str(v) for k, v in (tags or {}).items()},
        )
    except MlflowException as exc:
        raise RegistryError(
            f"cannot register run '{run_id}' as '{name}' from {model_uri or f'runs:/{run_id}/model'}: {exc}"
        ) from None
    return cl.get_model_version(name, mv.version)


def load_registered(uri: str):
    """Load an MLflow PyTorch model (``models:/name/version`` or ``models:/name@alias``) on CPU, eval mode."""
    import mlflow.pytorch

    model = mlflow.pytorch.load_model(uri, map_location="cpu")
    return model.eval()


def _version(name: str, mv) -> _gate.Version:
    return _gate.Version(
        version=str(mv.version),
        uri=version_uri(name, mv.version),
        run_id=mv.run_id or "",
        tags=dict(mv.tags or {}),
    )


def decide(
    cl,
    name: str,
    challenger,
    evaluate: Evaluator,
    gate: Gate,
    *,
    test_fingerprint: str = "",
    champion_alias: str = CHAMPION,
    force: bool = False,
) -> Decision:
    """:func:`traffictwin.mlops.gate.decide` for ``challenger`` (a ModelVersion) against ``name@champion``.

    Nothing in the registry changes here (see :func:`apply`). Raises :class:`RegistryError` if
    the evaluation has no figure for the gate's metric.
    """
    champ = get_alias(cl, name, champion_alias)
    try:
        return _gate.decide(
            name,
            _version(name, challenger),
            None if champ is None else _version(name, champ),
            evaluate,
            gate,
            test_fingerprint=test_fingerprint,
            force=force,
        )
    except RegistryError:
        raise
    except GateError as exc:
        raise RegistryError(str(exc)) from None


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
        cl.set_registered_model_tag(name, LOG_TAG, str(Path(log_path).resolve()))
        append_log(log_path, decision.to_dict())


def promotion_log(cl, name: str) -> Path | None:
    """The promotion log recorded for ``name`` by :func:`apply` (``None`` if none was recorded)."""
    try:
        tags = cl.get_registered_model(name).tags or {}
    except Exception:  # noqa: BLE001
        return None
    return Path(tags[LOG_TAG]) if tags.get(LOG_TAG) else None


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
        raise RegistryError(
            f"no registered model '{name}'"
            + (f" (registered: {', '.join(known)})" if known else "")
        ) from None
    current = get_alias(cl, name, champion_alias)
    cur = str(current.version) if current is not None else None
    hist = champion_history(cl, name)
    if version is None:
        while hist and hist[-1] == cur:
            hist.pop()
        if not hist:
            raise RegistryError(
                f"model '{name}': no previous champion to roll back to (current champion: v{cur}); "
                f"pass --version"
            )
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
        "event": "rollback",
        "name": name,
        "from_version": cur,
        "to_version": target,
        "timestamp": now,
        "time": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(now)),
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
    line = json.dumps(_finite(dict(record)), sort_keys=True, default=_json_default, allow_nan=False)
    write_text_atomic(path, old + line + "\n")


def _finite(obj: Any) -> Any:
    """Non-finite floats -> None, recursively (strict JSON lines)."""
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(float(obj)) else None
    return obj


def read_log(path: str | Path) -> list[dict[str, Any]]:
    """All records of a promotion log (empty if it does not exist)."""
    path = Path(path)
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def _json_default(o: Any) -> Any:
    return o.item() if isinstance(o, np.generic) else str(o)


def status(
    cl, names: Sequence[str], champion_alias: str = CHAMPION, challenger_alias: str = CHALLENGER
) -> list[dict[str, Any]]:
    """Champion/challenger version and their last recorded figures for each registered model."""
    rows = []
    for n in names:
        row: dict[str, Any] = {"name": n}
        for alias in (champion_alias, challenger_alias):
            mv = get_alias(cl, n, alias)
            row[alias] = (
                None
                if mv is None
                else {
                    "version": str(mv.version),
                    "run_id": mv.run_id,
                    "value": (mv.tags or {}).get("gate.challenger_value"),
                    "decision": (mv.tags or {}).get("gate.decision"),
                }
            )
        row["history"] = champion_history(cl, n)
        rows.append(row)
    return rows
