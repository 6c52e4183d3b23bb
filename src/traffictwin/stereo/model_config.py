"""Settings of the learned stereo network, the parameter group ``stereo_model``
(:class:`StereoModelConfig`): importable without torch or Lightning (the network's spec lives in
the torch-free :mod:`~traffictwin.stereo.network_spec`), so that ``check_params``, which validates every group
before any stage runs, starts quickly. The training: :mod:`traffictwin.risk.stereo_training`.
"""

from __future__ import annotations

from dataclasses import MISSING, dataclass
from typing import Any

from traffictwin.config import ConfigError
from traffictwin.config import spec as setting
from traffictwin.stereo.network_spec import StereoNetSpec


@dataclass
class StereoTrainConfig:
    """``stereo_model.train``."""

    batch_size: int = setting(MISSING, min=1)
    crop_height: int = setting(MISSING, min=16)
    crop_width: int = setting(MISSING, min=16)
    max_epochs: int = setting(MISSING, min=1)
    steps_per_epoch: int = setting(MISSING, min=1)
    max_train_frames: int = setting(MISSING, min=0)  # 0 = every fault-free training frame
    val_frames: int = setting(MISSING, min=1)
    early_stopping_patience: int = setting(MISSING, min=1)
    lr: float = setting(MISSING, min=1e-9, max=1.0)
    #: the learning rate x lr_factor after lr_patience epochs without a val/epe improvement
    lr_factor: float = setting(MISSING, min=1e-6, max=1.0)
    lr_patience: int = setting(MISSING, min=0)
    weight_decay: float = setting(MISSING, min=0.0)
    rel_weight: float = setting(MISSING, min=0.0)
    coarse_weight: float = setting(MISSING, min=0.0)
    valid_density: float = setting(MISSING, min=0.05, max=1.0)


@dataclass
class StereoModelConfig:
    """The ``stereo_model`` group: the architecture (:class:`StereoNetSpec` fields) and training."""

    architecture: dict[str, Any] = setting(MISSING)
    train: StereoTrainConfig = setting(MISSING)
    #: road templates the generalisation model never sees (stage train_stereo_holdout)
    holdout_templates: list[str] = setting(MISSING)

    def net_spec(self, source: str, key: str = "stereo_model") -> StereoNetSpec:
        """The validated architecture; the training crop must be wider than ``max_disparity``."""
        try:
            s = StereoNetSpec.from_dict(self.architecture)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"{source}: '{key}.architecture' is invalid: {exc}") from None
        t = self.train
        if t.crop_width <= s.max_disparity:
            raise ConfigError(
                f"{source}: '{key}.train.crop_width' ({t.crop_width} px) must exceed "
                f"'{key}.architecture.max_disparity' ({s.max_disparity} px)"
            )
        for k in ("crop_height", "crop_width"):
            if getattr(t, k) % s.stride:
                raise ConfigError(
                    f"{source}: '{key}.train.{k}' ({getattr(t, k)} px) must be a multiple of "
                    f"'{key}.architecture.stride' ({s.stride})"
                )
        return s
