"""The evaluated pairs: every configuration's prealigned test arrays on the same pair ids (so the
same noise draws for every configuration and method) and their raw maps, masses and grid checked."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from traffictwin.evidential.masses import check_masses
from traffictwin.fusion.pairs import evenly_spaced
from traffictwin.grid import GridSpec
from traffictwin.io.shards import Dataset, DatasetError


def _check_maps(a: np.ndarray, name: str, grid: GridSpec | None, channels: int = 2) -> None:
    """Masses ``a`` (N, channels, H, W): finite, on the simplex, on ``grid``; errors name ``name``."""
    a = np.asarray(a)
    if a.ndim != 4 or a.shape[1] != channels:
        raise DatasetError(f"{name}: expected shape (N, {channels}, H, W), got {a.shape}")
    if grid is not None and a.shape[-2:] != (grid.rows, grid.cols):
        raise DatasetError(
            f"{name}: grid {a.shape[-2]}x{a.shape[-1]} cells, expected {grid.rows}x{grid.cols} "
            "(params.yaml 'grid'; stale data?)"
        )
    for k in range(0, channels, 2):
        what = name if channels == 2 else f"{name} channels {k}-{k + 1}"
        try:
            check_masses(a[:, k : k + 2], what)
        except ValueError as exc:
            raise DatasetError(str(exc)) from None


def _load_prealigned(root: str | Path, split: str, grid: GridSpec | None) -> dict[str, np.ndarray]:
    """Every array of split ``split`` of the prealigned dataset ``root``, the needed ones checked."""
    ds = Dataset(root, kind="prealigned")
    arrays = ds.load_all(split)
    for key in ("inputs", "label", "noise", "rel_pose_true", "rel_pose_noisy", "pair_id"):
        if key not in arrays:
            raise DatasetError(f"{ds.root}: array '{key}' missing in split '{split}'")
    _check_maps(arrays["inputs"], f"{ds.root}: split '{split}' array 'inputs'", grid, 4)
    _check_maps(arrays["label"], f"{ds.root}: split '{split}' array 'label'", grid)
    return arrays


def load_test_sets(
    roots: Mapping[str, str | Path],
    split: str,
    max_pairs: int | None,
    grid: GridSpec | None = None,
) -> tuple[dict[str, dict[str, np.ndarray]], np.ndarray]:
    """Each configuration's ``split`` arrays (``roots[cfg]`` = its prealigned dataset) restricted to
    the same pair ids: ``max_pairs`` of the pair ids common to all configurations, spread evenly
    over them (so over scenarios/templates). ``inputs`` and ``label`` are checked (finite masses on
    the simplex, on ``grid`` when given): :class:`DatasetError` naming the dataset and array."""
    raw = {c: _load_prealigned(root, split, grid) for c, root in roots.items()}
    common = np.array(
        sorted(set.intersection(*(set(raw[c]["pair_id"].tolist()) for c in roots))),
        dtype=np.int64,
    )
    if not len(common):
        raise DatasetError(
            f"{', '.join(str(r) for r in roots.values())}: no pair id common to all '{split}' splits"
        )
    chosen = common[evenly_spaced(len(common), max_pairs)]
    out = {}
    for c in roots:
        pid = np.asarray(raw[c]["pair_id"], dtype=np.int64)
        # the first draw of each pair id wins (a stable sort keeps the first)
        order = np.argsort(pid, kind="stable")
        first = order[np.searchsorted(pid[order], chosen)]
        out[c] = {k: v[first] for k, v in raw[c].items()}
    return out, chosen


def load_raw_pairs(
    root: str | Path, pair_ids: np.ndarray, split: str, grid: GridSpec | None = None
) -> dict[str, np.ndarray]:
    """``map1``, ``map2``, ``label``, ``pose1``, ``pose2`` of the fusion dataset ``root`` for
    ``pair_ids`` (in that order); the maps are checked like :func:`load_test_sets`'s."""
    ds = Dataset(root, kind="fusion")
    keys = ("map1", "map2", "label", "pose1", "pose2", "pair_id")
    arrays = ds.load_all(split, keys=keys)
    index = {int(p): i for i, p in enumerate(arrays["pair_id"])}
    missing = [int(p) for p in pair_ids if int(p) not in index]
    if missing:
        raise DatasetError(
            f"{ds.root}: pair ids {missing[:5]} of the prealigned data missing in split '{split}' (stale data?)"
        )
    idx = np.array([index[int(p)] for p in pair_ids], dtype=np.int64)
    out = {k: arrays[k][idx] for k in keys}
    for k in ("map1", "map2", "label"):
        _check_maps(out[k], f"{ds.root}: split '{split}' array '{k}'", grid)
    return out
