"""What a fusion method (:mod:`traffictwin.fusion.methods`) is given: :class:`FusionInput`, a batch
of pairs with the fields its ``needs`` name; its own module so that the registration helpers the
methods call (:mod:`traffictwin.fusion.registration_batches`) take it without importing the registry."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from traffictwin.fusion.refinement import RefinementParams
from traffictwin.fusion.registration import RegistrationParams
from traffictwin.grid import GridSpec

__all__ = ["FusionInput"]


@dataclass
class FusionInput:
    """A batch of ``N`` pairs and what the methods may use (fields a method does not need stay None).

    ``inputs`` (N, 4, H, W) prealigned; ``map1``, ``map2`` (N, 2, H, W) raw; ``rel_pose_noisy`` /
    ``rel_pose_true`` (N, 3) relative pose of map 2's sensor in map 1's frame (x m, y m, yaw
    rad; the true one only for diagnostics); ``grid``; ``model`` (a fusion network),
    ``batch_size`` (its inference batch); ``registration`` (classical registration settings);
    ``refinement`` (the ECC refinement of the learned estimate, ``learned-refined``);
    ``pair_key`` (N,) ints naming each pair and ``memo`` a dict shared by every method run on
    these pairs: a registration (classical or learned) is then computed once per pair and reused
    by every method that uses it (``registered`` and ``registered+network``, ``learned`` and
    ``learned+network``), its wall time still counted in each method's per-pair seconds.
    """

    inputs: np.ndarray | None = None
    map1: np.ndarray | None = None
    map2: np.ndarray | None = None
    rel_pose_noisy: np.ndarray | None = None
    rel_pose_true: np.ndarray | None = None
    grid: GridSpec | None = None
    model: Any = None
    batch_size: int = 8
    registration: RegistrationParams = field(default_factory=RegistrationParams)
    refinement: RefinementParams = field(default_factory=RefinementParams)
    pair_key: np.ndarray | None = None
    memo: dict | None = None

    _ARRAYS = ("inputs", "map1", "map2", "rel_pose_noisy", "rel_pose_true", "pair_key")

    def __len__(self) -> int:
        for k in self._ARRAYS:
            v = getattr(self, k)
            if v is not None:
                return len(v)
        return 0

    def take(self, index: slice | np.ndarray) -> FusionInput:
        """The same input restricted to pairs ``index`` (a slice or an index array)."""
        arrays = {k: getattr(self, k)[index] for k in self._ARRAYS if getattr(self, k) is not None}
        return replace(self, **arrays)

    def missing(self, needs: tuple[str, ...]) -> list[str]:
        """Fields required by ``needs`` that are None."""
        req = {
            "prealigned": ("inputs",),
            "raw": ("map1", "map2", "rel_pose_noisy", "grid"),
            "pose": ("rel_pose_noisy", "grid"),
            "model": ("model",),
        }
        return [f for n in needs for f in req[n] if getattr(self, f) is None]
