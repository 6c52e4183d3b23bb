"""The one interface of every risk predictor (:class:`RiskPredictor`: the network
:class:`~traffictwin.risk.model_io.RiskModel`, the corridor rule and hybrid of
:mod:`traffictwin.risk.predictors`) and the raw frames it reads (:class:`RiskFrames`).

Every predictor names the arrays it reads in ``cfg.inputs`` (``rgb`` = the left image, or a
disparity key such as ``disp_sgm``, ``disp_gt``, ``disp_learned``); callers hand every
disparity they have by key (:meth:`RiskFrames.of_arrays`) and never branch on the predictor."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Hashable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np

#: the disparity keys a frame can carry: SGM's, the exact one, the learned stereo network's
DISPARITY_KEYS = ("disp_sgm", "disp_gt", "disp_learned")
#: where a risk model folder whose predictor reads the learned disparity packages its stereo network
PACKAGED_STEREO = "stereo"


@dataclass(frozen=True)
class RiskFrames:
    """Raw frames a risk predictor reads, each optional: ``left_bgr`` (N, H, W, 3) uint8,
    ``disparity`` key (:data:`DISPARITY_KEYS`) → (N, H, W) disparity px, ``speed`` (N,) subject
    speed m/s. ``derived`` memoises what predictors compute from these frames (e.g. the corridor
    profile several hybrids share), so every caller gets the sharing without knowing of it."""

    left_bgr: np.ndarray | None = None
    disparity: Mapping[str, np.ndarray] = field(default_factory=dict)
    speed: np.ndarray | None = None
    derived: dict[Hashable, np.ndarray] = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        bad = [k for k in self.disparity if k not in DISPARITY_KEYS]
        if bad:
            raise ValueError(
                f"RiskFrames.disparity: unknown key(s) {bad} (expected from {list(DISPARITY_KEYS)})"
            )
        given = {k: v for k, v in self.disparity.items() if v is not None}
        object.__setattr__(self, "disparity", MappingProxyType(given))

    @classmethod
    def of_arrays(cls, arrays: Mapping[str, np.ndarray], speed: np.ndarray | None) -> RiskFrames:
        """Frames from a dataset's arrays (``left`` and any of :data:`DISPARITY_KEYS`, as
        :meth:`~traffictwin.risk.source.RiskSource.iter_arrays` yields them) and ``speed`` m/s."""
        disp = {k: arrays[k] for k in DISPARITY_KEYS if k in arrays}
        return cls(arrays.get("left"), disp, speed)

    def disp(self, key: str, who: str) -> np.ndarray:
        """The disparity ``key`` (N, H, W) px; ``ValueError`` naming ``who`` when it is absent."""
        d = self.disparity.get(key)
        if d is None:
            raise ValueError(
                f"the {who} reads the disparity {key!r}, which was not given "
                f"(given: {sorted(self.disparity) or 'none'})"
            )
        return d

    def memo(self, key: Hashable, make: Callable[[], np.ndarray]) -> np.ndarray:
        """``make()``, computed once per ``key`` for these frames."""
        if key not in self.derived:
            self.derived[key] = make()
        return self.derived[key]


class RiskPredictor(ABC):
    """The one ``predict`` of every risk predictor; subclasses give :meth:`predict_frames`."""

    def predict(
        self,
        left_bgr: np.ndarray | None = None,
        disp_sgm: np.ndarray | None = None,
        disp_gt: np.ndarray | None = None,
        speed: np.ndarray | None = None,
        batch_size: int = 256,
        *,
        disparity: Mapping[str, np.ndarray] | None = None,
    ) -> np.ndarray:
        """Predicted normalised risk (N,) float32 for raw frames (:class:`RiskFrames`), in
        batches of ``batch_size`` where the predictor batches. ``disparity`` gives further
        disparities by key (e.g. ``disp_learned``) beside ``disp_sgm`` / ``disp_gt``."""
        disp = {"disp_sgm": disp_sgm, "disp_gt": disp_gt, **(disparity or {})}
        return self.predict_frames(RiskFrames(left_bgr, disp, speed), batch_size)

    @abstractmethod
    def predict_frames(self, frames: RiskFrames, batch_size: int) -> np.ndarray:
        """Normalised risk (N,) float32 of ``frames``."""
