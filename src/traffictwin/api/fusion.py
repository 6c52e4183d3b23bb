"""Fusion through the API: load the fusion network, read evidential grid maps (``.npz``), check a
grid against the model's training grid (rows, cols, cell in m) and fuse pairs in batches."""

from __future__ import annotations

import os
import warnings
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .errors import ApiError, ApiWarning, InputFileError, InputValueError, ModelDomainError
from .inputs import (
    _chunks,
    check_cell,
    check_count,
    check_instance,
    check_mass_grids,
    check_optional_text,
    check_path,
    check_pose,
    checked_items,
)
from .registry import _load_model

DIVISOR = 16  # the fusion network's output stride: grid rows and cols must be multiples


@dataclass
class FusionModel:
    """A fusion network (eval mode, CPU), its metadata, training grid and a description."""

    net: Any
    meta: dict[str, Any]
    grid: dict[str, float]
    description: str


def load_fusion(model: str | os.PathLike, *, tracking_uri: str | None = None) -> FusionModel:
    """Load the fusion network by registry reference (``name@alias``, or a bare alias of
    ``traffictwin-fusion``: one network serves every pose-noise level) or model folder. Raises
    :class:`ApiError`."""
    from traffictwin.fusion.model_io import FusionModelError, load_fusion_model
    from traffictwin.mlops.registry import FUSION_NAME

    check_path(model, "model", "a registry reference name@alias or a model folder path")
    check_optional_text(tracking_uri, "tracking_uri")
    net, desc = _load_model(
        model, load_fusion_model, FusionModelError, "fusion model", FUSION_NAME, tracking_uri
    )
    meta = dict(getattr(net, "meta", {}) or {})
    return FusionModel(net, meta, dict(meta.get("grid") or {}), desc)


def load_masses(path: str | os.PathLike) -> tuple[np.ndarray, float | None, np.ndarray | None]:
    """Read and validate an evidential grid ``.npz``: masses ``(2, H, W)`` float32, the optional
    ``cell`` (m) and the optional sensor ``pose`` (x m, y m, yaw rad). Raises :class:`ApiError`."""
    from traffictwin.io.limits import InputError, check_grid_cells, npz_headers

    path = Path(check_path(path, "path"))
    if not path.is_file():
        raise InputFileError(f"{path}: file not found")
    keys = ("m_free", "m_occ", "cell", "pose")  # the arrays read; no other one is decompressed
    try:  # zip and sizes from the .npy headers, before any array is decompressed
        heads = npz_headers(path, keys)
    except InputError as exc:
        raise InputFileError(f"{exc}; expected arrays m_free and m_occ, (H, W) float") from None
    try:
        for k in heads:
            check_grid_cells(heads[k].shape, f"{path}: array '{k}'")
    except InputError as exc:
        raise InputValueError(str(exc)) from None
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in heads}
            names = sorted(z.files)
    except Exception as exc:  # noqa: BLE001 - zip/format errors of all kinds
        raise InputFileError(
            f"{path}: not a readable .npz file ({type(exc).__name__}: {exc})"
        ) from None
    missing = [k for k in ("m_free", "m_occ") if k not in data]
    if missing:
        raise InputFileError(
            f"{path}: array(s) {missing} missing (has {names}); expected m_free and m_occ, (H, W) float"
        )
    mf, mo = data["m_free"], data["m_occ"]
    for k, a in (("m_free", mf), ("m_occ", mo)):
        if a.ndim != 2:
            raise InputValueError(f"{path}: '{k}' must be a 2-D (H, W) grid, got shape {a.shape}")
        if not np.issubdtype(a.dtype, np.floating):
            raise InputValueError(
                f"{path}: '{k}' must be a float array of masses, got dtype {a.dtype}"
            )
    if mf.shape != mo.shape:
        raise InputValueError(f"{path}: 'm_free' {mf.shape} and 'm_occ' {mo.shape} differ in shape")
    m = check_mass_grids(np.stack([mf, mo]), str(path))  # the one validator of the API
    cell = check_cell(data["cell"], str(path)) if "cell" in data else None
    pose = check_pose(data["pose"], f"{path}: 'pose'") if "pose" in data else None
    return m, cell, pose


@dataclass
class FusePair:
    """One fusion input: maps ``(2, H, W)`` in their sensor frames, world poses (x, y, yaw; m,
    m, rad), the cell size (m; ``None`` = the model's) and an id."""

    m1: np.ndarray
    m2: np.ndarray
    pose1: np.ndarray
    pose2: np.ndarray
    cell: float | None = None
    id: str = ""

    def __post_init__(self) -> None:
        """:class:`InputValueError` unless ``id`` is a string (the arrays are checked by
        :func:`fuse`, with the pair's id in the message)."""
        if not isinstance(self.id, str):
            raise InputValueError(f"FusePair id: expected a string, got {type(self.id).__name__}")


@dataclass
class FuseResult:
    """Fused masses ``(2, H, W)`` and ``u (H, W)`` (float32, map 1's frame), map 2 prealigned,
    the relative pose used (3,), the cell (m), the id of the pair and whether map 2 overlaps
    map 1's grid at all (``False``: the fused map is map 1 alone; :func:`fuse` warns)."""

    id: str
    masses: np.ndarray
    u: np.ndarray
    m2_prealigned: np.ndarray
    rel_pose: np.ndarray
    cell: float
    m1: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))
    overlap: bool = True  #: whether any cell of map 2 lands on map 1's grid at the poses


