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

This module takes explicit arguments only (never params.yaml).
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import logging
import os
import socket
import tempfile
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TypeVar
from urllib.parse import unquote, urlparse

import numpy as np

from traffictwin.io.atomic import write_text_atomic
from traffictwin.io.jsonio import json_clean
from traffictwin.mlops import gate as _gate
from traffictwin.mlops import model_artifact as art
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

__all__ = [
    "ChampionEvaluationError",
    "Decision",
    "Gate",
    "GateError",
    "IncompatibleModelError",
    "LegacyModelError",
    "ModelArtifactError",
    "RegistryError",
    "TamperedArtifactError",
]  # re-exported for callers of the adapter

log = logging.getLogger("traffictwin.registry")
T = TypeVar("T")

CHAMPION = "champion"
CHALLENGER = "challenger"
HISTORY_TAG = "traffictwin.champion_history"
HISTORY_MAX = 100
LOG_TAG = "traffictwin.promotion_log"
# one registered model per task (conf/registry/base.yaml holds the same names)
FUSION_NAME = "traffictwin-fusion"
REGISTRATION_NAME = "traffictwin-registration"
RISK_NAME = "traffictwin-risk"


class RegistryError(GateError):
    """A registry operation cannot be done (missing model, alias, version or run)."""


class ChampionChangedError(RegistryError):
    """The champion alias moved between a decision and its application."""


class LockTimeoutError(RegistryError):
    """The registry lock was not acquired in time."""


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


ORPHAN_TAG = "traffictwin.orphan"


def latest_versions(cl, names: Sequence[str]) -> dict[str, int]:
    """The highest version number of each registered model in ``names`` (0: none yet)."""
    from mlflow.exceptions import MlflowException

    out: dict[str, int] = {}
    for n in names:
        try:
            vs = cl.search_model_versions(f"name='{n}'")
        except MlflowException:
            vs = []
        out[n] = max((int(v.version) for v in vs), default=0)
    return out


def retire_versions_after(cl, before: Mapping[str, int], reason: str) -> list[str]:
    """Versions registered after ``before`` (:func:`latest_versions` of an interrupted promotion):
    deleted when no alias points at them, else tagged :data:`ORPHAN_TAG` with ``reason``. Their
    files belong to outputs that were rolled back. Returns ``name vN`` of each, with what was done."""
    done: list[str] = []
    for name, last in before.items():
        newer = [
            mv for mv in cl.search_model_versions(f"name='{name}'") if int(mv.version) > int(last)
        ]
        for mv in sorted(newer, key=lambda m: int(m.version)):
            full = cl.get_model_version(name, mv.version)
            if getattr(full, "aliases", None):
                cl.set_model_version_tag(name, mv.version, ORPHAN_TAG, reason)
                done.append(f"{name} v{mv.version} tagged orphan (aliases {list(full.aliases)})")
            else:
                cl.delete_model_version(name, mv.version)
                done.append(f"{name} v{mv.version} deleted")
        if int(last) == 0 and newer and not cl.search_model_versions(f"name='{name}'"):
            cl.delete_registered_model(name)  # created by the interrupted promotion, now empty
    return done


