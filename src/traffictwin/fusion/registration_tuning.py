"""Choosing registration settings on validation pairs: every combination of a settings grid
(:func:`parameter_grid`) scored by its registration success rate (:func:`validation_success`).
Used by the evaluation only, so the stages that import the fusion methods do not depend on it."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from traffictwin.fusion.method_input import FusionInput
from traffictwin.fusion.registration_batches import refined_registration_batch, register_many

__all__ = ["parameter_grid", "validation_success"]


def parameter_grid(base: Any, grid: dict[str, list[Any]]) -> list[Any]:
    """Every combination of ``grid`` (field → candidate values, in order: the first value of each
    field varies slowest) applied to the frozen settings dataclass ``base``
    (:class:`RegistrationParams`, :class:`RefinementParams`); ``[base]`` for an empty grid."""
    import itertools

    fields = set(getattr(base, "__dataclass_fields__", {}))
    bad = sorted(set(grid) - fields)
    if bad:
        raise ValueError(
            f"parameter_grid: {bad} are not fields of {type(base).__name__} (has {sorted(fields)})"
        )
    keys = list(grid)
    return [
        replace(base, **dict(zip(keys, values)))
        for values in itertools.product(*(list(grid[k]) for k in keys))
    ]


def validation_success(
    kind: str,
    inputs: list[FusionInput],
    candidates: list[Any],
    success_trans_m: float,
    success_rot_deg: float,
    registration: Any = None,
    workers: int = 1,
) -> np.ndarray:
    """Registration success rate (residual ≤ ``success_trans_m`` and ≤ ``success_rot_deg``,
    pooled over every pair of ``inputs``) of each candidate setting: ``kind`` ``"registered"``
    (candidates :class:`RegistrationParams`, :func:`register_many` on ``workers`` cores) or
    ``"learned-refined"`` (candidates :class:`RefinementParams` refining the learned network
    ``registration``'s pose, computed once per input and shared). Each input needs raw maps and
    ``rel_pose_true``. Returns ``(len(candidates),)`` rates."""
    from traffictwin.fusion.registration import pose_error

    if kind not in ("registered", "learned-refined"):
        raise ValueError(
            f"validation_success: kind must be 'registered' or 'learned-refined', got {kind!r}"
        )
    if kind == "learned-refined" and registration is None:
        raise ValueError(
            "validation_success: 'learned-refined' needs the learned registration network"
        )
    true = np.concatenate([np.asarray(x.rel_pose_true, dtype=np.float64) for x in inputs])
    rates = np.empty(len(candidates))
    for j, params in enumerate(candidates):
        if kind == "registered":  # every input's pairs in one pool of workers
            res = register_many(
                np.concatenate([x.map1 for x in inputs]),
                np.concatenate([x.map2 for x in inputs]),
                np.concatenate([x.rel_pose_noisy for x in inputs]),
                inputs[0].grid,
                params,
                workers,
            )
            poses = np.stack([r.pose for r in res])
        else:
            for x in inputs:
                x.refinement = params
            poses = np.concatenate(
                [refined_registration_batch(x, registration).poses for x in inputs]
            )
        t, r = pose_error(poses, true)
        rates[j] = float(((t <= success_trans_m) & (r <= success_rot_deg)).mean())
    return rates
