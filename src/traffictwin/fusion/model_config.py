"""Settings of the two fusion networks, the parameter groups ``fusion_model`` (the evidential
DeepLabV3+: :class:`FusionModelConfig`, its :class:`FusionHParams`, :func:`spec_from_cfg`) and
``registration_model`` (the learned registration: :class:`RegistrationModelConfig`).

Importable without torch or Lightning, and it validates the architectures without them too (the
networks' specs live in the torch-free :mod:`~traffictwin.fusion.deeplab_spec` and
:mod:`~traffictwin.fusion.registration_spec`; the data settings load inside :meth:`FusionModelConfig.data`):
``check_params`` validates every group before any stage runs, and its start-up is paid by each
`dvc repro`. The training itself: :mod:`traffictwin.fusion.training` and
:mod:`traffictwin.fusion.registration_training`.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import MISSING, asdict, dataclass, field, fields, make_dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from traffictwin.config import ConfigError
from traffictwin.config import spec as setting
from traffictwin.fusion.deeplab_spec import DeepLabSpec
from traffictwin.fusion.loss_registry import LOSSES
from traffictwin.fusion.registration_spec import RegistrationNetSpec

if TYPE_CHECKING:
    from traffictwin.fusion.training_data import DataSettings


# -- fusion_model -------------------------------------------------------------------------------
@dataclass(frozen=True)
class FusionHParams:
    """Optimisation and loss settings (paper IV: Adam lr 0.01, plateau decay 0.5 / patience 10, o_w 3)."""

    lr: float = 0.01
    weight_decay: float = 0.0
    lr_factor: float = 0.5
    lr_patience: int = 10
    loss: str = "mass"  # a registered loss (traffictwin.fusion.loss_registry.LOSSES)
    # its settings (the fields of its settings dataclass, fusion_model.loss.<loss>)
    loss_settings: dict[str, Any] = field(default_factory=lambda: {"occupied_weight": 3.0})
    augment_flip: bool = True
    augment_rotation_deg: float = 20.0
    channels_last: bool = (
        True  # NHWC activations: ~1.2-1.5x faster convolutions on oneDNN CPUs and tensor cores
    )


def spec_from_cfg(model_cfg: Mapping[str, Any], in_channels: int = 4) -> DeepLabSpec:
    """DeepLabSpec from the ``fusion_model.architecture`` mapping (``backbone: {block, layers, base_width}``, ...)."""
    d = json.loads(json.dumps(dict(model_cfg)))
    bb = dict(d.pop("backbone", {}))
    bb.setdefault("in_channels", in_channels)
    if "output_stride" in bb:
        os_ = int(bb.pop("output_stride"))
        if os_ not in (8, 16, 32):
            raise ValueError(f"backbone.output_stride must be 8, 16 or 32, got {os_}")
        bb["dilate"] = {
            8: [False, True, True],
            16: [False, False, True],
            32: [False, False, False],
        }[os_]
        if os_ == 8:
            d.setdefault("aspp_rates", [12, 24, 36])
    return DeepLabSpec.from_dict({**d, "backbone": bb})


@dataclass
class OptimConfig:
    """``fusion_model.optim``: Adam and the plateau decay of the learning rate."""

    lr: float = setting(min=1e-9)
    weight_decay: float = setting(min=0.0)
    lr_factor: float = setting(min=1e-6, max=1.0)
    lr_patience: int = setting(min=0)


def loss_schema() -> type:
    """The schema of ``fusion_model.loss`` from the registry as it is now: ``name`` (a registered
    loss) and one block per registered loss (its settings dataclass), every block required (a
    variant may train with any of them)."""
    blocks = [(n, loss.settings, setting()) for n, loss in LOSSES.items()]
    return make_dataclass("LossConfig", [("name", str, setting(choices=tuple(LOSSES))), *blocks])


@dataclass
class AugmentConfig:
    """``fusion_model.augment``: random flips and rotation (paper III-D)."""

    flip: bool = setting()
    rotation_deg: float = setting(min=0.0, max=180.0)


@dataclass
class FusionTrainConfig:
    """``fusion_model.train``: batches, epochs, stopping, memory format."""

    batch_size: int = setting(min=2)
    max_epochs: int = setting(min=1)
    train_samples_per_epoch: int = setting(min=0)
    val_samples: int = setting(min=0)
    early_stopping_patience: int = setting(min=1)
    early_stopping_min_delta: float = setting(min=0.0)
    gradient_clip_val: float | None = setting()
    channels_last: bool = setting()
    # added to the run's ``seed`` for this training only (initialisation, noise draws, batch
    # order); the data stays the same: the seed replicates of the fusion claims use 1, 2, ...
    seed_offset: int = setting(0, min=0)


@dataclass
class FusionModelConfig:
    """The ``fusion_model`` group: architecture (see :func:`spec_from_cfg`) and its training."""

    name: str = setting()
    architecture: dict[str, Any] = setting()
    optim: OptimConfig = setting()
    loss: Any = setting()  # checked against the registry's losses: a :func:`loss_schema` instance
    augment: AugmentConfig = setting()
    train: FusionTrainConfig = setting()

    def __post_init__(self) -> None:
        try:
            self.loss = OmegaConf.to_object(
                OmegaConf.merge(OmegaConf.structured(loss_schema()), self.loss)
            )
        except OmegaConfBaseException as exc:  # named from fusion_model's root, like the rest
            exc.full_key = f"loss.{exc.full_key}" if getattr(exc, "full_key", "") else "loss"
            raise

    def deeplab_spec(self, source: str | Path, key: str = "fusion_model") -> DeepLabSpec:
        """The network's :class:`DeepLabSpec`; an invalid architecture is a ConfigError."""
        try:
            return spec_from_cfg(self.architecture)
        except (TypeError, ValueError) as exc:
            full = f"{key}.architecture" if key else "architecture"
            raise ConfigError(f"{source}: '{full}' is invalid: {exc}") from None

    def hparams(self, loss: str | None = None) -> FusionHParams:
        """Optimisation and loss settings; ``loss`` overrides ``loss.name`` (a variant's loss)."""
        o, a = self.optim, self.augment
        name = loss or self.loss.name
        if name not in LOSSES or not hasattr(self.loss, name):
            raise ConfigError(f"unknown fusion loss {name!r}; expected one of {list(LOSSES)}")
        return FusionHParams(
            lr=o.lr,
            weight_decay=o.weight_decay,
            lr_factor=o.lr_factor,
            lr_patience=o.lr_patience,
            loss=name,
            loss_settings=asdict(getattr(self.loss, name)),
            augment_flip=a.flip,
            augment_rotation_deg=a.rotation_deg,
            channels_last=self.train.channels_last,
        )

    def data(self, num_workers: int) -> DataSettings:
        from traffictwin.fusion.training_data import DataSettings

        return _from_fields(DataSettings, self.train, num_workers=num_workers)

    def loop(self) -> LoopSettings:
        return _from_fields(LoopSettings, self.train)


