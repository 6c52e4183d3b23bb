"""Arrays with JSON metadata in one deterministic ``.npz``: what an evaluation stage keeps for a
figure that plot_data draws (``data/figure_inputs``). Apart from :mod:`traffictwin.io.npz` so
that the data stages, which read and write shards through it, do not depend on this file."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from traffictwin.io.npz import DatasetError, read_npz, write_npz_deterministic

META_KEY = "meta_json"  # the JSON metadata of :func:`write_arrays_with_meta`, as UTF-8 bytes


def write_arrays_with_meta(
    path: str | Path, arrays: Mapping[str, np.ndarray], meta: Mapping[str, Any]
) -> str:
    """:func:`write_npz_deterministic` of ``arrays`` plus ``meta`` (JSON-serialisable: names,
    numbers) stored as the UTF-8 bytes of its sorted JSON under :data:`META_KEY`."""
    text = json.dumps(dict(meta), sort_keys=True, allow_nan=False).encode()
    return write_npz_deterministic(path, {**arrays, META_KEY: np.frombuffer(text, np.uint8)})


def read_arrays_with_meta(path: str | Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """The arrays and metadata :func:`write_arrays_with_meta` wrote to ``path``."""
    arrays = read_npz(path)
    if META_KEY not in arrays:
        raise DatasetError(f"{path}: no '{META_KEY}' array (not written by write_arrays_with_meta)")
    return arrays, json.loads(arrays.pop(META_KEY).tobytes().decode())
