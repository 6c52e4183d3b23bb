"""Registering trained models as registry versions, and retiring versions of an interrupted run.

:func:`ensure_version` registers a trained model (its MLflow run's logged model, of the
:mod:`traffictwin.mlops.model_artifact` flavour) as a new version of its registered model (a run
that is already registered reuses its version). The artifact files are checked against the
SHA-256 recorded when they were logged, and the record is copied onto the version as the tag
``traffictwin.sha256``. :func:`latest_versions` / :func:`retire_versions_after` undo the
registrations of a promotion that was rolled back. Part of the :mod:`traffictwin.mlops.registry`
adapter (which re-exports the public names).
"""

from __future__ import annotations

import json
import logging
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from traffictwin.mlops import model_artifact as art
from traffictwin.mlops.errors import RegistryError
from traffictwin.mlops.uris import mask_uri

log = logging.getLogger("traffictwin.registry")

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


@dataclass(frozen=True)
class PlannedVersion:
    """A candidate that a dry run would register: not in the registry; ``uri`` is its logged
    model (``models:/<model_id>``, loaded with its own SHA-256 record)."""

    name: str
    run_id: str
    uri: str
    tags: Mapping[str, str] = field(default_factory=dict)
    version: str = "(new)"


def _versions_of_run(cl, name: str, run_id: str) -> list:
    """The versions of ``name`` registered from ``run_id`` (empty if none or the model is absent);
    RegistryError naming the run and the (masked) tracking URI if the run does not exist."""
    import mlflow
    from mlflow.exceptions import MlflowException

    try:
        cl.get_run(run_id)
    except MlflowException:
        raise RegistryError(
            f"MLflow run '{run_id}' (for model '{name}') not found at {mask_uri(mlflow.get_tracking_uri())}"
        ) from None
    try:
        return list(cl.search_model_versions(f"name='{name}' and run_id='{run_id}'"))
    except MlflowException:
        return []


def planned_version(
    cl, name: str, run_id: str, model_uri: str | None = None, tags: Mapping[str, Any] | None = None
):
    """What :func:`ensure_version` would return, without changing the registry: the version
    registered from ``run_id`` if there is one, else a :class:`PlannedVersion` of the run's
    logged model, its files checked against their SHA-256 record (read only)."""
    existing = _versions_of_run(cl, name, run_id)
    if existing:
        return max(existing, key=lambda v: int(v.version))
    model_id = _run_model_id(cl, run_id, model_uri)
    _sealed_record(cl, model_id, f"run '{run_id}' (model '{name}')")
    return PlannedVersion(
        name, run_id, f"models:/{model_id}", {k: str(v) for k, v in (tags or {}).items()}
    )


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
    from mlflow.exceptions import MlflowException
    from mlflow.utils.mlflow_tags import MLFLOW_MODEL_VERSIONS

    existing = _versions_of_run(cl, name, run_id)
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
