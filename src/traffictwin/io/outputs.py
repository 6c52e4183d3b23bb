"""A command's output files, checked before any work and written all-or-nothing.

The rules every ``traffictwin`` command follows:

- an output never replaces an input (compared by resolved path and, for existing files, by
  ``os.path.samefile``, so a symlink or a second path to the same file is caught too);
- an output path is a regular file or nothing: a symbolic link, a device, a FIFO or a socket is
  refused, ``force`` or not (:func:`special_file_reason`);
- an existing output is refused unless ``force`` (``--force``), and ``force`` replaces only a
  previous output of the same *kind*, recognised by its content (:data:`KINDS`: a fused grid
  ``.npz`` of ``fuse`` / ``twin`` is never replaced by a TorchScript export, a PNG that is not a
  ``traffictwin`` preview is never replaced by one); the message suggests ``--force`` only where
  ``--force`` would replace the file;
- a path the project keeps is never an output, ``force`` or not (:func:`protected_reason`): a
  file inside a model folder, a SQLite database (the MLflow store), anything under ``mlruns/``,
  ``mlartifacts/``, ``.git/`` or ``.dvc/``, anything under ``src/``, ``conf/`` or ``tests/`` of
  the repository the path lives in, an output of that repository's DVC pipeline (``outs``,
  ``metrics``, ``plots`` of its ``dvc.yaml`` / ``dvc.lock``), a path tracked by a ``*.dvc``
  file, and ``dvc.lock``, ``dvc.yaml``, ``params.yaml``, ``*.dvc``;
- an output path that is a directory (or names one with a trailing ``/``) or is empty is refused;
- missing parent folders are created (for every command alike), and removed again if the command
  fails before its outputs are committed;
- every file is first written to a hidden temp file beside its final name; :meth:`OutputSet.commit`
  moves them all onto their names at the end, so a failing or killed command leaves no output
  half-written. A name that did not exist is created exclusively (a hard link of the temp
  file): of two commands writing the same new output at once, one wins and the other fails.

:class:`OutputError` carries the one-line message (naming the path and the rule).
:func:`check_regular_file` is the check for *inputs* that must be regular files (a FIFO would
block the reader forever): it stats before anything opens the file.
"""

from __future__ import annotations

import errno
import fnmatch
import json
import os
import re
import stat
import tempfile
import zipfile
import zlib
from collections.abc import Callable, Iterable, Sequence
from functools import lru_cache
from pathlib import Path
from types import TracebackType


class OutputError(ValueError):
    """An output path breaks a rule (input, existing without force, directory, bad parent)."""


class NotRegularFileError(OSError):
    """A path that must be a regular file is a FIFO, device, socket or folder
    (:func:`check_regular_file`); an ``OSError`` with ``filename`` and ``strerror`` set."""


MODEL_FILES = ("model.ckpt", "model_meta.json")
PROJECT_FILES = ("dvc.lock", "dvc.yaml", "params.yaml", ".dvcignore")
STORE_FOLDERS = (".git", ".dvc", "mlruns", "mlartifacts")
#: folders of a repository (the nearest folder above holding ``.git`` or ``.dvc``) that hold
#: its code, configuration and tests: never an output
SOURCE_FOLDERS = ("src", "conf", "tests")
_SQLITE = b"SQLite format 3\x00"
_ZIP = b"PK\x03\x04"
_PNG = b"\x89PNG\r\n\x1a\n"


# ============================================================================ what a path is


def _file_type(mode: int) -> str | None:
    """The name of a non-regular file type, or ``None`` for a regular file."""
    for test, name in (
        (stat.S_ISLNK, "a symbolic link"),
        (stat.S_ISFIFO, "a FIFO (named pipe)"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISSOCK, "a socket"),
        (stat.S_ISDIR, "a directory"),
    ):
        if test(mode):
            return name
    return None


def special_file_reason(path: str | os.PathLike) -> str | None:
    """What ``path`` is if it exists and is not a regular file (checked with ``lstat``, so a
    link is a link, even a dangling one), e.g. ``"a FIFO (named pipe)"``; ``None`` for a
    regular file or nothing."""
    try:
        st = os.lstat(path)
    except OSError:
        return None
    return _file_type(st.st_mode)


def check_regular_file(path: str | os.PathLike, what: str = "") -> Path:
    """``path`` if it is a regular file (links followed); raise before anything opens it.

    A missing file is ``FileNotFoundError``; a FIFO, device, socket or folder is
    :class:`NotRegularFileError` (an ``OSError``: ``filename`` is the path, ``strerror`` says
    what it is and, with ``what``, what was expected), so opening a FIFO never blocks. For
    inputs such as ``--params``, ``rollback --log``, ``model.ckpt`` / ``model_meta.json``.
    """
    p = Path(path)
    st = os.stat(p)  # FileNotFoundError / PermissionError name the file themselves
    kind = _file_type(st.st_mode)
    if kind is not None:
        expected = f"expected {what}" if what else "expected a regular file"
        raise NotRegularFileError(errno.EINVAL, f"is {kind}; {expected}", str(p))
    return p


