"""The one registry-wide lock a promotion gate (or a rollback) holds while it moves aliases.

:func:`gate_lock` takes ``fcntl.flock`` on a file next to the SQLite database
(:func:`default_lock_path`): two gates run one after the other, and the second decides against
the champion the first left. Part of the :mod:`traffictwin.mlops.registry` adapter (which
re-exports the public names).
"""

from __future__ import annotations

import fcntl
import hashlib
import logging
import os
import socket
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from urllib.parse import unquote, urlparse

from traffictwin.mlops.errors import LockTimeoutError

log = logging.getLogger("traffictwin.registry")


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
