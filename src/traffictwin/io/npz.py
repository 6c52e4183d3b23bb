"""Deterministic ``.npz`` archives and file hashes (the shards of :mod:`traffictwin.io.shards`).

:func:`write_npz_deterministic` writes a zip of ``.npy`` arrays with fixed zip timestamps,
atomically, so the same arrays give the same bytes; :func:`read_npz` reads one back. Both refuse
float arrays with NaN or ±inf (:func:`check_finite`) unless the key is named in ``allow_inf``
(arrays where infinity is a defined value); NaN is never data. :func:`read_npz` reads every
array's ``.npy`` header first (:func:`traffictwin.io.limits.npz_headers`) and refuses arrays that
hold no numbers or whose data differs from what the header announces, before allocating anything.
"""

from __future__ import annotations

import hashlib
import io
import zipfile
from collections.abc import Collection, Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from traffictwin.io.atomic import atomic_path
from traffictwin.io.limits import NPY_HEADER_LOCK, InputError, npz_headers

_ZIP_DATE = (1980, 1, 1, 0, 0, 0)


class DatasetError(RuntimeError):
    """A dataset folder, manifest, shard or table is missing, corrupt or of the wrong kind."""


def sha256_file(path: str | Path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while True:
            b = fh.read(chunk)
            if not b:
                break
            h.update(b)
    return h.hexdigest()


def check_finite(
    arrays: Mapping[str, np.ndarray], where: str | Path, allow_inf: Collection[str] = ()
) -> None:
    """Raise :class:`DatasetError` naming ``where`` and the array when a float array of ``arrays``
    holds NaN, or ±inf unless its key is in ``allow_inf``. Integer and bool arrays pass."""
    for key in sorted(arrays):
        a = np.asarray(arrays[key])
        if a.dtype.kind not in "fc":
            continue
        ok = ~np.isnan(a) if key in allow_inf else np.isfinite(a)
        if ok.all():
            continue
        bad = ~ok
        n_nan, n_inf = int(np.isnan(a).sum()), int((bad & ~np.isnan(a)).sum())
        first = tuple(int(i) for i in np.argwhere(bad)[0])
        raise DatasetError(
            f"{where}: array '{key}' holds {n_nan} NaN and {n_inf} infinite value(s) "
            f"(first at index {first}); shards must hold finite numbers"
        )


def write_npz_deterministic(
    path: str | Path,
    arrays: Mapping[str, np.ndarray],
    compresslevel: int = 6,
    *,
    allow_inf: Collection[str] = (),
    check: bool = True,
) -> str:
    """Write ``arrays`` as a compressed ``.npz`` with fixed metadata, atomically; return its SHA-256.

    Non-finite float arrays are refused before anything is written (:func:`check_finite`;
    ``allow_inf``: keys where ±inf is a value). ``check=False`` writes them as given — only for
    building corrupt fixtures in tests of the readers.
    """
    path = Path(path)
    if check:
        check_finite(arrays, f"{path} (refusing to write)", allow_inf)
    with atomic_path(path, suffix=".npz") as tmp:
        with zipfile.ZipFile(
            tmp, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=compresslevel
        ) as zf:
            for key in sorted(arrays):
                buf = io.BytesIO()
                np.lib.format.write_array(
                    buf, np.ascontiguousarray(arrays[key]), allow_pickle=False
                )
                info = zipfile.ZipInfo(f"{key}.npy", date_time=_ZIP_DATE)
                info.compress_type = zipfile.ZIP_DEFLATED
                info.external_attr = 0o644 << 16
                zf.writestr(
                    info,
                    buf.getvalue(),
                    compress_type=zipfile.ZIP_DEFLATED,
                    compresslevel=compresslevel,
                )
        digest = sha256_file(tmp)
    return digest


# numpy parses each array's .npy header with ast.literal_eval; CPython 3.11's AST constructor is
# not safe to run in two threads at once ("SystemError: AST constructor recursion depth mismatch"),
# so threads that read shards (Dataset.load_all) parse headers one at a time and decompress in
# parallel
_NPY_PARSE_LOCK = NPY_HEADER_LOCK  # the package's one lock (io.limits reads headers under it)


def _read_member(z: Any, key: str) -> np.ndarray:
    """Array ``key`` of an open ``np.load`` archive: its bytes decompressed outside the lock (zlib
    releases the GIL), its header parsed and the array built under :data:`_NPY_PARSE_LOCK`."""
    member = f"{key}.npy" if f"{key}.npy" in z.zip.namelist() else key
    raw = z.zip.read(member)
    with _NPY_PARSE_LOCK:
        return np.lib.format.read_array(io.BytesIO(raw), allow_pickle=False)


def read_npz(
    path: str | Path,
    allow_inf: Collection[str] = (),
    keys: Iterable[str] | None = None,
    *,
    max_bytes: int | None = None,
) -> dict[str, np.ndarray]:
    """Read every array of an ``.npz`` (or only ``keys``: the others are not decompressed) into
    memory; a clear error if it is not a readable archive, lacks a key, or a float array holds NaN
    (or ±inf outside ``allow_inf``; :func:`check_finite`).

    Before any array is decompressed, each one's ``.npy`` header is checked
    (:func:`traffictwin.io.limits.npz_headers`): numbers only, data of exactly itemsize × elements
    bytes, at most ``max_bytes`` bytes per array (``None``, the default for dataset shards: no
    limit beyond what the zip directory declares; their sizes follow from the bounded config)."""
    path = Path(path)
    keys = None if keys is None else list(keys)
    if not path.exists():
        raise DatasetError(f"{path}: file not found")
    try:
        npz_headers(path, keys, max_bytes=max_bytes)
    except InputError as exc:
        raise DatasetError(str(exc)) from None
    try:
        with np.load(path, allow_pickle=False) as z:
            names = list(z.files) if keys is None else list(keys)
            missing = [k for k in names if k not in z.files]
            if missing:
                raise DatasetError(f"{path}: array(s) {missing} missing (has {sorted(z.files)})")
            arrays = {k: _read_member(z, k) for k in names}
    except FileNotFoundError:
        raise DatasetError(f"{path}: file not found") from None
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as exc:
        raise DatasetError(f"{path}: not a readable .npz archive ({exc})") from None
    check_finite(arrays, path, allow_inf)
    return arrays
