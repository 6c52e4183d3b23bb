"""Typed configuration of the twin (``twin`` of params.yaml; conf/twin/base.yaml documents every key)."""

from __future__ import annotations

from dataclasses import MISSING, dataclass
from typing import Any

from traffictwin.config import spec, typed
from traffictwin.stats import CIConfig

__all__ = ["TwinEvalSettings", "TwinFigureConfig", "TwinConfig", "twin_config"]


@dataclass(frozen=True)
class TwinEvalSettings:
    """Occupied-cell threshold on m_O, the ego's footprint margin (m), the critical THW (s), the
    corridor margin (m), strategy, bootstrap resamples / seed / level."""

    occ_threshold: float = 0.5
    self_margin: float = 0.5
    critical_thw: float = 1.5
    corridor_margin: float = 0.0
    strategy: str = "reference"
    n_boot: int = 2000
    seed: int = 0
    level: float = 0.95


@dataclass
class TwinFigureConfig:
    sequence: int | None = spec(MISSING, min=0)


@dataclass
class TwinConfig:
    """``twin``: the cooperative sequences (stage generate_twin) and the twin's evaluation (evaluate_twin)."""

    sequences: int = spec(MISSING, min=2)
    frames: int = spec(MISSING, min=2)
    fps: float = spec(MISSING, min=0.1)
    vehicles: int = spec(MISSING, min=2, max=16)
    occluded_share: float = spec(MISSING, min=0.0, max=1.0)
    pedestrian_share: float = spec(MISSING, min=0.0, max=1.0)
    templates: list[str] = spec(MISSING)
    workers: int = spec(MISSING, min=1)
    compresslevel: int = spec(MISSING, min=0, max=9)
    corridor_margin: float = spec(MISSING, min=-1.0, max=3.0)
    methods: list[str] = spec(MISSING)
    headline: str = MISSING
    target_configuration: str = MISSING
    configurations: list[str] | None = spec(MISSING)  # evaluated (None: every one)
    strategy: str = spec(MISSING, choices=("reference", "sequential"))
    occ_threshold: float = spec(MISSING, min=0.0, max=1.0)
    self_margin: float = spec(MISSING, min=0.0, max=3.0)
    critical_thw: float = spec(MISSING, min=0.1, max=10.0)
    ci: CIConfig = MISSING
    figure: TwinFigureConfig = MISSING

    def __post_init__(self) -> None:
        from traffictwin.sim.cooperative import JUNCTIONS
        from traffictwin.twin.methods import TWIN_METHODS

        bad = [m for m in self.methods if m not in TWIN_METHODS]
        if bad or not self.methods:
            raise ValueError(
                f"'twin.methods' has unknown method(s) {bad or '(empty)'}; expected from {list(TWIN_METHODS)}"
            )
        if self.headline not in self.methods:
            raise ValueError(
                f"'twin.headline' ({self.headline!r}) must be one of 'twin.methods' {self.methods}"
            )
        if self.configurations is not None and self.target_configuration not in self.configurations:
            raise ValueError(
                f"'twin.target_configuration' ({self.target_configuration!r}) must be one of "
                f"'twin.configurations' {self.configurations}"
            )
        bad = [t for t in self.templates if t not in JUNCTIONS]
        if bad or not self.templates:
            raise ValueError(
                f"'twin.templates' has unknown junction(s) {bad or '(empty)'}; expected from {list(JUNCTIONS)}"
            )

    def scenario(self) -> Any:
        """The simulator's :class:`~traffictwin.sim.cooperative.CooperativeConfig`."""
        from traffictwin.sim.cooperative import CooperativeConfig

        return CooperativeConfig(
            fps=self.fps,
            frames=self.frames,
            vehicles=self.vehicles,
            occluded_share=self.occluded_share,
            pedestrian_share=self.pedestrian_share,
            templates=tuple(self.templates),
        )

    def settings(self) -> Any:
        """The evaluation's :class:`TwinEvalSettings`."""
        return TwinEvalSettings(
            occ_threshold=self.occ_threshold,
            self_margin=self.self_margin,
            critical_thw=self.critical_thw,
            corridor_margin=self.corridor_margin,
            strategy=self.strategy,
            n_boot=self.ci.n_boot,
            seed=self.ci.seed,
            level=self.ci.level,
        )


def twin_config(cfg: Any) -> TwinConfig:
    """``twin`` of params.yaml, checked (errors name the dotted key); ``configurations`` must be
    keys of ``configurations``."""
    from traffictwin.config import ConfigError

    tc = typed(cfg["twin"], TwinConfig, key="twin")
    known = list(cfg["configurations"]) if "configurations" in cfg else []
    bad = [c for c in tc.configurations or () if c not in known]
    if bad:
        raise ConfigError(
            f"params.yaml: 'twin.configurations' has {bad}, not keys of 'configurations' ({known})"
        )
    return tc
