"""Loading a registered model safely, with a verified local cache.

:func:`load_registered` is the only way a registered model is loaded: files checked against the
version's SHA-256 record first, then the caller's problem loader (``weights_only`` checkpoints);
nothing is unpickled, and a model logged as an ``mlflow.pytorch`` pickle is refused. Part of the
:mod:`traffictwin.mlops.registry` adapter (which re-exports the public names).
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

from traffictwin.mlops import model_artifact as art
from traffictwin.mlops.errors import IncompatibleModelError, RegistryError
from traffictwin.mlops.model_artifact import ModelArtifactError
from traffictwin.mlops.registry_versions import _download

T = TypeVar("T")


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


#: aliases a bare ``--model`` value stands for (``champion`` = ``<family>@champion``)
REFERENCE_ALIASES = ("champion", "challenger")


def split_model_reference(
    model: str | os.PathLike, aliases: tuple[str, ...] = REFERENCE_ALIASES
) -> tuple[str | None, str | None, Path | None]:
    """``(name, alias, None)`` for a registry reference, ``(None, None, path)`` for a folder.

    Registry references resolve only against the registry, whatever the working directory
    holds: a bare alias (``champion``: the caller's family), ``name@alias`` (no ``/``) and
    ``models:/name@alias``. Everything else is a path, and a path is only a path: a folder whose
    name looks like a reference is passed with a directory part (``./traffictwin-risk@champion``,
    ``./champion``). Raises :class:`RegistryError` for a reference with an empty name or alias,
    a path that does not exist, and a file (``model_meta.json``: pass its folder).
    """
    text = os.fspath(model)
    if isinstance(text, bytes):
        text = os.fsdecode(text)
    if text in aliases:
        return None, text, None
    ref = text[len("models:/") :] if text.startswith("models:/") else None
    if ref is None and "@" in text and "/" not in text and os.sep not in text:
        ref = text
    if ref is not None:
        name, _, alias = ref.rpartition("@")
        if not name or not alias or "/" in ref:
            raise RegistryError(
                f"--model: '{text}' is not a registry reference name@alias (a model folder with "
                f"such a name: pass ./{text})"
            )
        return name, alias, None
    p = Path(text)
    if not p.exists():
        raise RegistryError(
            f"--model: '{text}' is neither a registry reference (name@alias, or "
            f"{' / '.join(aliases)}) nor an existing model folder"
        )
    if not p.is_dir():
        raise RegistryError(
            f"--model: '{text}' is a file; pass the model folder that holds it"
            + (f" ({p.parent})" if p.name in ("model_meta.json", "model.ckpt") else "")
        )
    return None, None, p


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
