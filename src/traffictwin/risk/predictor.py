"""The one interface of every risk predictor (:class:`RiskPredictor`: the network
:class:`~traffictwin.risk.model_io.RiskModel`, the corridor rule and hybrid of
:mod:`traffictwin.risk.predictors`) and the raw frames it reads (:class:`RiskFrames`)."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class RiskFrames:
    """Raw frames a risk predictor reads, each optional: ``left_bgr`` (N, H, W, 3) uint8,
    ``disp_sgm`` / ``disp_gt`` (N, H, W) disparity px, ``speed`` (N,) subject speed m/s."""

    left_bgr: np.ndarray | None = None
    disp_sgm: np.ndarray | None = None
    disp_gt: np.ndarray | None = None
    speed: np.ndarray | None = None


class RiskPredictor(ABC):
    """The one ``predict`` of every risk predictor; subclasses give :meth:`predict_frames`."""

    def predict(
        self,
        left_bgr: np.ndarray | None = None,
        disp_sgm: np.ndarray | None = None,
        disp_gt: np.ndarray | None = None,
        speed: np.ndarray | None = None,
        batch_size: int = 256,
    ) -> np.ndarray:
        """Predicted normalised risk (N,) float32 for raw frames (:class:`RiskFrames`), in
        batches of ``batch_size`` where the predictor batches."""
        return self.predict_frames(RiskFrames(left_bgr, disp_sgm, disp_gt, speed), batch_size)

    @abstractmethod
    def predict_frames(self, frames: RiskFrames, batch_size: int) -> np.ndarray:
        """Normalised risk (N,) float32 of ``frames``."""
