"""A command's output files, checked before any work and written all-or-nothing.

The rules every ``traffictwin`` command follows (issue 18, defect 6):

- an output never replaces an input (compared by resolved path and, for existing files, by
  ``os.path.samefile``, so a symlink or a second path to the same file is caught too);
- an existing output is refused unless ``force`` (``--force``), and ``force`` overwrites only a
  file of the kind this output is (by content: a ``.npz``/``.pt`` zip archive, a PNG, a JSON
  document, a text/CSV file), i.e. a previous output of the same command (issue 35, item 1);
- a path the project keeps is never an output, ``force`` or not: a file inside a model folder
  (a folder holding ``model.ckpt`` or ``model_meta.json``), a SQLite database (the MLflow store),
  anything under ``mlruns/``, ``mlartifacts/``, ``.git/`` or ``.dvc/``, and ``dvc.lock``,
  ``dvc.yaml``, ``params.yaml``, ``*.dvc``;
- an output path that is a directory is refused;
- missing parent folders are created (for every command alike), and removed again if the command
  fails before its outputs are committed;
- every file is first written to a hidden temp file beside its final name; :meth:`OutputSet.commit`
  renames them all at the end, so a failing or killed command leaves no output half-written.

:class:`OutputError` carries the one-line message (naming the path and the rule).
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterable
from pathlib import Path
from types import TracebackType


class OutputError(ValueError):
    """An output path breaks a rule (input, existing without force, directory, bad parent)."""


MODEL_FILES = ("model.ckpt", "model_meta.json")
PROJECT_FILES = ("dvc.lock", "dvc.yaml", "params.yaml", ".dvcignore")
STORE_FOLDERS = (".git", ".dvc", "mlruns", "mlartifacts")
_SQLITE = b"SQLite format 3\x00"
_ZIP = b"PK\x03\x04"
_PNG = b"\x89PNG\r\n\x1a\n"


def _head(p: Path, n: int = 16) -> bytes:
    try:
        with open(p, "rb") as fh:
            return fh.read(n)
    except OSError:
        return b""


def protected_reason(path: str | os.PathLike) -> str | None:
    """Why ``path`` may never be a command's output (a model, the MLflow store, a DVC/Git file),
    or ``None``."""
    p = Path(path)
    rp = p.resolve()
    if rp.name in MODEL_FILES or any((rp.parent / m).exists() for m in MODEL_FILES):
        return f"{rp.parent} is a model folder (it holds {' / '.join(MODEL_FILES)})"
    hit = next((part for part in rp.parts[:-1] if part in STORE_FOLDERS), None)
    if hit is not None:
        return f"it lies inside a {hit}/ store"
    if rp.name in PROJECT_FILES or rp.suffix == ".dvc":
        return f"{rp.name} is a file of the DVC pipeline"
    if p.is_file() and _head(p) == _SQLITE:
        return "it is a SQLite database (e.g. the MLflow tracking/registry store)"
    return None


def _kind_of(p: Path) -> str:
    """The content kind of an existing file: ``zip``, ``png``, ``json``, ``text`` or ``binary``."""
    head = _head(p, 4096)
    if head.startswith(_ZIP):
        return "zip"
    if head.startswith(_PNG):
        return "png"
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError:
        # a cut in the middle of a multi-byte character at the end of the read block is still text
        try:
            text = head[:-3].decode("utf-8")
        except UnicodeDecodeError:
            return "binary"
    if "\x00" in text:
        return "binary"
    return "json" if text.lstrip()[:1] in ("{", "[") else "text"


_EXPECTED_KIND = {
    ".npz": ("zip",),
    ".pt": ("zip",),
    ".png": ("png",),
    ".json": ("json",),
    ".csv": ("text",),
}


def _same_kind(p: Path) -> bool:
    """May ``--force`` replace the existing file ``p``: is its content what this output will be?"""
    want = _EXPECTED_KIND.get(p.suffix.lower())
    kind = _kind_of(p)
    if want is None:  # an output named freely (e.g. a CSV without suffix): text only
        return kind in ("text", "json")
    return kind in want


def _identity(p: Path) -> tuple[int, int] | None:
    try:
        st = p.stat()
    except OSError:
        return None
    return st.st_dev, st.st_ino


class OutputSet:
    """The outputs of one command. Use as a context manager::

        with OutputSet([out_npz, out_png], inputs=[map1, map2], force=args.force) as outs:
            outs.write_bytes(out_npz, data)        # to a temp file beside out_npz
            with outs.open(out_png, "wb") as fh:   # streamed writes
                ...
            outs.commit()                          # rename every temp file onto its name

    Leaving the block without :meth:`commit` (an exception) deletes the temp files and the
    folders this set created. ``option``: how the outputs are named in messages (``-o``).
    """

    def __init__(
        self,
        paths: Iterable[str | os.PathLike],
        *,
        inputs: Iterable[str | os.PathLike] = (),
        force: bool = False,
        option: str = "-o",
    ) -> None:
        self.paths = [Path(p) for p in paths]
        self.option = option
        self._tmp: dict[Path, Path] = {}
        self._made: list[Path] = []
        self._committed = False
        ins = [Path(p) for p in inputs]
        in_paths = {i.resolve() for i in ins}
        in_files = {ident for i in ins if (ident := _identity(i)) is not None}
        seen: set[Path] = set()
        for p in self.paths:
            rp = p.resolve()
            if rp in seen:
                raise OutputError(f"{option}: {p} is named twice among the outputs")
            seen.add(rp)
            if rp in in_paths or (p.exists() and _identity(p) in in_files):
                raise OutputError(
                    f"{option}: writing {p} would overwrite an input of this command; refusing to overwrite it"
                )
            if p.is_dir():
                raise OutputError(f"{option}: {p} is a directory; expected a file name")
            why = protected_reason(p)
            if why is not None:
                raise OutputError(f"{option}: refusing to write {p}: {why}; choose another path")
            if p.exists() and not force:
                raise OutputError(f"{option}: {p} exists; pass --force to overwrite it")
            if p.exists() and not _same_kind(p):
                raise OutputError(
                    f"{option}: {p} exists and is not a previous {p.suffix or 'text'} output "
                    f"(its content is {_kind_of(p)}); --force overwrites only a previous output "
                    "of this kind; choose another path"
                )
            for parent in (p.parent, *p.parent.parents):
                if parent.exists():
                    if not parent.is_dir():
                        raise OutputError(f"{option}: {parent} is not a folder (parent of {p})")
                    break

    # ---------------------------------------------------------------- writing

    def _temp(self, path: Path) -> Path:
        path = Path(path)
        if path not in self.paths:
            raise ValueError(f"{path} is not one of the declared outputs")
        if path in self._tmp:
            return self._tmp[path]
        missing = [q for q in (path.parent, *path.parent.parents) if not q.exists()]
        for q in reversed(missing):
            q.mkdir()
            self._made.append(q)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        os.close(fd)
        self._tmp[path] = Path(tmp)
        return self._tmp[path]

    def temp_path(self, path: str | os.PathLike) -> Path:
        """The temp file that stands for ``path`` until :meth:`commit` (created empty)."""
        return self._temp(Path(path))

    def open(self, path: str | os.PathLike, mode: str = "w", **kw):  # noqa: ANN201 - a file object
        """Open the temp file of ``path`` (text ``"w"`` or binary ``"wb"``)."""
        return open(self._temp(Path(path)), mode, **kw)  # noqa: SIM115 - caller closes it

    def write_bytes(self, path: str | os.PathLike, data: bytes) -> None:
        with open(self._temp(Path(path)), "wb") as fh:
            fh.write(data)

    def write_text(self, path: str | os.PathLike, text: str) -> None:
        self.write_bytes(path, text.encode("utf-8"))

    def commit(self) -> None:
        """Rename every written temp file onto its final name (fsync first)."""
        missing = [str(p) for p in self.paths if p not in self._tmp]
        if missing:
            raise ValueError(f"outputs not written: {', '.join(missing)}")
        mask = os.umask(0)
        os.umask(mask)
        for tmp in self._tmp.values():
            with open(tmp, "rb+") as fh:
                os.fsync(fh.fileno())
            os.chmod(tmp, 0o666 & ~mask)
        for path, tmp in self._tmp.items():
            os.replace(tmp, path)
        self._committed = True

    def discard(self) -> None:
        """Delete the temp files and the folders this set created (nothing is left behind)."""
        for tmp in self._tmp.values():
            if tmp.exists():
                tmp.unlink()
        self._tmp.clear()
        for q in reversed(self._made):
            try:
                q.rmdir()
            except OSError:
                pass
        self._made.clear()

    def __enter__(self) -> OutputSet:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if not self._committed:
            self.discard()