def ensure_version(
    cl, name: str, run_id: str, model_uri: str | None = None, tags: Mapping[str, Any] | None = None
):
    """The model version of ``name`` registered from ``run_id``; registers it if there is none.

    ``model_uri``: the logged model to register (default: the run's logged model ``model``).
    The artifact is checked against the SHA-256 recorded when it was logged, and the record is
    set on the version (tag ``traffictwin.sha256``; an existing version without it gets it now).
    Raises :class:`RegistryError` if the run does not exist or its model cannot be registered
    safely (a pickled ``mlflow.pytorch`` model, files that changed since logging).

    The registered model is created here when absent and the version with
    ``MlflowClient.create_model_version``, not ``mlflow.register_model``: that one tries to create
    the registered model every time and prints "Registered model '<name>' already exists" to
    stderr for each version. What it adds beyond the version, the logged model's
    ``mlflow.modelVersions`` tag (the UI's link from the logged model), is set here too. One log
    line per model created and per version registered.
    """
    import mlflow
    from mlflow.exceptions import MlflowException
    from mlflow.utils.mlflow_tags import MLFLOW_MODEL_VERSIONS

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
        mv = max(existing, key=lambda v: int(v.version))
        if art.SHA_TAG not in (mv.tags or {}):
            model_id = _logged_model_id(mv.source)
            record = _sealed_record(cl, model_id, f"model '{name}' v{mv.version}")
            cl.set_model_version_tag(name, str(mv.version), art.SHA_TAG, art.encode_hashes(record))
            mv = cl.get_model_version(name, str(mv.version))
        return mv
    model_id = _run_model_id(cl, run_id, model_uri)
    record = _sealed_record(cl, model_id, f"run '{run_id}' (model '{name}')")
    try:
        cl.get_registered_model(name)
    except MlflowException:
        cl.create_registered_model(
            name,
            description=f"traffictwin model '{name}' (promotion gate: traffictwin.mlops.registry)",
        )
        log.info("registered model '%s' created", name)
    all_tags = {k: str(v) for k, v in (tags or {}).items()}
    all_tags[art.SHA_TAG] = art.encode_hashes(record)
    try:
        # the run id comes from the logged model (as mlflow.register_model leaves it)
        mv = cl.create_model_version(name, f"models:/{model_id}", tags=all_tags, model_id=model_id)
    except MlflowException as exc:
        raise RegistryError(
            f"cannot register run '{run_id}' as '{name}' from models:/{model_id}: {exc}"
        ) from None
    try:
        linked = json.loads(
            (cl.get_logged_model(model_id).tags or {}).get(MLFLOW_MODEL_VERSIONS, "[]")
        )
        linked = [*linked, {"name": mv.name, "version": mv.version}]
        cl.set_logged_model_tags(model_id, {MLFLOW_MODEL_VERSIONS: json.dumps(linked)})
    except (MlflowException, ValueError, TypeError) as exc:  # only the UI's back link is missing
        log.warning(
            "model '%s' v%s: logged model %s not linked back (%s)", name, mv.version, model_id, exc
        )
    log.info("model '%s': version %s registered from run %s", name, mv.version, run_id)
    return cl.get_model_version(name, mv.version)


def _logged_model_id(source: str | None) -> str:
    """The logged-model id of a version's ``source`` (``models:/m-…``); error for other sources."""
    src = str(source or "")
    if src.startswith("models:/") and "/" not in src[len("models:/") :]:
        return src[len("models:/") :]
    raise RegistryError(
        f"model source '{src}' is not a logged model (models:/<model_id>); re-register it from "
        "a run logged by this version of traffictwin"
    )


def _run_model_id(cl, run_id: str, model_uri: str | None) -> str:
    """The logged model to register: ``model_uri`` (``models:/m-…`` or ``runs:/<run>/<name>``),
    else the run's logged model named ``model``."""
    if model_uri and model_uri.startswith("models:/"):
        return _logged_model_id(model_uri)
    want = "model"
    if model_uri and model_uri.startswith("runs:/"):
        want = model_uri[len("runs:/") :].split("/", 1)[-1] or want
    outputs = getattr(cl.get_run(run_id), "outputs", None)
    ids = [o.model_id for o in (getattr(outputs, "model_outputs", None) or [])]
    for mid in reversed(ids):
        if cl.get_logged_model(mid).name == want:
            return mid
    raise RegistryError(
        f"run '{run_id}' has no logged model '{want}' (a model logged before MLflow 3, or by "
        "another tool?); retrain it (`dvc repro -f` of its train stage)"
    )


def _sealed_record(cl, model_id: str, who: str) -> dict[str, str]:
    """The SHA-256 record of logged model ``model_id``, after checking its files against it."""
    lm = cl.get_logged_model(model_id)
    value = (lm.tags or {}).get(art.SHA_TAG)
    with tempfile.TemporaryDirectory(prefix="tt-register-") as tmp:
        folder = _download(cl, f"models:/{model_id}", tmp)
        if value is None:
            art.read_flavor(folder, who)  # LegacyModelError for a pickled model
            raise RegistryError(
                f"{who}: logged model {model_id} has no SHA-256 record (tag '{art.SHA_TAG}'); "
                "log it with traffictwin.trainer.log_model"
            )
        record = art.decode_hashes(value, who)
        art.verify(folder, record, who)
        art.read_flavor(folder, who)
    return record


