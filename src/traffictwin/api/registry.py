"""Model registry access of the API: the tracking URI (never creating a database), one probe of
the registry, model references (``name@alias``, a bare alias, or a model folder) and loading a
registered model through the sealed-artifact loader."""

from __future__ import annotations

import os
from pathlib import Path

from .errors import ApiError

ALIASES = ("champion", "challenger")
#: MLflow HTTP client settings for interactive use: no retries, 5 s per request (MLflow's own
#: defaults retry for minutes against a dead server). The CLI sets them unless already set.
HTTP_ENV = {
    "MLFLOW_HTTP_REQUEST_MAX_RETRIES": "0",
    "MLFLOW_HTTP_REQUEST_TIMEOUT": "5",
    "MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR": "0",
    # no "Downloading artifacts" bar before a load's one-line result or error
    "MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR": "false",
}


def resolve_tracking_uri(tracking_uri: str | None = None) -> str:
    """The registry URI to use (see :mod:`traffictwin.api`, Registry); never creates a database.

    Raises :class:`ApiError` when no URI is given outside the project, or when a SQLite
    database (or a local file store) does not exist.
    """
    from traffictwin.mlops.stores import sqlite_path
    from traffictwin.mlops.tracking import ENV_URI, repo_root

    from .inputs import check_optional_text

    check_optional_text(tracking_uri, "tracking_uri")
    uri = tracking_uri or os.environ.get(ENV_URI)
    if not uri:
        root = repo_root()
        if not (root / "dvc.yaml").is_file():
            raise ApiError(
                "no model registry: pass --tracking-uri URI (or set MLFLOW_TRACKING_URI), run "
                f"inside the traffictwin project (its mlflow.db), or pass --model PATH of a model "
                f"folder ({Path.cwd()} is not in the project)"
            )
        uri = f"sqlite:///{root / 'mlflow.db'}"
    db = sqlite_path(uri)
    if db is not None and not db.is_file():
        raise ApiError(
            f"{uri}: no MLflow database at {db} (not creating one): run the pipeline and "
            "`python -m pipelines.promote` first, or pass --tracking-uri"
        )
    if uri.startswith(("file:", "/", "./", "../")):  # a local file store
        folder = Path(uri[len("file://") :] if uri.startswith("file://") else uri)
        if not folder.is_dir():
            raise ApiError(f"{uri}: no MLflow file store at {folder} (not creating one)")
    return uri


def _first_line(exc: BaseException, limit: int = 200) -> str:
    text = str(exc).strip().splitlines()
    msg = text[0] if text else ""
    return (msg[:limit] + "…") if len(msg) > limit else msg


def connect(tracking_uri: str | None = None):
    """An ``MlflowClient`` on :func:`resolve_tracking_uri` after one probe of the registry.

    Raises :class:`ApiError` ("unreachable") when the probe fails (dead server, wrong URI,
    unreadable database), so a missing model is never confused with a missing registry.
    """
    from traffictwin.mlops import registry as reg
    from traffictwin.mlops.uris import mask_uri

    uri = resolve_tracking_uri(tracking_uri)
    try:
        cl = reg.client(uri)
        cl.search_registered_models(max_results=1)
    except Exception as exc:  # noqa: BLE001 - any failure of the probe means "unreachable"
        raise ApiError(
            f"{mask_uri(uri)}: model registry unreachable ({type(exc).__name__}: {_first_line(exc)})"
        ) from None
    return cl


def _split_ref(model: str | os.PathLike) -> tuple[str | None, str | None, Path | None]:
    """``(name or None, alias, None)`` for a registry reference, ``(None, None, path)`` for a
    folder (:func:`traffictwin.mlops.registry_loading.split_model_reference`: a reference
    resolves only against the registry, a path is only a path)."""
    from traffictwin.mlops.errors import RegistryError
    from traffictwin.mlops.registry_loading import split_model_reference

    try:
        return split_model_reference(model, ALIASES)
    except RegistryError as exc:
        raise ApiError(str(exc)) from None


def _load_model(
    model: str | os.PathLike,
    loader,
    model_error: type[Exception],
    what: str,
    family: str,
    tracking_uri: str | None,
):
    """``(model, description)`` of ``model``: a registry reference (``name@alias``; a bare alias
    of ``family``) loaded by :func:`_load_registered`, or a model folder read by ``loader``
    (its ``model_error`` becomes an :class:`ApiError`)."""
    name, alias, path = _split_ref(model)
    if path is None:
        return _load_registered(connect(tracking_uri), name or family, alias, loader, what, family)
    try:
        return loader(path), _folder_description(path)
    except model_error as exc:
        raise ApiError(str(exc)) from None


def _folder_description(path: Path) -> str:
    """How a model folder is reported: the path with a directory part, so a folder named like a
    registry reference (``./traffictwin-risk@champion``) never reads as that reference."""
    return str(path) if path.is_absolute() or path.parent != Path(".") else f".{os.sep}{path}"


def _load_registered(cl, name: str, alias: str, loader, what: str, family: str | None = None):
    """Load ``name@alias`` with ``loader``. ``family``: the registry name of this problem
    (``traffictwin-fusion``...): a name outside it is refused before anything is downloaded,
    and the hint of a missing alias lists only the registered models this loader can load."""
    from traffictwin.mlops import registry as reg

    def loadable(n: str) -> bool:
        return family is None or n == family or n.startswith(f"{family}-")

    if not loadable(name):
        raise ApiError(
            f"--model: '{name}@{alias}' is not a {what}; {what}s are registered as '{family}'"
        )
    mv = reg.get_alias(cl, name, alias)
    if mv is None:
        known = [n for n in reg._registered_names(cl) if loadable(n)]
        hint = (
            f"registered {what}s: {', '.join(known)}"
            if known
            else f"no {what} is registered yet (run the promotion gate: `make promote`)"
        )
        raise ApiError(f"model '{name}' has no version with alias '{alias}' ({hint})")
    uri = reg.version_uri(name, mv.version)
    try:
        return reg.load_registered(uri, loader, cl=cl, cache=True), f"{name}@{alias} ({uri})"
    except reg.GateError as exc:  # tampered, legacy pickle, missing files, ...
        raise ApiError(_first_line(exc, 400)) from None
    except Exception as exc:  # noqa: BLE001
        raise ApiError(
            f"{uri}: cannot load the registered {what} ({type(exc).__name__}: {_first_line(exc)})"
        ) from None