def check_fusion_domain(
    model: FusionModel, shape: tuple[int, int], cell: float | None, who: str
) -> float:
    """The cell size to use for a grid of ``shape`` (rows, cols); :class:`ApiError` naming
    ``who`` unless the grid matches the model's training grid (rows, cols, cell)."""
    check_instance(model, FusionModel, "model", "a FusionModel (api.load_fusion)")
    h, w = shape
    if h % DIVISOR or w % DIVISOR:
        raise ModelDomainError(
            f"{who}: grid {h}x{w} cells: rows and cols must be divisible by {DIVISOR} (network output stride)"
        )
    g = model.grid
    if "rows" in g and "cols" in g and (int(g["rows"]), int(g["cols"])) != (h, w):
        raise ModelDomainError(
            f"{who}: grid {h}x{w} cells (rows x cols) but the model ({model.description}) was "
            f"trained on {int(g['rows'])}x{int(g['cols'])}"
        )
    if cell is None:
        cell = float(g["cell"]) if "cell" in g else None
    if cell is None:
        raise ApiError(
            f"{who}: grid cell size unknown: give the pair's cell (m per cell; --cell in the CLI) or store 'cell' in the .npz"
        )
    if "cell" in g and abs(float(g["cell"]) - cell) > 1e-9:
        raise ModelDomainError(
            f"{who}: maps have {cell} m cells but the model ({model.description}) was trained on {g['cell']} m cells"
        )
    return float(cell)


def fuse(
    model: FusionModel, pairs: Iterable[FusePair], *, batch_size: int = 8
) -> Iterator[FuseResult]:
    """Prealign each pair's map 2 into map 1's frame by the poses and fuse with the network,
    ``batch_size`` pairs per forward pass. Pairs are consumed lazily and results yielded in
    order, so memory stays bounded by one batch. The arguments are checked at the call (an
    :class:`InputValueError` naming the argument); a pair outside the training grid raises
    :class:`ApiError` when its batch comes. A pair whose map 2 does not overlap map 1's grid at
    the given poses is fused (the result is map 1 alone, ``overlap`` False) with an
    :class:`ApiWarning`."""
    check_instance(model, FusionModel, "model", "a FusionModel (api.load_fusion)")
    items = checked_items(pairs, FusePair, "pairs", "api.FusePair(m1, m2, pose1, pose2, cell, id)")
    return _fuse(model, items, check_count(batch_size, "batch_size"))


def check_relative_pose(pose1: np.ndarray, pose2: np.ndarray, who: str) -> np.ndarray:
    """Map 2's sensor pose in map 1's frame (x m, y m, yaw rad); :class:`InputValueError` naming
    ``who`` (the two poses) when it is not finite (poses too large to subtract, e.g. ±1e308)."""
    from traffictwin.geometry import relative_pose

    with np.errstate(over="ignore", invalid="ignore"):
        rel = np.asarray(relative_pose(pose1, pose2), np.float64)
    if not np.isfinite(rel).all():
        raise InputValueError(
            f"{who}: map 2's pose relative to map 1 is not finite "
            f"({pose1.tolist()} -> {pose2.tolist()}); give poses in metres within the grid's reach"
        )
    return rel


def _overlaps(rel: np.ndarray, grid: Any) -> bool:
    """Whether any cell of a map warped by ``rel`` (:func:`warp_masses`) lands on ``grid``:
    never when the sensors (each at its grid's centre) are farther apart than the grid's
    diagonal (m; the warp is not even tried: at 1e308 m its matrix overflows), else whether a
    cell of a probe map lands on it."""
    from traffictwin.evidential.warp import warp_masses

    if np.hypot(rel[0], rel[1]) > grid.cell * (np.hypot(grid.rows, grid.cols) + 2):
        return False
    probe = np.full((2, grid.rows, grid.cols), 0.5, np.float32)
    return bool((warp_masses(probe, rel, grid).sum(axis=0) > 1e-6).any())


def _fuse(model: FusionModel, pairs: Iterable[FusePair], batch_size: int) -> Iterator[FuseResult]:
    from traffictwin.fusion.model_io import predict_masses
    from traffictwin.fusion.pairs import prealign
    from traffictwin.grid import GridSpec

    for chunk in _chunks(pairs, batch_size):
        xs, prep = [], []
        for p in chunk:
            who = f"pair {p.id!r}"
            m1, m2 = check_mass_grids(p.m1, f"{who} m1"), check_mass_grids(p.m2, f"{who} m2")
            if m1.shape != m2.shape:
                raise InputValueError(
                    f"{who}: maps must both be (2, H, W) of one size, got {m1.shape} and {m2.shape}"
                )
            pose1, pose2 = check_pose(p.pose1, f"{who} pose1"), check_pose(p.pose2, f"{who} pose2")
            cell = check_fusion_domain(model, m1.shape[1:], check_cell(p.cell, who), who)
            grid = GridSpec(rows=m1.shape[1], cols=m1.shape[2], cell=cell)
            rel = check_relative_pose(pose1, pose2, f"{who} pose1, pose2")
            overlap = _overlaps(rel, grid)
            if overlap:
                m2w, rel = prealign(m2, pose1, pose2, grid)
            else:  # what the warp gives when nothing lands: every cell unknown
                m2w = np.zeros_like(m2)
                warnings.warn(
                    f"{who}: map 2 does not overlap map 1's grid at the given poses (map 2 at "
                    f"x {rel[0]:.6g} m, y {rel[1]:.6g} m in map 1's frame); the output is map 1 alone",
                    ApiWarning,
                    stacklevel=3,
                )
            xs.append(np.concatenate([m1, m2w]).astype(np.float32))
            prep.append((p, m2w, rel, cell, overlap))
        m, u = predict_masses(model.net, np.stack(xs), batch_size=batch_size)
        for k, (p, m2w, rel, cell, overlap) in enumerate(prep):
            yield FuseResult(p.id, m[k], u[k], m2w, rel, cell, xs[k][:2], overlap)