def _download(cl, source: str, dst: str | Path) -> Path:
    """Download the model directory ``source`` (``models:/<model_id>`` or an artifact URI) with
    ``cl``'s tracking store into ``dst``."""
    import mlflow.artifacts

    if source.startswith("models:/"):
        source = cl.get_logged_model(_logged_model_id(source)).artifact_location
    return Path(
        mlflow.artifacts.download_artifacts(
            artifact_uri=source, dst_path=str(dst), tracking_uri=cl.tracking_uri
        )
    )


def parse_model_uri(uri: str) -> tuple[str, str | None, str | None]:
    """``(name, version, alias)`` of ``models:/name/version`` or ``models:/name@alias``;
    ``(model_id, None, None)`` for a logged model ``models:/m-…``."""
    if not uri.startswith("models:/"):
        raise RegistryError(
            f"{uri}: expected a registry URI models:/<name>/<version>, models:/<name>@<alias> "
            "or a logged model models:/<model_id>"
        )
    rest = uri[len("models:/") :].rstrip("/")
    if "@" in rest:
        name, alias = rest.rsplit("@", 1)
        return name, None, alias
    if "/" in rest:
        name, version = rest.rsplit("/", 1)
        return name, version, None
    return rest, None, None


def load_registered(
    uri: str,
    loader: Callable[[Path], T],
    *,
    check: Callable[[dict[str, Any]], str | None] | None = None,
    cl=None,
    cache: bool = False,
) -> T:
    """Load a registered model safely and return ``loader(folder)``.

    ``uri``: ``models:/name/version``, ``models:/name@alias`` or a logged model
    ``models:/m-…``. The model directory is downloaded to a temp folder and checked, in order:
    its files against the SHA-256 recorded on the version (on the logged model for
    ``models:/m-…``) — :class:`TamperedArtifactError` names the model, version and file; the
    ``traffictwin`` flavour — a pickled ``mlflow.pytorch`` model raises
    :class:`LegacyModelError`; then ``check(meta)`` on its ``model_meta.json``: a returned reason
    raises :class:`IncompatibleModelError`. Only then ``loader(folder)`` (a problem loader
    reading ``model.ckpt`` with ``weights_only=True``) builds the model. The temp folder is
    removed afterwards. ``cache`` (the CLI and API's interactive loads): a verified copy is kept
    under :func:`model_cache_root`, keyed by the SHA-256 record, and used (re-verified against
    the record) instead of a new download, so a registry load costs about what a folder load
    costs; the promotion gate never uses it (it checks the store itself). ``cl``: the client
    (default: one on the fluent API's current URIs).
    """
    if cl is None:
        from mlflow import MlflowClient

        cl = MlflowClient()  # the fluent API's tracking and registry URIs
    name, version, alias = parse_model_uri(uri)
    if version is None and alias is None:
        who = f"logged model {name}"
        source = uri
        value = (cl.get_logged_model(name).tags or {}).get(art.SHA_TAG)
    else:
        from mlflow.exceptions import MlflowException

        try:
            mv = (
                cl.get_model_version_by_alias(name, alias)
                if alias is not None
                else cl.get_model_version(name, version)
            )
        except MlflowException:
            raise RegistryError(f"{uri}: no such registered model version") from None
        who = f"model '{name}' v{mv.version}"
        source = mv.source
        value = (mv.tags or {}).get(art.SHA_TAG)
    cached = _cached_copy(value, who) if cache else None
    if cached is not None:  # a verified copy of exactly the recorded files: no download
        return _checked_load(cached, who, check, loader)
    with tempfile.TemporaryDirectory(prefix="tt-load-") as tmp:
        folder = _download(cl, source, tmp)
        if value is None:
            art.read_flavor(folder, who)  # a pickled mlflow.pytorch model: LegacyModelError
            raise ModelArtifactError(
                f"{who}: no SHA-256 recorded (tag '{art.SHA_TAG}'); refusing to load it — "
                "register it with `python -m pipelines.promote`"
            )
        art.verify(folder, art.decode_hashes(value, who), who)
        model = _checked_load(folder, who, check, loader)
        if cache:
            _keep_copy(folder, value)
        return model


#: where verified registry downloads are kept (``TRAFFICTWIN_MODEL_CACHE``; ``off``: no cache)
CACHE_ENV = "TRAFFICTWIN_MODEL_CACHE"