@dataclass(frozen=True)
class LoopSettings:
    """Epochs and stopping: max_epochs; early_stopping_patience (epochs without val/kld_full improvement)."""

    max_epochs: int = 200
    early_stopping_patience: int = 30
    early_stopping_min_delta: float = 0.0  # val KLD(b) must fall by more than this to count
    gradient_clip_val: float | None = None


def _from_fields(cls: type, source: Any, **given: Any) -> Any:
    """``cls(**given)`` with every other field of ``cls`` taken from ``source``'s attribute of the same name."""
    names = {f.name for f in fields(cls)} - set(given)
    return cls(**{k: getattr(source, k) for k in names}, **given)


# -- registration_model ------------------------------------------------------------------------
@dataclass
class RegistrationTrainConfig:
    """``registration_model.train``."""

    batch_size: int = setting(MISSING, min=2)
    max_epochs: int = setting(MISSING, min=1)
    train_samples_per_epoch: int = setting(MISSING, min=0)
    val_samples: int = setting(MISSING, min=0)
    early_stopping_patience: int = setting(MISSING, min=1)
    lr: float = setting(MISSING, min=1e-9, max=1.0)
    weight_decay: float = setting(MISSING, min=0.0)
    augment_prob: float = setting(MISSING, min=0.0, max=1.0)
    augment_scale: float = setting(MISSING, min=0.0, max=10.0)
    map_weight: float = setting(MISSING, min=0.0)
    # added to the run's ``seed`` for this training only (the seed replicates use 1, 2, ...)
    seed_offset: int = setting(0, min=0)


@dataclass
class RegistrationModelConfig:
    """The ``registration_model`` group: the network (:class:`RegistrationNetSpec` fields), the
    fallback's ``min_gain`` and the training (one network per pose-noise configuration)."""

    architecture: dict[str, Any] = setting(MISSING)
    min_gain: float = setting(MISSING, min=-1.0, max=1.0)
    train: RegistrationTrainConfig = setting(MISSING)

    def net_spec(self, source: str, key: str = "registration_model") -> RegistrationNetSpec:
        try:
            return RegistrationNetSpec.from_dict(self.architecture)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"{source}: '{key}.architecture' is invalid: {exc}") from None
