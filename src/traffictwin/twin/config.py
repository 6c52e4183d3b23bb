"""Typed configuration of the twin (``twin`` of params.yaml; conf/twin/base.yaml documents every key)."""

from __future__ import annotations

from dataclasses import MISSING, dataclass, field
from typing import Any

from traffictwin.config import spec, typed
from traffictwin.stats import CIConfig
from traffictwin.twin.predict import PredictSettings

__all__ = ["TwinEvalSettings", "TwinFigureConfig", "TwinConfig", "twin_config"]


@dataclass(frozen=True)
class TwinEvalSettings:
    """Occupied-cell threshold on m_O, the ego's footprint margin (m), the critical THW (s), the
    reaction time (s: a map warns below ``critical_thw + reaction_s``), the corridor margin (m),
    strategy, the warning horizon (s: a warning up to this long before a critical episode is an
    early warning of it, one with no episode within it a false alarm), bootstrap resamples / seed
    / level."""

    occ_threshold: float = 0.5
    self_margin: float = 0.5
    critical_thw: float = field(kw_only=True)
    reaction_s: float = 0.0
    corridor_margin: float = 0.0
    strategy: str = "reference"
    horizon_s: float = 2.0
    predict: PredictSettings = field(kw_only=True)  # TTC (predictive warnings)
    n_boot: int = 2000
    seed: int = 0
    level: float = 0.95

    @property
    def warn_thw(self) -> float:
        """THW (s) below which a map warns: ``critical_thw + reaction_s``."""
        return self.critical_thw + self.reaction_s


@dataclass
class TwinFigureConfig:
    sequence: int | None = spec(MISSING, min=0)


@dataclass
class TwinConfig:
    """``twin``: the cooperative sequences (stage generate_twin) and the twin's evaluation (evaluate_twin)."""

    sequences: int = spec(MISSING, min=2, max=100_000)  # paper: 200 (each one a shard)
    # sequences of the validation split (indices after the evaluated ones): the predictive rule is
    # chosen on them (0: no choice, the configured level unconfirmed)
    validation_sequences: int = spec(MISSING, min=0, max=100_000)
    frames: int = spec(MISSING, min=2, max=10_000)  # paper: 50 (a shard holds every frame's maps)
    fps: float = spec(MISSING, min=0.1)
    vehicles: int = spec(MISSING, min=2, max=16)
    occluded_share: float = spec(MISSING, min=0.0, max=1.0)
    pedestrian_share: float = spec(MISSING, min=0.0, max=1.0)
    emerging_car_share: float = spec(MISSING, min=0.0, max=1.0)
    templates: list[str] = spec(MISSING)
    lead_in: list[float] = spec(MISSING)  # (low, high) s from the sequence start to the onset
    hidden_s: float = spec(MISSING, min=0.0, max=10.0)
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
    horizon_s: float = spec(MISSING, min=0.0, max=10.0)
    ttc_warn_s: float = spec(MISSING, min=0.1, max=10.0)
    ttc_warn_candidates: list[float] = spec(MISSING)  # s, each <= ttc_warn_s (chosen on validation)
    ttc_confirm_candidates: list[int] = spec(MISSING)  # consecutive frames (chosen on validation)
    # s: a warning comes this long before the critical threshold (a driver's reaction time)
    reaction_s: float = spec(MISSING, min=0.0, max=5.0)
    ttc_step_s: float = spec(MISSING, min=0.01, max=1.0)
    motion_min_speed: float = spec(MISSING, min=0.0, max=10.0)
    motion_max_speed: float = spec(MISSING, min=0.1, max=60.0)
    motion_max_extent: float = spec(MISSING, min=0.5, max=50.0)
    bias_share: float = spec(MISSING, min=0.0, max=1.0)
    bias_kinds: list[str] = spec(MISSING)  # kinds evaluated under the persistent bias ([] = none)
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
        from traffictwin.sim.cooperative import KINDS

        bad = [k for k in self.bias_kinds if k not in KINDS]
        if bad:
            raise ValueError(
                f"'twin.bias_kinds' has unknown kind(s) {bad}; expected from {list(KINDS)}"
            )
        if self.motion_min_speed >= self.motion_max_speed:
            raise ValueError(
                f"'twin.motion_min_speed' ({self.motion_min_speed}) must be below "
                f"'twin.motion_max_speed' ({self.motion_max_speed}) m/s"
            )
        if self.reaction_s > self.horizon_s:
            raise ValueError(
                f"'twin.reaction_s' ({self.reaction_s} s) must not exceed 'twin.horizon_s' "
                f"({self.horizon_s} s): a warning that early would count as a false alarm"
            )
        if self.pedestrian_share + self.emerging_car_share > 1.0:
            raise ValueError(
                f"'twin.pedestrian_share' + 'twin.emerging_car_share' must be <= 1 (the rest are "
                f"stopped cars), got {self.pedestrian_share} + {self.emerging_car_share}"
            )
        if len(self.lead_in) != 2 or not 0 < self.lead_in[0] <= self.lead_in[1]:
            raise ValueError(
                f"'twin.lead_in' must be [low, high] s with 0 < low <= high, got {list(self.lead_in)}"
            )
        bad = [w for w in self.ttc_warn_candidates if not 0 < w <= self.ttc_warn_s]
        if bad or not self.ttc_warn_candidates:
            raise ValueError(
                f"'twin.ttc_warn_candidates' must be levels in (0, 'twin.ttc_warn_s' = "
                f"{self.ttc_warn_s}] s (the TTC is computed up to that), got {list(self.ttc_warn_candidates)}"
            )
        if not self.ttc_confirm_candidates or min(self.ttc_confirm_candidates) < 1:
            raise ValueError(
                f"'twin.ttc_confirm_candidates' must be frame counts >= 1, got "
                f"{list(self.ttc_confirm_candidates)}"
            )
        if self.hidden_s >= self.frames / self.fps:
            raise ValueError(
                f"'twin.hidden_s' ({self.hidden_s} s) must be shorter than a sequence "
                f"('twin.frames' / 'twin.fps' = {self.frames / self.fps:g} s)"
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
            emerging_car_share=self.emerging_car_share,
            templates=tuple(self.templates),
            lead_in=(float(self.lead_in[0]), float(self.lead_in[1])),
            hidden_s=self.hidden_s,
            critical_thw=self.critical_thw,
        )

    def predict(self) -> PredictSettings:
        """The predictive measure's :class:`~traffictwin.twin.predict.PredictSettings`: a map warns
        when its TTC is below ``ttc_warn_s + reaction_s``, computed up to that or ``horizon_s``."""
        warn_s = self.ttc_warn_s + self.reaction_s
        return PredictSettings(
            min_speed=self.motion_min_speed,
            max_speed=self.motion_max_speed,
            max_extent=self.motion_max_extent,
            step_s=self.ttc_step_s,
            horizon_s=max(self.horizon_s, warn_s),
            warn_s=warn_s,
        )

    def settings(self) -> Any:
        """The evaluation's :class:`TwinEvalSettings`."""
        return TwinEvalSettings(
            occ_threshold=self.occ_threshold,
            self_margin=self.self_margin,
            critical_thw=self.critical_thw,
            reaction_s=self.reaction_s,
            corridor_margin=self.corridor_margin,
            strategy=self.strategy,
            horizon_s=self.horizon_s,
            predict=self.predict(),
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
