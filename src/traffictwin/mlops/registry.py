"""MLflow Model Registry adapter: versions, aliases, champion history, apply/rollback, log.

Names (docs/design.md "Tracking"): ``traffictwin-fusion``, ``traffictwin-registration`` and
``traffictwin-risk`` (one model per task); aliases
``champion`` and ``challenger`` (lowercase). The decision itself is pure and lives in
:mod:`traffictwin.mlops.gate`; this module looks up what it needs in the registry and applies it:

1. :func:`ensure_version` registers a trained model (its MLflow run's logged model, of the
   :mod:`traffictwin.mlops.model_artifact` flavour) as a new version of its registered model (a
   run that is already registered reuses its version, so re-running promotion after a no-op
   ``dvc repro`` registers nothing new). The artifact files are checked against the SHA-256
   recorded when they were logged, and the record is copied onto the version as the tag
   ``traffictwin.sha256``.
2. :func:`decide` reads the current ``champion`` and the challenger's ``gate.*`` tags and calls
   :func:`traffictwin.mlops.gate.decide`, which re-evaluates both versions on the same test set.
3. :func:`apply` re-reads ``champion`` and refuses (:class:`ChampionChangedError`) if it moved
   since the decision; else it records the decision on the challenger's version as ``gate.*``
   tags and as one JSON line in the promotion log, records a known-incompatible champion as
   ``gate.incompatible`` on that version, points ``challenger`` at the newest candidate and moves
   ``champion`` if the decision promotes. Old versions stay registered.

:func:`gate_lock` is the one registry-wide lock (``fcntl.flock`` on a file next to the SQLite
database, :func:`default_lock_path`) that a gate holds from its decisions to its last alias move,
and a rollback while it moves the alias: two gates run one after the other, and the second
decides against the champion the first left.

:func:`load_registered` is the only way a registered model is loaded: files checked against the
version's SHA-256 record first, then the caller's problem loader (``weights_only`` checkpoints);
nothing is unpickled, and a model logged as an ``mlflow.pytorch`` pickle is refused.

:func:`rollback` moves ``champion`` back to the previous champion (a stack kept in the
registered model's ``traffictwin.champion_history`` tag) or to an explicit version. The
promotion log a model's decisions go to is kept in its ``traffictwin.promotion_log`` tag, so a
rollback from the command line logs to the same file without knowing the project layout.

The adapter is this module and three beside it, whose public names it re-exports:
:mod:`~traffictwin.mlops.registry_versions` (1., registration),
:mod:`~traffictwin.mlops.registry_loading` (:func:`load_registered` and its cache) and
:mod:`~traffictwin.mlops.registry_lock` (:func:`gate_lock`); its errors are in
:mod:`traffictwin.mlops.errors`.

This module takes explicit arguments only (never params.yaml).
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from traffictwin.io.atomic import write_text_atomic
from traffictwin.io.jsonio import json_clean
from traffictwin.mlops import gate as _gate
from traffictwin.mlops.errors import ChampionChangedError, LockTimeoutError, RegistryError
from traffictwin.mlops.gate import (
    ChampionEvaluationError,
    Decision,
    Evaluator,
    Gate,
    GateError,
    IncompatibleModelError,
)
from traffictwin.mlops.model_artifact import (
    LegacyModelError,
    ModelArtifactError,
    TamperedArtifactError,
)
from traffictwin.mlops.registry_loading import (
    CACHE_ENV,
    load_registered,
    model_cache_root,
    parse_model_uri,
    split_model_reference,
)
from traffictwin.mlops.registry_lock import default_lock_path, gate_lock
from traffictwin.mlops.registry_versions import (
    ORPHAN_TAG,
    PlannedVersion,
    ensure_version,
    latest_versions,
    planned_version,
    retire_versions_after,
)
from traffictwin.mlops.stores import SQLITE_MAGIC

__all__ = [
    "CACHE_ENV",
    "ORPHAN_TAG",
    "ChampionChangedError",
    "ChampionEvaluationError",
    "Decision",
    "Gate",
    "GateError",
    "IncompatibleModelError",
    "LegacyModelError",
    "LockTimeoutError",
    "ModelArtifactError",
    "PlannedVersion",
    "RegistryError",
    "TamperedArtifactError",
    "default_lock_path",
    "ensure_version",
    "gate_lock",
    "latest_versions",
    "load_registered",
    "model_cache_root",
    "parse_model_uri",
    "planned_version",
    "retire_versions_after",
    "split_model_reference",
]  # defined in the adapter's other modules (errors, registry_*), re-exported for its callers

CHAMPION = "champion"
CHALLENGER = "challenger"
HISTORY_TAG = "traffictwin.champion_history"
HISTORY_MAX = 100
LOG_TAG = "traffictwin.promotion_log"
# one registered model per task (conf/registry/base.yaml holds the same names)
FUSION_NAME = "traffictwin-fusion"
REGISTRATION_NAME = "traffictwin-registration"
RISK_NAME = "traffictwin-risk"
STEREO_NAME = "traffictwin-stereo"


def registered_names(cl, prefix: str = "") -> list[str]:
    """Names of the registered models that start with ``prefix`` (sorted)."""
    return sorted(m.name for m in cl.search_registered_models() if m.name.startswith(prefix))


def client(uri: str | None = None):
    """An ``MlflowClient`` on ``uri`` (default: :func:`traffictwin.mlops.tracking.tracking_uri`).

    Also points the fluent API (model loading, registration) at the same URI.
    """
    import mlflow
    from mlflow import MlflowClient

    from traffictwin.mlops.stores import check_sqlite_store, sqlalchemy_uri
    from traffictwin.mlops.tracking import tracking_uri

    uri = uri or tracking_uri()
    try:
        check_sqlite_store(uri)
    except ValueError as exc:
        raise RegistryError(str(exc)) from None
    uri = sqlalchemy_uri(uri)  # ?mode=ro: read-only, as asked
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


def _version(name: str, mv) -> _gate.Version:
    planned = isinstance(mv, PlannedVersion)  # a dry run's unregistered candidate
    return _gate.Version(
        version=str(mv.version),
        uri=mv.uri if planned else version_uri(name, mv.version),
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
    the evaluation has no figure for the gate's metric, :class:`ChampionEvaluationError` if the
    champion cannot be evaluated (and is not known-incompatible).
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
    except (RegistryError, ChampionEvaluationError, IncompatibleModelError):
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

    First re-reads ``champion``: if it is no longer the version the decision was taken against,
    nothing changes and :class:`ChampionChangedError` is raised (decide again). A champion the
    decision skipped as known-incompatible gets the tag ``gate.incompatible`` (the reason). An
    ``unchanged`` decision changes nothing and is not logged. Hold :func:`gate_lock` around
    decide and apply.
    """
    if decision.action == "unchanged":
        return
    if log_path is not None:
        log_path = check_log_path(log_path, "promotion log")
    name, ver = decision.name, decision.challenger_version
    now = get_alias(cl, name, champion_alias)
    now_v = None if now is None else str(now.version)
    if now_v != (decision.champion_version or None):
        raise ChampionChangedError(
            f"model '{name}': champion moved from "
            f"{'v' + decision.champion_version if decision.champion_version else 'none'} to "
            f"{'v' + now_v if now_v else 'none'} since the decision on v{ver}; nothing applied"
        )
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
    if decision.champion_incompatible and decision.champion_version:
        cl.set_model_version_tag(
            name,
            decision.champion_version,
            "gate.incompatible",
            decision.champion_incompatible[:4000],
        )
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
    model, version or a previous champion does not exist, or ``log_path`` is no promotion log
    (:func:`check_log_path`) — always before the alias moves: a refused rollback changes nothing.
    """
    from mlflow.exceptions import MlflowException

    if log_path is not None:
        log_path = check_log_path(log_path)
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


#: files that mark a folder as a model folder (a log written there would sit in the model)
MODEL_FILES = ("model_meta.json", "model.ckpt", "MLmodel")


def check_log_path(path: str | Path, who: str = "--log") -> Path:
    """``path`` as a promotion log that :func:`append_log` may write, checked before any alias
    moves; :class:`RegistryError` (one line naming ``who`` and the path) otherwise.

    Refused: a path that exists and is not a regular file (folder, FIFO, device, socket,
    symlink), a SQLite database (the registry's own ``mlflow.db``), a file in a model folder
    (one holding ``model_meta.json``, ``model.ckpt`` or ``MLmodel``), an existing file that is
    not JSON lines, a path whose folder (or, if missing, nearest existing folder above it) is
    not a writable folder. Only ``lstat``, 16 bytes
    and (for an existing log) its lines are read: a FIFO is never opened.
    """
    import os
    import stat

    p = Path(path)
    try:
        st = os.lstat(p)
    except (FileNotFoundError, NotADirectoryError):
        st = None
    except OSError as exc:
        raise RegistryError(f"{who} {p}: cannot be examined ({exc.strerror})") from None
    if st is not None and not stat.S_ISREG(st.st_mode):
        kind = (
            "a symlink"
            if stat.S_ISLNK(st.st_mode)
            else "a folder"
            if stat.S_ISDIR(st.st_mode)
            else "a FIFO"
            if stat.S_ISFIFO(st.st_mode)
            else "a device, socket or other special file"
        )
        raise RegistryError(
            f"{who} {p}: is {kind}; expected a promotion log file (JSON lines) or a new file name"
        )
    parent = p.absolute().parent
    hits = [n for n in MODEL_FILES if (parent / n).exists()]
    if p.name in MODEL_FILES or hits:
        raise RegistryError(
            f"{who} {p}: lies in a model folder ({', '.join(hits) or p.name} there); a promotion "
            "log must not be written into a model: pass a file such as reports/promotions.jsonl"
        )
    base = parent  # the folder is created if missing: its nearest existing ancestor must do
    while not base.exists() and base != base.parent:
        base = base.parent
    if not base.is_dir():
        raise RegistryError(f"{who} {p}: {base} is not a folder")
    if not os.access(base, os.W_OK) or (st is not None and not os.access(p, os.W_OK)):
        raise RegistryError(f"{who} {p}: not writable")
    if st is not None and st.st_size:
        with open(p, "rb") as fh:
            head = fh.read(len(SQLITE_MAGIC))
        if head == SQLITE_MAGIC:
            raise RegistryError(
                f"{who} {p}: is a SQLite database (the registry?); expected a promotion log file"
            )
        try:
            read_log(p)
        except ValueError as exc:  # JSONDecodeError, UnicodeDecodeError, a non-object line
            raise RegistryError(
                f"{who} {p}: exists and is not a promotion log (JSON lines: {type(exc).__name__}); "
                "pass another file"
            ) from None
    return p


def append_log(path: str | Path, record: Mapping[str, Any]) -> None:
    """Append one JSON line to ``path`` (the whole file is rewritten atomically)."""
    path = Path(path)
    old = path.read_text() if path.exists() else ""
    if old and not old.endswith("\n"):
        old += "\n"
    line = json.dumps(
        json_clean(dict(record)), sort_keys=True, default=_json_default, allow_nan=False
    )
    write_text_atomic(path, old + line + "\n")


def read_log(path: str | Path) -> list[dict[str, Any]]:
    """All records of a promotion log (empty if it does not exist)."""
    path = Path(path)
    if not path.exists():
        return []
    records = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    if not all(isinstance(r, dict) for r in records):
        raise ValueError(f"{path}: a line is not a JSON object")
    return records


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
