"""Artifact surgery for the reliability tests: where a version's files are, a pickle that runs code."""

from __future__ import annotations

from pathlib import Path
from urllib.parse import unquote, urlparse


def artifact_dir(cl, name: str, version: str | int) -> Path:
    """The folder on disk that holds the files of registered version ``name`` v``version``."""
    mv = cl.get_model_version(name, str(version))
    model_id = mv.source[len("models:/") :]
    loc = cl.get_logged_model(model_id).artifact_location
    u = urlparse(loc)
    return Path(unquote(u.path) if u.scheme == "file" else loc)


class Payload:
    """Unpickling this object opens (creates) ``marker``: stands for any code an attacker runs."""

    def __init__(self, marker: Path) -> None:
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def write_malicious_pickle(path: Path, marker: Path) -> None:
    """Replace ``path`` by a torch file whose unpickling creates ``marker``."""
    import torch

    path.unlink(missing_ok=True)
    torch.save({"state_dict": {}, "payload": Payload(marker)}, path)


def payload_runs(path: Path, marker: Path) -> bool:
    """Whether unpickling ``path`` unsafely creates ``marker`` (so the payload is real)."""
    import torch

    try:
        torch.load(path, weights_only=False)
    except Exception:  # noqa: BLE001 - the payload's return value is no checkpoint
        pass
    return marker.exists()
