"""Typed configuration of the ``registry`` group (promotion gate and scheduled retraining).

Validated once at the start of ``pipelines/promote.py`` and ``pipelines/retrain.py`` with
``traffictwin.config.typed(cfg.registry, RegistryConfig, key="registry")``. Folders of data and
models are not here: the workflow layer derives them (``pipelines/_paths.py``); the fusion
one fusion network and the one learned registration are gated on every configuration (the keys
of ``configurations``), the learned stereo network on validation pairs, and the risk variant must be ``shipped`` (models/risk_shipped) or one of
``risk_model.run_variants``. :func:`seed_overrides` and :func:`compose_with_seeds` are the
retraining's new data batch: its seed keys moved on, as Hydra overrides of conf/.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from traffictwin.config import ConfigError, compose_config, get, spec
from traffictwin.mlops.gate import Gate

MODES = ("min", "max")


@dataclass
class AliasesConfig:
    champion: str  # the version inference uses by default
    challenger: str  # the newest registered candidate


@dataclass
class GateConfig:
    """What every gate has: the test split, the evaluation batch size and the :class:`Gate`."""

    split: str
    batch_size: int = spec(min=1)
    metric: str = spec()
    mode: str = spec(choices=MODES)
    margin: float = spec(min=0.0)

    def gate(self) -> Gate:
        return Gate(self.metric, self.mode, self.margin)  # type: ignore[arg-type]


@dataclass
class FusionGateConfig(GateConfig):
    """Registered model ``name``: the one fusion network (or learned registration), gated on the
    first ``max_pairs`` pairs (by pair id) of split ``split`` of every configuration."""

    name: str = spec()
    max_pairs: int | None = spec()  # first K pairs by pair_id per configuration; None = all


@dataclass
class RiskGateConfig(GateConfig):
    """Registered model ``name``: the risk network of variant ``variant``."""

    name: str = spec()
    variant: str = (
        spec()
    )  # shipped (the predictor chosen on validation) or one of risk_model.run_variants
    max_frames: int | None = spec()  # first K test frames by frame id; None = all


@dataclass
class StereoGateConfig(GateConfig):
    """Registered model ``name``: the learned stereo network, gated on ``max_frames`` evenly
    spaced fault-free pairs of split ``split`` (None = all)."""

    name: str = spec()
    max_frames: int | None = spec()


@dataclass
class RetrainConfig:
    lock: str  # fcntl lock file (relative to the repository)
    seed_keys: list[str]  # params keys bumped for a new data batch (top-level or <group>.<key>)
    seed_step: int = spec(min=1)
    summary: str = spec()  # base name of the .json and .md summary


@dataclass
class RegistryConfig:
    aliases: AliasesConfig
    log: str  # promotion log: one JSON line per decision / rollback
    fusion: FusionGateConfig
    registration: FusionGateConfig
    risk: RiskGateConfig
    stereo: StereoGateConfig
    retrain: RetrainConfig


def seed_overrides(cfg, keys: list[str], step: int, seed: int | None) -> dict[str, tuple[int, int]]:
    """``{key: (old, new)}`` for every seed key: new = ``seed`` if given, else old + ``step``."""
    olds = {k: get(cfg, k, int) for k in keys}
    return {k: (old, seed if seed is not None else old + step) for k, old in olds.items()}


def compose_with_seeds(
    conf: Path, profile: str, seeds: dict[str, tuple[int, int]]
) -> tuple[dict[str, Any], list[str]]:
    """params composed from ``conf`` with ``profile=<profile>`` and ``<key>=<new>`` overrides, and the
    overrides; error if a seed does not compose to its new value (e.g. fixed by the profile)."""
    overrides = [f"profile={profile}", *(f"{k}={new}" for k, (_, new) in seeds.items())]
    composed = compose_config(conf, overrides)
    for k, (_, new) in seeds.items():
        if (got := get(composed, k, int)) != new:
            raise ConfigError(
                f"conf/: '{k}' composes to {got}, not the new seed {new} (overridden by profile '{profile}'?)"
            )
    return composed, overrides
