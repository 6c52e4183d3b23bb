"""Validation of the API's inputs: world poses (x m, y m, yaw rad), cell sizes (m), evidential
mass grids (free, occupied) and speeds (m/s); and batching of lazily consumed input streams."""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Iterator
from typing import Any

import numpy as np

from .errors import InputValueError

SIMPLEX_TOL = 1e-4


def _is_real(a: np.ndarray) -> bool:
    return np.issubdtype(a.dtype, np.floating) or (
        np.issubdtype(a.dtype, np.integer) and a.dtype != np.bool_
    )


def check_pose(value: Any, who: str) -> np.ndarray:
    """A world pose as float64 ``(3,)`` = x (m), y (m), yaw (rad): three finite real numbers
    (a complex pose is refused, never cast); :class:`InputValueError` naming ``who``."""
    try:
        a = np.asarray(value)
    except Exception:  # noqa: BLE001 - ragged lists and other non-arrays
        a = np.asarray(None)
    if a.shape != (3,) or not _is_real(a) or not np.isfinite(a).all():
        got = f"shape {a.shape}, dtype {a.dtype}" if a.dtype != object else type(value).__name__
        raise InputValueError(
            f"{who}: expected 3 finite real numbers x, y, yaw (m, m, rad), got {got}"
        )
    return a.astype(np.float64)


def check_cell(value: Any, who: str) -> float | None:
    """A cell size (m): ``None`` or one finite positive real number; :class:`InputValueError`."""
    if value is None:
        return None
    a = np.asarray(value)
    if a.size != 1 or not _is_real(a) or not (math.isfinite(float(a)) and float(a) > 0):
        raise InputValueError(
            f"{who}: 'cell' must be one positive real number (m per cell), got {value!r}"
        )
    return float(a)


def check_mass_grids(m: Any, who: str) -> np.ndarray:
    """Masses ``(2, H, W)`` (free, occupied) of a real float dtype, finite, on the simplex
    within :data:`SIMPLEX_TOL` (then cleaned onto it); float32. :class:`InputValueError`."""
    from traffictwin.evidential.masses import check_masses, clean_masses

    a = np.asarray(m)
    if a.ndim != 3 or a.shape[0] != 2:
        raise InputValueError(f"{who}: masses must be (2, H, W) (free, occupied), got {a.shape}")
    if not np.issubdtype(a.dtype, np.floating):
        raise InputValueError(f"{who}: masses must be a real float array, got dtype {a.dtype}")
    try:
        checked = check_masses(a.astype(np.float64), f"{who}: masses (free, occupied)", SIMPLEX_TOL)
    except ValueError as exc:
        raise InputValueError(str(exc)) from None
    return clean_masses(checked).astype(np.float32)


def check_speed_value(speed: Any, who: str = "speed") -> float | None:
    """``None`` or one finite real speed >= 0 (m/s); :class:`InputValueError` naming ``who``."""
    if speed is None:
        return None
    if isinstance(speed, (bool, np.bool_)) or not isinstance(speed, (int, float, np.number)):
        raise InputValueError(f"{who}: expected a number of m/s, got {type(speed).__name__}")
    if not (math.isfinite(float(speed)) and float(speed) >= 0):
        raise InputValueError(f"{who}: must be a finite speed >= 0 m/s, got {speed}")
    return float(speed)


def check_count(value: Any, who: str, minimum: int = 1) -> int:
    """An integer count >= ``minimum`` (a bool or a float such as 2.5 is refused, never rounded);
    :class:`InputValueError` naming ``who``."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise InputValueError(f"{who}: expected an integer >= {minimum}, got {value!r}")
    if value < minimum:
        raise InputValueError(f"{who}: must be >= {minimum}, got {value}")
    return int(value)


def check_flag(value: Any, who: str) -> bool:
    """A boolean (True / False, not 0 / 1 or a string); :class:`InputValueError` naming ``who``."""
    if not isinstance(value, (bool, np.bool_)):
        raise InputValueError(f"{who}: expected True or False, got {value!r}")
    return bool(value)


def check_path(
    value: Any, who: str, expected: str = "a file path (str or os.PathLike)"
) -> str | os.PathLike:
    """A file or folder path (``str`` or ``os.PathLike``, not empty); :class:`InputValueError`
    naming ``who`` and ``expected``."""
    if not isinstance(value, (str, os.PathLike)) or not os.fspath(value):
        got = repr(value) if isinstance(value, str) else type(value).__name__
        raise InputValueError(f"{who}: expected {expected}, got {got}")
    return value


def check_optional_text(value: Any, who: str) -> str | None:
    """``None`` or a non-empty string; :class:`InputValueError` naming ``who``."""
    if value is not None and not (isinstance(value, str) and value):
        raise InputValueError(f"{who}: expected a string or None, got {value!r}")
    return value


def check_instance(value: Any, cls: type, who: str, expected: str) -> Any:
    """``value`` if it is a ``cls``; :class:`InputValueError` naming ``who`` and ``expected``."""
    if not isinstance(value, cls):
        raise InputValueError(f"{who}: expected {expected}, got {type(value).__name__}")
    return value


def checked_items(items: Any, cls: type, who: str, expected: str) -> Iterator[Any]:
    """The items of the iterable ``items`` (consumed lazily), each checked to be a ``cls``:
    :class:`InputValueError` naming ``who``, the item's position and ``expected`` (a
    non-iterable ``items`` at once, a wrong item when it comes)."""
    if isinstance(items, (str, bytes, cls)) or not isinstance(items, Iterable):
        raise InputValueError(
            f"{who}: expected an iterable of {expected}, got {type(items).__name__}"
        )

    def typed() -> Iterator[Any]:
        for k, it in enumerate(items):
            if not isinstance(it, cls):
                raise InputValueError(f"{who}[{k}]: expected {expected}, got {type(it).__name__}")
            yield it

    return typed()


def _chunks(items: Iterable[Any], n: int) -> Iterator[list[Any]]:
    buf: list[Any] = []
    for it in items:
        buf.append(it)
        if len(buf) == n:
            yield buf
            buf = []
    if buf:
        yield buf
