"""SQLite tracking stores as a user names them: the file of a ``sqlite:///`` URI (a query such as
``?mode=ro`` is no part of it), that URI in the form SQLAlchemy's driver honours, and a one-line
refusal of a file that is not a SQLite database (MLflow would print a long SQLAlchemy traceback).

Kept apart from :mod:`traffictwin.mlops.tracking`, which every pipeline stage depends on.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path
from urllib.parse import unquote

#: the first bytes of every SQLite database file
SQLITE_MAGIC = b"SQLite format 3\x00"
ENV_URI = "MLFLOW_TRACKING_URI"


def sqlite_path(uri: str) -> Path | None:
    """The database file of a ``sqlite:///`` URI (``None`` for any other scheme); a query
    (``?mode=ro``) and SQLite's ``file:`` prefix are not part of the path."""
    if not uri.startswith("sqlite:///"):
        return None
    path = unquote(uri.removeprefix("sqlite:///").split("?", 1)[0])
    return Path(path.removeprefix("file:"))


def sqlalchemy_uri(uri: str) -> str:
    """``uri`` as SQLAlchemy's SQLite driver honours it: ``sqlite:///PATH?mode=ro`` becomes
    ``sqlite:///file:PATH?mode=ro&uri=true`` (without ``uri=true`` the driver ignores ``mode``
    with a warning); any other URI is returned unchanged."""
    if not uri.startswith("sqlite:///") or "?" not in uri:
        return uri
    path, query = uri.removeprefix("sqlite:///").split("?", 1)
    keys = {kv.split("=", 1)[0] for kv in query.split("&")}
    if "mode" not in keys or "uri" in keys:
        return uri
    return f"sqlite:///{path if path.startswith('file:') else 'file:' + path}?{query}&uri=true"


def check_sqlite_store(uri: str) -> None:
    """Refuse (``ValueError``, one line naming the file) a ``sqlite:///`` URI whose file exists
    and is not a SQLite database; a missing file or another scheme passes (MLflow creates or
    reaches it). Reads 16 bytes of a regular file only (a FIFO is never opened)."""
    db = sqlite_path(uri)
    if db is None:
        return
    try:
        st = os.stat(db)
    except OSError:
        return
    if not stat.S_ISREG(st.st_mode):
        raise ValueError(f"{db}: not an MLflow database (not a regular file) — check {ENV_URI}")
    with open(db, "rb") as fh:
        head = fh.read(len(SQLITE_MAGIC))
    if st.st_size and head != SQLITE_MAGIC:
        raise ValueError(
            f"{db}: not an MLflow database (not a SQLite file) — check {ENV_URI} / --tracking-uri"
        )