def model_cache_root() -> Path | None:
    """The folder of verified model copies (default ``~/.cache/traffictwin/models``), or None."""
    v = os.environ.get(CACHE_ENV)
    if v is not None and v.strip().lower() in ("", "off", "0", "false", "none"):
        return None
    if v:
        return Path(v)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "traffictwin" / "models"


def _cache_key(value: str) -> str:
    return hashlib.sha256(value.encode()).hexdigest()[:32]


def _cached_copy(value: str | None, who: str) -> Path | None:
    """The cached copy of the files recorded in ``value`` (the version's SHA-256 record), checked
    against the record now; None when there is none or it no longer matches (then removed)."""
    root = model_cache_root()
    if value is None or root is None:
        return None
    folder = root / _cache_key(value)
    if not folder.is_dir():
        return None
    try:
        art.verify(folder, art.decode_hashes(value, who), who)
    except Exception:  # noqa: BLE001 - an altered cache entry is dropped and downloaded again
        import shutil

        shutil.rmtree(folder, ignore_errors=True)
        return None
    return folder


def _keep_copy(folder: Path, value: str) -> None:
    """Keep a verified download for the next load (best effort: a full disk only costs speed)."""
    import shutil

    root = model_cache_root()
    if root is None:
        return
    dest = root / _cache_key(value)
    tmp = root / f".{dest.name}.{os.getpid()}.tmp"
    try:
        root.mkdir(parents=True, exist_ok=True)
        shutil.copytree(folder, tmp)
        os.replace(tmp, dest)
    except OSError:
        shutil.rmtree(tmp, ignore_errors=True)


def _checked_load(folder: Path, who: str, check, loader):
    art.read_flavor(folder, who)
    if check is not None:
        reason = check(art.read_meta(folder, who))
        if reason:
            raise IncompatibleModelError(f"{who}: {reason}")
    return loader(folder)


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


def default_lock_path(uri: str | None = None) -> Path:
    """The registry lock file of tracking/registry ``uri`` (default: the current one).

    SQLite: ``<database>.gate.lock`` beside the database; a local file store:
    ``<root>/.gate.lock``. A server URI has no shared folder: the lock is a file in the temp
    folder named after the URI, which serialises the gates of this machine only (pass a lock path
    on a shared file system to cover several machines).
    """
    if uri is None:
        from traffictwin.mlops.tracking import tracking_uri

        uri = tracking_uri()
    u = urlparse(uri)
    if uri.startswith("sqlite:///"):
        db = unquote(uri[len("sqlite:///") :]).split("?", 1)[0]
        if db and db != ":memory:":
            p = Path(db).resolve()
            return p.with_name(p.name + ".gate.lock")
    if u.scheme in ("", "file"):
        root = Path(unquote(u.path) if u.scheme == "file" else uri)
        return root.resolve() / ".gate.lock"
    key = hashlib.sha256(uri.encode()).hexdigest()[:16]
    return Path(tempfile.gettempdir()) / f"traffictwin-gate-{key}.lock"


@contextmanager
def gate_lock(
    path: str | Path, *, timeout_s: float | None = None, poll_s: float = 0.2
) -> Iterator[None]:
    """Hold the registry-wide exclusive lock (``fcntl.flock`` on ``path``) for the block.

    Waits for another holder (``timeout_s`` seconds at most; ``None``: as long as it takes,
    logging who holds it). The holder's pid, host and start time are written into the file for
    that message. Closing the file releases the lock, also when the process dies.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fh = open(path, "a+")  # noqa: SIM115 - held open for the whole block
    try:
        t0 = time.monotonic()
        told = False
        while True:
            try:
                fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if not told:
                    fh.seek(0)
                    holder = fh.read().strip() or "unknown holder"
                    log.info("registry lock %s is held (%s); waiting", path, holder)
                    told = True
                if timeout_s is not None and time.monotonic() - t0 >= timeout_s:
                    raise LockTimeoutError(
                        f"registry lock {path} still held after {timeout_s:g} s; not deciding"
                    ) from None
                time.sleep(poll_s)
        fh.seek(0)
        fh.truncate()
        fh.write(
            f"pid {os.getpid()} on {socket.gethostname()} since "
            f"{time.strftime('%Y-%m-%dT%H:%M:%S')}\n"
        )
        fh.flush()
        yield
    finally:
        fh.close()


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
