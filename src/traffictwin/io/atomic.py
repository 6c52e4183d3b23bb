"""Atomic file writes: write to a temp name in the same folder, fsync, then rename.

A killed process therefore never leaves a half-written file under the final name. The one
writer of each kind: bytes, text, JSON, CSV tables (:func:`write_csv_atomic`) and PNG figures
(:func:`save_figure`; matplotlib is imported only when a figure is saved).
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any


@contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = "") -> Iterator[Path]:
    """Yield a temp path beside ``path``; on success rename it onto ``path``, else delete it.

    ``suffix`` keeps an extension on the temp name for writers that infer the format from it.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(
        prefix=f".{path.name}.", suffix=(suffix or path.suffix) + ".tmp", dir=path.parent
    )
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        if tmp_path.exists():
            os.chmod(tmp_path, 0o666 & ~_umask())  # mkstemp makes 0600; give the usual file mode
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    """Write UTF-8 ``text`` to ``path`` atomically."""
    write_bytes_atomic(path, text.encode("utf-8"))


def write_json_atomic(path: str | os.PathLike, obj: Any) -> None:
    """Write ``obj`` as indented, key-sorted JSON to ``path`` atomically."""
    write_text_atomic(path, json.dumps(obj, indent=2, sort_keys=True, default=_json_default) + "\n")


def write_csv_atomic(
    path: str | os.PathLike,
    frame: Any,
    *,
    float_format: str | None = None,
    lineterminator: str = "\n",
) -> Path:
    """Write pandas DataFrame ``frame`` as CSV without its index to ``path`` atomically.

    ``float_format`` (e.g. ``"%.6g"``; ``None``: pandas' repr) and ``lineterminator`` go to
    ``DataFrame.to_csv``. Returns ``path``.
    """
    path = Path(path)
    with atomic_path(path, suffix=".csv") as tmp:
        frame.to_csv(tmp, index=False, float_format=float_format, lineterminator=lineterminator)
    return path


def save_figure(
    fig: Any,
    path: str | os.PathLike,
    *,
    dpi: float = 110,
    bbox_inches: str | None = "tight",
    metadata: Mapping[str, str | None] | None = None,
) -> Path:
    """Write matplotlib ``fig`` as PNG to ``path`` atomically, then close it. Returns ``path``.

    ``dpi`` (dots per inch), ``bbox_inches`` (``None``: the full canvas) and ``metadata`` (PNG
    text chunks; ``{"Software": None}`` drops the matplotlib version) go to ``Figure.savefig``.
    """
    path = Path(path)
    kwargs: dict[str, Any] = {"dpi": dpi, "format": "png"}
    if bbox_inches is not None:
        kwargs["bbox_inches"] = bbox_inches
    if metadata is not None:
        kwargs["metadata"] = dict(metadata)
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, **kwargs)
    pyplot().close(fig)
    return path


def pyplot() -> Any:
    """matplotlib.pyplot on the Agg backend (no display), for figure code that imports it only
    when it draws (risk/figures.py and risk/data_figures.py still pick Agg at import)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _json_default(o: Any) -> Any:
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
