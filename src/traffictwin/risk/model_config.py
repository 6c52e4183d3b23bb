"""The ``risk_model`` config group (validated once by the stage with
:func:`traffictwin.config.typed`) and the optimisation settings it gives a variant
(:class:`TrainConfig`; paper sec. 3.5)."""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

from traffictwin.config import spec as setting
from traffictwin.risk.dave2_config import OBJECTIVES, Dave2Config

LABELS = (
    "risk",
    "risk_thw_corridor",
    "risk_thw_paper",
    "risk_thw_fov",
    "risk_ttc",
    "risk_wttc",
)
#: a run whose validation predictions spread less than this (std of the normalised risk) has
#: collapsed to a constant: it fails instead of being published
#: (:class:`~traffictwin.risk.training.CollapsedModelError`)
MIN_PRED_STD = 1e-3


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation settings (paper sec. 3.5: Adam, batch 10, 30 epochs, validation every 10 steps)."""

    epochs: int = 30
    batch_size: int = 10
    lr: float = 1e-4
    weight_decay: float = 0.0
    val_every_n_steps: int = 10
    limit_val_batches: int | float = 1.0
    eval_batch_size: int = 256
    seed: int = 0
    warmup_steps: int = 0
    bce_weight: float = 0.05
    min_pred_std: float = MIN_PRED_STD

    def __post_init__(self) -> None:
        for k in ("epochs", "batch_size", "val_every_n_steps", "eval_batch_size"):
            if int(getattr(self, k)) < 1:
                raise ValueError(f"TrainConfig.{k} must be >= 1, got {getattr(self, k)}")
        if not self.lr > 0:
            raise ValueError(f"TrainConfig.lr must be > 0, got {self.lr}")


# the ``risk_model`` config group (validated once by the stage with traffictwin.config.typed)


@dataclass
class VariantConfig:
    """``risk_model.variants.<name>``: input channel groups, speed input, label (None = ``label``),
    training objective (:data:`~traffictwin.risk.dave2_config.OBJECTIVES`), the seed offset added to the
    training seed, and ``replicate_of``: the variant this one repeats with another seed (None)."""

    inputs: list[str] = setting()  # checked by Dave2Config (rgb, disp_sgm, disp_gt)
    speed: bool = setting()
    label: str | None = setting(choices=(*LABELS, None))
    objective: str = setting(choices=tuple(OBJECTIVES))
    seed_offset: int = setting(min=0)
    replicate_of: str | None = setting()


@dataclass
class ObjectiveSchema:
    """``risk_model.objective``: the THW (s) that stands for "nothing ahead" in ``log_thw``, and
    the weight of the classification term and its THW threshold (s) in ``mse_bce``."""

    thw_cap_s: float = setting(min=0.1)
    bce_weight: float = setting(min=0.0)
    critical_thw_s: float = setting(min=0.1)


@dataclass
class RiskTrainSchema:
    """``risk_model.train``; ``limit_val_batches``: a batch count (int >= 1) or a fraction in (0, 1]."""

    epochs: int = setting(min=1)
    batch_size: int = setting(min=1)
    lr: float = setting(min=1e-12)
    weight_decay: float = setting(min=0.0)
    warmup_steps: int = setting(min=0)
    min_pred_std: float = setting(min=0.0)
    val_every_n_steps: int = setting(min=1)
    limit_val_batches: Any = setting()
    eval_batch_size: int = setting(min=1)
    max_train_frames: int | None = setting(min=1)
    seed_offset: int = setting(min=0)


@dataclass
class RiskModelConfig:
    """The ``risk_model`` group: the network (per variant) and its training."""

    orb_filter: bool = setting()
    label: str = setting(choices=LABELS)
    height: int = setting(min=1)
    width: int = setting(min=1)
    disp_scale: float = setting(min=1e-6)
    speed_scale: float = setting(min=1e-6)
    dropout: float = setting(min=0.0, max=0.99)
    objective: ObjectiveSchema = setting()
    train: RiskTrainSchema = setting()
    run_variants: list[str] = setting()
    variants: dict[str, VariantConfig] = setting()

    def __post_init__(self) -> None:
        unknown = [v for v in self.run_variants if v not in self.variants]
        if unknown:
            raise ValueError(
                f"run_variants {unknown} are not in variants (has {sorted(self.variants)})"
            )
        for name, v in self.variants.items():
            base = v.replicate_of
            if base is None:
                continue
            b = self.variants.get(base)
            if b is None or b.replicate_of is not None:
                raise ValueError(
                    f"variants.{name}.replicate_of must name a variant that is not itself a "
                    f"replicate, got {base!r}"
                )
            same = ("inputs", "speed", "label", "objective")
            diff = [k for k in same if getattr(v, k) != getattr(b, k)]
            if diff or v.seed_offset == b.seed_offset:
                raise ValueError(
                    f"variants.{name} replicates {base!r}: it must have the same {list(same)} "
                    f"(differs in {diff}) and another seed_offset"
                )

    def variant(self, name: str) -> tuple[Dave2Config, str]:
        """The network config and the training label of variant ``name``."""
        if name not in self.variants:
            raise KeyError(f"no variant {name!r} (has {sorted(self.variants)})")
        v = self.variants[name]
        cfg = Dave2Config(
            inputs=tuple(v.inputs),
            height=self.height,
            width=self.width,
            use_speed=v.speed,
            speed_scale=self.speed_scale,
            disp_scale=self.disp_scale,
            dropout=self.dropout,
            objective=v.objective,
            thw_cap_s=self.objective.thw_cap_s,
            critical_thw_s=self.objective.critical_thw_s,
        )
        return cfg, v.label or self.label

    def train_config(self, seed: int, variant: str | None = None) -> TrainConfig:
        """Optimisation settings; the seed is the global ``seed`` + ``train.seed_offset`` (+ the
        variant's ``seed_offset``).

        Raises ValueError when ``train.limit_val_batches`` is neither a batch count (int >= 1)
        nor a fraction in (0, 1].
        """
        t = self.train
        lvb = t.limit_val_batches
        if (
            isinstance(lvb, bool)
            or not isinstance(lvb, (int, float))
            or lvb <= 0
            or (isinstance(lvb, float) and lvb > 1)
        ):
            raise ValueError(
                "'train.limit_val_batches' must be a batch count (int >= 1) or a fraction"
                f" in (0, 1], got {lvb!r}"
            )
        same = {f.name for f in fields(TrainConfig)} - {"seed", "bce_weight"}
        extra = self.variants[variant].seed_offset if variant is not None else 0
        return TrainConfig(
            **{k: getattr(t, k) for k in same},
            seed=seed + t.seed_offset + extra,
            bce_weight=self.objective.bce_weight,
        )