def _head(p: Path, n: int = 16) -> bytes:
    try:
        if not stat.S_ISREG(os.stat(p).st_mode):  # never open a FIFO or device to sniff it
            return b""
    except OSError:
        return b""
    try:
        with open(p, "rb") as fh:
            return fh.read(n)
    except OSError:
        return b""


# ============================================================================ protected paths


def _repo_root(rp: Path) -> Path | None:
    """The nearest folder above ``rp`` holding ``.git`` or ``.dvc`` (the repository), or None."""
    return next((d for d in rp.parents if (d / ".git").exists() or (d / ".dvc").exists()), None)


_TEMPLATE = re.compile(r"\$\{[^}]*\}")


@lru_cache(maxsize=32)
def _dvc_out_patterns(pipeline_file: str, _mtime_ns: int) -> tuple[str, ...]:
    """The outputs (``outs``, ``metrics``, ``plots``) of the stages of a ``dvc.yaml`` /
    ``dvc.lock``, relative to its folder; ``${...}`` of ``foreach`` / ``matrix`` stages become
    ``*``. An unreadable file gives no patterns (DVC itself reports it)."""
    import yaml

    from traffictwin.io.yamlio import safe_load

    try:
        doc = safe_load(Path(pipeline_file).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return ()
    stages = doc.get("stages") if isinstance(doc, dict) else None
    if not isinstance(stages, dict):
        return ()
    pats: list[str] = []
    for st in stages.values():
        body = st.get("do", st) if isinstance(st, dict) else None
        if not isinstance(body, dict):
            continue
        wdir = body.get("wdir") if isinstance(body.get("wdir"), str) else "."
        for key in ("outs", "metrics", "plots"):
            items = body.get(key)
            for item in items if isinstance(items, list) else ():
                path = item
                if isinstance(
                    item, dict
                ):  # {path: {cache: false}} or dvc.lock's {path: ..., md5: ...}
                    path = item.get("path") if "path" in item else next(iter(item), None)
                if isinstance(path, str):
                    pats.append(os.path.normpath(os.path.join(wdir, _TEMPLATE.sub("*", path))))
    return tuple(pats)


def _dvc_reason(rp: Path, root: Path | None) -> str | None:
    """Why ``rp`` belongs to DVC: tracked by a ``*.dvc`` file or an output of a ``dvc.yaml`` /
    ``dvc.lock`` in a folder above it (up to the repository ``root``)."""
    for q in (rp, *rp.parents):
        tracker = q.with_name(q.name + ".dvc") if q.name else None
        if tracker is not None and tracker.is_file():
            return f"it is tracked by DVC ({tracker})"
        if q == root:
            break
    for d in rp.parents:
        for name in ("dvc.yaml", "dvc.lock"):
            f = d / name
            try:
                mtime = f.stat().st_mtime_ns
            except OSError:
                continue
            rel = rp.relative_to(d).as_posix()
            prefixes = [rel, *(p.as_posix() for p in Path(rel).parents if str(p) != ".")]
            pats = _dvc_out_patterns(str(f), mtime)
            if any(fnmatch.fnmatchcase(x, pat) for pat in pats for x in prefixes):
                return f"it is an output of the DVC pipeline {f} (written by `dvc repro`)"
        if d == root:
            break
    return None


def protected_reason(path: str | os.PathLike) -> str | None:
    """Why ``path`` may never be a command's output (a model, the MLflow store, a DVC/Git file,
    the code, configuration or tests of a repository, a DVC output), or ``None``."""
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
    root = _repo_root(rp)
    if root is not None:
        top = rp.relative_to(root).parts[0]
        if top in SOURCE_FOLDERS and len(rp.relative_to(root).parts) > 1:
            return (
                f"it lies under {top}/ of the repository {root} (its code, configuration or tests)"
            )
    return _dvc_reason(rp, root)


# ============================================================================ output kinds

#: the PNG text chunk that marks a preview written by ``traffictwin`` (:func:`mark_png`)
PNG_MARK = b"traffictwin\x00preview"
#: the extra file of a TorchScript export (:data:`traffictwin.export.META_FILE`)
EXPORT_META_MEMBER = "extra/traffictwin.json"


def mark_png(png: bytes) -> bytes:
    """``png`` with a ``tEXt`` chunk :data:`PNG_MARK` after its header: the provenance marker by
    which ``--force`` recognises a previous preview."""
    if not png.startswith(_PNG) or png[12:16] != b"IHDR":
        raise ValueError("not a PNG with an IHDR chunk")
    end = 8 + 12 + int.from_bytes(png[8:12], "big")
    body = b"tEXt" + PNG_MARK
    chunk = len(PNG_MARK).to_bytes(4, "big") + body + zlib.crc32(body).to_bytes(4, "big")
    return png[:end] + chunk + png[end:]


def _zip_members(p: Path) -> list[str]:
    try:
        with zipfile.ZipFile(p) as zf:
            return zf.namelist()
    except (OSError, zipfile.BadZipFile, ValueError):
        return []


def _is_grid(p: Path) -> bool:
    names = _zip_members(p)
    return (
        bool(names)
        and all(n.endswith(".npy") for n in names)
        and {"m_free.npy", "m_occ.npy", "u.npy"} <= set(names)
    )


def _is_disparity(p: Path) -> bool:
    names = _zip_members(p)
    return (
        bool(names)
        and all(n.endswith(".npy") for n in names)
        and {"disparity.npy", "confidence.npy"} <= set(names)
    )


def _is_preview(p: Path) -> bool:
    head = _head(p, 256)
    return head.startswith(_PNG) and b"tEXt" + PNG_MARK in head


def _is_export(p: Path) -> bool:
    return any(n.endswith("/" + EXPORT_META_MEMBER) for n in _zip_members(p))


def _is_risk_json(p: Path) -> bool:
    head = _head(p, 1 << 20)
    try:
        doc = json.loads(head.decode("utf-8"))
    except (UnicodeDecodeError, ValueError):
        return False
    return isinstance(doc, dict) and {
        "id", "left", "right", "model", "predictor", "stereo_settings"
    } <= set(doc)  # fmt: skip


def _csv_header(*columns: str) -> Callable[[Path], bool]:
    def test(p: Path) -> bool:
        first = _head(p, 1 << 16).split(b"\n", 1)[0].rstrip(b"\r")
        return first.split(b",")[: len(columns)] == [c.encode() for c in columns]

    return test


#: the outputs ``--force`` may replace: kind -> (what it is, test of an existing file's content)
KINDS: dict[str, tuple[str, Callable[[Path], bool]]] = {
    "grid": ("a fused grid .npz of traffictwin fuse / twin", _is_grid),
    "preview": ("a preview PNG of traffictwin fuse / twin", _is_preview),
    "disparity": ("a disparity .npz of traffictwin disparity", _is_disparity),
    "export": ("a TorchScript file of traffictwin export", _is_export),
    "risk-json": ("a result JSON of traffictwin risk", _is_risk_json),
    "risk-csv": ("a result CSV of traffictwin risk FOLDER", _csv_header("id", "left", "right")),
    "fuse-summary": (
        "a summary.csv of traffictwin fuse --pairs",
        _csv_header("id", "map1", "map2", "output"),
    ),
    "runs-csv": (
        "a table of traffictwin runs compare",
        _csv_header("run_name", "run_id", "status", "start_time"),
    ),
}
#: the kind of an output whose caller names none, by suffix (others: --force replaces nothing)
SUFFIX_KINDS = {".npz": "grid", ".png": "preview", ".pt": "export", ".json": "risk-json"}


def content_kind(p: Path) -> str:
    """The content of an existing file in words: ``zip``, ``png``, ``json``, ``text``, ``binary``."""
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


def _identity(p: Path) -> tuple[int, int] | None:
    try:
        st = p.stat()
    except OSError:
        return None
    return st.st_dev, st.st_ino


# ============================================================================ the output set


class OutputSet:
    """The outputs of one command. Use as a context manager::

        with OutputSet([out_npz, out_png], kinds=["grid", "preview"], inputs=[map1, map2],
                       force=args.force) as outs:
            outs.write_bytes(out_npz, data)        # to a temp file beside out_npz
            with outs.open(out_png, "wb") as fh:   # streamed writes
                ...
            outs.commit()                          # move every temp file onto its name

    ``kinds``: each output's kind (a key of :data:`KINDS`, one for all or one per path; default:
    by suffix, :data:`SUFFIX_KINDS`): what ``force`` may replace. Leaving the block without
    :meth:`commit` (an exception) deletes the temp files and the folders this set created.
    ``option``: how the outputs are named in messages (``-o``).
    """

    def __init__(
        self,
        paths: Iterable[str | os.PathLike],
        *,
        kinds: str | Sequence[str | None] | None = None,
        inputs: Iterable[str | os.PathLike] = (),
        force: bool = False,
        option: str = "-o",
    ) -> None:
        raw = list(paths)
        self.option = option
        for r in raw:
            if not os.fspath(r):
                raise OutputError(f"{option}: the output path is empty; expected a file name")
            if os.fspath(r).endswith(("/", os.sep)):
                raise OutputError(f"{option}: {os.fspath(r)} names a folder; expected a file name")
        self.paths = [Path(p) for p in raw]
        kind_list = [kinds] * len(raw) if kinds is None or isinstance(kinds, str) else list(kinds)
        if len(kind_list) != len(raw):
            raise ValueError(f"kinds: {len(kind_list)} given for {len(raw)} outputs")
        self.kinds = {
            p: k if k is not None else SUFFIX_KINDS.get(p.suffix.lower())
            for p, k in zip(self.paths, kind_list, strict=True)
        }
        unknown = sorted({k for k in self.kinds.values() if k is not None} - set(KINDS))
        if unknown:
            raise ValueError(f"kinds: unknown output kind(s) {unknown}; expected {sorted(KINDS)}")
        self._tmp: dict[Path, Path] = {}
        self._made: list[Path] = []
        self._replace: set[Path] = set()  # outputs that existed and are replaced (--force)
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
            if p.is_dir() and not p.is_symlink():
                raise OutputError(f"{option}: {p} is a directory; expected a file name")
            special = special_file_reason(p)
            if special is not None:
                raise OutputError(
                    f"{option}: refusing to write {p}: it is {special}; outputs are written only "
                    "as regular files; choose another path"
                )
            why = protected_reason(p)
            if why is not None:
                raise OutputError(f"{option}: refusing to write {p}: {why}; choose another path")
            if p.exists():
                self._check_existing(p, force)
                self._replace.add(p)
            for parent in (p.parent, *p.parent.parents):
                if parent.exists():
                    if not parent.is_dir():
                        raise OutputError(f"{option}: {parent} is not a folder (parent of {p})")
                    break

    def _check_existing(self, p: Path, force: bool) -> None:
        """An existing output: refused unless ``force`` and a previous output of its kind."""
        kind = self.kinds[p]
        if kind is not None:
            what, test = KINDS[kind]
            if test(p):
                if not force:
                    raise OutputError(
                        f"{self.option}: {p} exists ({what}); pass --force to overwrite it"
                    )
                return
        expected = f"{KINDS[kind][0]} expected" if kind is not None else "no kind to replace"
        raise OutputError(
            f"{self.option}: {p} exists and is not a previous {p.suffix + ' ' if p.suffix else ''}"
            f"output ({expected}, its content is {content_kind(p)}); it is kept; choose another path"
        )

    # ---------------------------------------------------------------- writing

    def _temp(self, path: Path) -> Path:
        path = Path(path)
        if path not in self.paths:
            raise ValueError(f"{path} is not one of the declared outputs")
        if path in self._tmp:
            return self._tmp[path]
        missing = [q for q in (path.parent, *path.parent.parents) if not q.exists()]
        for q in reversed(missing):
            try:
                q.mkdir()
            except FileExistsError:  # made by another writer meanwhile: not ours to remove
                continue
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
        """Move every written temp file onto its final name (fsync first).

        A name that did not exist when the set was checked is created exclusively (a hard link
        of the temp file; ``O_EXCL`` where links are not supported), in a fixed order: if another
        writer made one of them meanwhile, the names this commit already made are removed again
        and :class:`OutputError` says so. A previous output (``--force``) is replaced atomically.
        """
        missing = [str(p) for p in self.paths if p not in self._tmp]
        if missing:
            raise ValueError(f"outputs not written: {', '.join(missing)}")
        mask = os.umask(0)
        os.umask(mask)
        for tmp in self._tmp.values():
            with open(tmp, "rb+") as fh:
                os.fsync(fh.fileno())
            os.chmod(tmp, 0o666 & ~mask)
        made: list[Path] = []
        try:
            for path in sorted(p for p in self._tmp if p not in self._replace):
                _create_exclusive(self._tmp[path], path)
                made.append(path)
        except FileExistsError as exc:
            for path in made:
                path.unlink(missing_ok=True)
            raise OutputError(
                f"{self.option}: {exc.filename} was created by another command while this one "
                "ran; nothing written"
            ) from None
        for path, tmp in self._tmp.items():
            if path in self._replace:
                os.replace(tmp, path)
            else:
                tmp.unlink(missing_ok=True)
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


def _create_exclusive(tmp: Path, path: Path) -> None:
    """Give the written ``tmp`` the name ``path``, which must not exist (``FileExistsError``)."""
    try:
        os.link(tmp, path)
        return
    except FileExistsError:
        raise FileExistsError(errno.EEXIST, "exists", str(path)) from None
    except OSError as exc:
        if exc.errno not in (
            errno.EPERM,
            errno.ENOTSUP,
            errno.EOPNOTSUPP,
            errno.EXDEV,
            errno.EMLINK,
        ):
            raise
    fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666)  # no hard links here
    os.close(fd)
    os.replace(tmp, path)
