"""The lock and the journal of a job that changes files in place (the scheduled retraining).

:func:`exclusive_lock` lets one run at a time in (a second one fails at once, naming the
holder). Before changing anything the run copies what it will change into a :class:`Journal`;
after a failure, an interruption or a SIGKILL (then in the next run) :meth:`Snapshot.restore_files`
puts it back. The journal is written under ``<path>.tmp`` and renamed, so it exists complete or
not at all; its ``state.json`` holds whatever the job needs to know to undo the rest.
"""

from __future__ import annotations

import fcntl
import json
import os
import shutil
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from traffictwin.io.atomic import write_bytes_atomic, write_json_atomic


class JournalError(RuntimeError):
    """A journal is in the way or unreadable (the message names it)."""


class LockBusy(RuntimeError):
    """Another run holds the lock (the message names the lock and its holder)."""


@contextmanager
def exclusive_lock(path: str | os.PathLike, what: str = "run") -> Iterator[int]:
    """Hold an exclusive ``fcntl.flock`` on ``path`` (created if needed) for the block, or raise
    :class:`LockBusy` at once. Yields the descriptor: a child process given it (``pass_fds``)
    keeps the lock held while it lives. Closing it releases the lock, also when the process dies.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a+") as fh:
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            fh.seek(0)
            holder = fh.read().strip() or "unknown holder"
            raise LockBusy(
                f"another {what} holds the lock {path} ({holder}); not starting a second one"
            ) from None
        fh.seek(0)
        fh.truncate()
        fh.write(f"pid {os.getpid()} since {time.strftime('%Y-%m-%dT%H:%M:%S')}\n")
        fh.flush()
        yield fh.fileno()


class Snapshot:
    """Copies of ``paths`` (files or folders, relative to ``root``) in ``dest``.

    ``Snapshot(root, dest, paths)`` takes the copies; ``Snapshot.open(root, dest)`` reads an
    existing one. A path absent at snapshot time is removed again by :meth:`restore_files`.
    """

    def __init__(
        self, root: Path, dest: Path, paths: Sequence[str] = (), *, take: bool = True
    ) -> None:
        self.root, self.dest = Path(root), Path(dest)
        if not take:
            self.present = json.loads((self.dest / "snapshot.json").read_text())
            return
        self.dest.mkdir(parents=True, exist_ok=True)
        self.present = {}
        for rel in paths:
            p = self.root / rel
            self.present[rel] = p.exists()
            if p.is_dir():
                shutil.copytree(p, self.dest / rel, symlinks=True)
            elif p.exists():
                shutil.copy2(p, self.dest / rel)
        write_json_atomic(self.dest / "snapshot.json", self.present)

    @classmethod
    def open(cls, root: Path, dest: Path) -> Snapshot:
        """An existing snapshot in ``dest``."""
        return cls(root, dest, take=False)

    def restore_files(self) -> None:
        """Put every path back as it was when the snapshot was taken (idempotent)."""
        for rel, present in self.present.items():
            p, copy = self.root / rel, self.dest / rel
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p)
            elif not (present and copy.is_file()):
                p.unlink(missing_ok=True)
            if present and copy.is_dir():
                shutil.copytree(copy, p, symlinks=True)
            elif present:
                write_bytes_atomic(p, copy.read_bytes())


class Journal:
    """``<path>/state.json`` (the job's state) and ``<path>/snapshot/`` (a :class:`Snapshot`)."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.tmp = self.path.with_name(self.path.name + ".tmp")
        self.state: dict[str, Any] = {}

    def snapshot(self, root: Path) -> Snapshot:
        return Snapshot.open(root, self.path / "snapshot")

    def begin(self, root: Path, paths: Sequence[str], state: dict[str, Any]) -> None:
        """Snapshot ``paths`` of ``root`` and write ``state``; complete or not at all."""
        if self.path.exists():
            raise JournalError(f"journal {self.path} exists: an earlier run was not undone")
        shutil.rmtree(self.tmp, ignore_errors=True)
        try:
            Snapshot(root, self.tmp / "snapshot", paths)
            write_json_atomic(self.tmp / "state.json", state)
            os.replace(self.tmp, self.path)
        except BaseException:
            shutil.rmtree(self.tmp, ignore_errors=True)
            raise
        self.state = dict(state)

    def update(self, **kw: Any) -> None:
        self.state.update(kw)
        write_json_atomic(self.path / "state.json", self.state)

    def read(self) -> dict[str, Any]:
        try:
            self.state = json.loads((self.path / "state.json").read_text())
        except (OSError, ValueError) as exc:
            raise JournalError(
                f"journal {self.path} is unreadable ({exc}); put the copies in "
                f"{self.path / 'snapshot'} back by hand, then remove the journal"
            ) from None
        return self.state

    def discard(self) -> None:
        shutil.rmtree(self.path, ignore_errors=True)
        shutil.rmtree(self.tmp, ignore_errors=True)
