"""Typed configuration of the risk problem: the ``risk_data`` and ``evaluation.risk`` groups.

Stages validate each group once at start with :func:`traffictwin.config.typed` (unknown, missing,
mistyped or out-of-range keys fail with a :class:`~traffictwin.config.ConfigError` naming the
dotted key) and hand the library these objects. The SGM and ORB settings (``risk_data.sgm``,
``risk_data.orb``) are the stereo package's :class:`~traffictwin.stereo.sgm.SgmParams` and
:class:`~traffictwin.stereo.orb.OrbParams`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from traffictwin.config import spec
from traffictwin.grid import GridSpec
from traffictwin.risk.baselines import GeometricParams
from traffictwin.risk.dataset import LABELS, RiskDataSpec
from traffictwin.risk.metric import RiskConfig
from traffictwin.sim.camera import StereoCamera
from traffictwin.sim.driving import MIN_TOP_SPEED, SITUATIONS, DrivingConfig
from traffictwin.stereo.check import StereoCheckParams
from traffictwin.stereo.orb import OrbParams
from traffictwin.stereo.sgm import SgmParams

#: most pixels along each side of the camera image (paper: 320 x 160; images beyond the CLI's
#: 4096 x 4096 read limit could not be assessed anyway)
MAX_IMAGE_SIDE = 4096
MAX_SEQUENCES = 1_000_000  # risk_data.sequences (paper: 13,769)
MAX_FRAMES_PER_SEQUENCE = 1_000  # risk_data.frames_per_sequence (paper: 8)


@dataclass
class CameraParams:
    """``risk_data.camera``: image size (px), field of view (deg), baseline and mount (m), range (m),
    sensor noise (DN)."""

    width: int = spec(min=16, max=MAX_IMAGE_SIDE)
    height: int = spec(min=16, max=MAX_IMAGE_SIDE)
    hfov_deg: float = spec(min=5, max=150)
    baseline: float = spec(min=0.01)
    mount_x: float = spec()
    mount_height: float = spec(min=0.1)
    max_range: float = spec(min=1)
    noise_std: float = spec(min=0)


@dataclass
class FaultParams:
    """``risk_data.faults``: shares of delayed / vertically misaligned right images, the delay (s)
    and the |misalignment| range (px, [low, high])."""

    delay_share: float = spec(min=0, max=1)
    vertical_share: float = spec(min=0, max=1)
    delay_s: float = spec(min=0)
    vertical_px: list[float] = spec()

    def __post_init__(self) -> None:
        if len(self.vertical_px) != 2 or not 0 <= self.vertical_px[0] <= self.vertical_px[1]:
            raise ValueError(
                f"'faults.vertical_px' must be [low, high] px with 0 <= low <= high, "
                f"got {list(self.vertical_px)}"
            )


@dataclass
class MetricParams:
    """``risk_data.metric``: the subject's footprint (m), the grid fill, whether pedestrians count,
    the corridor's margin beyond the lane on each side (m) and the THW horizon (s) that the grid
    must cover at the top speed (a longer look-ahead than the grid holds is a config error)."""

    subject_length: float = spec(min=0.5)
    subject_width: float = spec(min=0.3)
    fill: str = spec(choices=("border", "filled"))
    include_pedestrians: bool = spec()
    corridor_margin: float = spec(min=-1.0, max=3.0)
    horizon_s: float = spec(min=0.1)


@dataclass
class RiskDataConfig:
    """``risk_data``: the driving sequences, stereo camera, faults, risk metric, SGM and ORB check."""

    seed: int = spec(min=0)
    sequences: int = spec(min=1, max=MAX_SEQUENCES)
    frames_per_sequence: int = spec(min=1, max=MAX_FRAMES_PER_SEQUENCE)
    fps: float = spec(min=0.1)
    warmup: float = spec(min=0)
    max_speed: float = spec(min=MIN_TOP_SPEED)  # the situations draw speeds from 12 m/s up to it
    situations: dict[str, float] = spec()
    parked_prob: list[float] = spec()
    templates: list[str] = spec()
    label: str = spec(choices=LABELS)
    splits: list[float] = spec()
    workers: int = spec(min=1)
    compresslevel: int = spec(min=0, max=9)
    ground_res: float = spec(min=0.02, max=1.0)
    camera: CameraParams = spec()
    faults: FaultParams = spec()
    metric: MetricParams = spec()
    sgm: SgmParams = spec()
    orb: OrbParams = spec()
    check: StereoCheckParams = spec()

    def __post_init__(self) -> None:
        if len(self.splits) != 3:
            raise ValueError(
                f"'splits' must be 3 fractions (train, val, test), got {list(self.splits)}"
            )
        unknown = [k for k in self.situations if k not in SITUATIONS]
        if unknown:
            raise ValueError(
                f"'situations': unknown situation(s) {unknown}; expected some of {list(SITUATIONS)}"
            )
        w = [float(v) for v in self.situations.values()]
        if not w or min(w) < 0 or sum(w) <= 0:
            raise ValueError(
                f"'situations': weights must be >= 0 with a positive sum, got {dict(self.situations)}"
            )
        if len(self.parked_prob) != 2 or not 0 <= self.parked_prob[0] <= self.parked_prob[1] <= 1:
            raise ValueError(
                f"'parked_prob' must be [low, high] with 0 <= low <= high <= 1, got {list(self.parked_prob)}"
            )

    def check_grid(self, grid: GridSpec) -> None:
        """The risk grid must reach ``max_speed * metric.horizon_s`` ahead of the front bumper,
        else the label would silently miss objects: ConfigError naming the settings."""
        need = self.max_speed * self.metric.horizon_s + self.metric.subject_length / 2
        reach = grid.length / 2
        if need > reach:
            from traffictwin.config import ConfigError

            raise ConfigError(
                f"params.yaml: 'risk_data.max_speed' {self.max_speed} m/s x "
                f"'risk_data.metric.horizon_s' {self.metric.horizon_s} s needs the grid to reach "
                f"{need:.1f} m ahead of the reference point, but 'grid.rows' x 'grid.cell' "
                f"({grid.rows} x {grid.cell} m) reaches {reach:.2f} m: lower max_speed or horizon_s, "
                f"or enlarge the grid"
            )

    def data_seed(self, global_seed: int) -> int:
        """The dataset seed from the global ``seed`` and this group's ``seed`` offset."""
        return int(global_seed) + 1_000_003 * int(self.seed)

    def split_fractions(self) -> tuple[float, float, float]:
        a, b, c = (float(x) for x in self.splits)
        return a, b, c

    def data_spec(self, grid: GridSpec, critical_thw_s: float) -> RiskDataSpec:
        """The generation spec: driving config, camera, ``grid``, risk metric settings and the
        critical THW ``critical_thw_s`` (s; the primary ``evaluation.risk.thresholds_s``) (checks
        that ``grid`` covers the look-ahead, :meth:`check_grid`)."""
        self.check_grid(grid)
        c, f, m = self.camera, self.faults, self.metric
        cam = StereoCamera(
            width=c.width,
            height=c.height,
            hfov_deg=c.hfov_deg,
            baseline=c.baseline,
            mount_x=c.mount_x,
            mount_height=c.mount_height,
            max_range=c.max_range,
            noise_std=c.noise_std,
        )
        drv = DrivingConfig(
            fps=self.fps,
            frames=self.frames_per_sequence,
            warmup=self.warmup,
            max_speed=self.max_speed,
            situations=tuple((str(k), float(v)) for k, v in self.situations.items()),
            parked_prob=(float(self.parked_prob[0]), float(self.parked_prob[1])),
            templates=tuple(self.templates),
            fault_delay=f.delay_share,
            fault_vertical=f.vertical_share,
            delay=f.delay_s,
            vertical_px=(float(f.vertical_px[0]), float(f.vertical_px[1])),
        )
        risk = RiskConfig(
            subject_length=m.subject_length,
            subject_width=m.subject_width,
            hfov_deg=cam.hfov_deg,
            mount_x=cam.mount_x,
            fill=m.fill,
            include_pedestrians=m.include_pedestrians,
            corridor_margin=m.corridor_margin,
        )
        return RiskDataSpec(
            drv, cam, grid, risk, critical_thw_s, label=self.label, ground_res=self.ground_res
        )


@dataclass
class GeometricConfig:
    """``evaluation.risk.geometric``: the corridor rule (:class:`GeometricParams` without the
    subject footprint, which comes from ``risk_data.metric``). ``half_widths``: the candidate
    corridor half-widths (m); stage ``select_risk`` picks one per rule on the validation split."""

    half_widths: list[float] = spec()
    min_height: float = spec()
    max_height: float = spec()
    min_pixels: int = spec()
    max_range: float = spec()

    def __post_init__(self) -> None:
        if not self.half_widths or any(not w > 0 for w in self.half_widths):
            raise ValueError(
                f"'geometric.half_widths' must be a non-empty list of metres > 0, got {list(self.half_widths)}"
            )
        try:  # GeometricParams' own checks, at validation time
            self.params(1.0, 1.0)
        except ValueError as exc:
            raise ValueError(f"'geometric': {exc}") from None

    def params(
        self, subject_length: float, subject_width: float, half_width: float | None = None
    ) -> GeometricParams:
        """The rule's settings with corridor half-width ``half_width`` (m; default: the widest
        candidate)."""
        return GeometricParams(
            corridor_half_width=float(max(self.half_widths) if half_width is None else half_width),
            min_height=self.min_height,
            max_height=self.max_height,
            min_pixels=self.min_pixels,
            max_range=self.max_range,
            subject_length=subject_length,
            subject_width=subject_width,
        )


@dataclass
class EvalRiskConfig:
    """``evaluation.risk``: THW thresholds (s; the first is the primary), the THW error cap (s),
    the inference batch size, the headline variant (figures, targets, comparisons), the geometric
    baseline, the sequence bootstrap ``ci`` ({n_boot, seed, level}; checked by the stage against
    :class:`traffictwin.risk.evaluation.CIConfig`) and ``collapse_std``: a model whose test
    predictions have a smaller standard deviation (normalised risk) is a failed, collapsed run."""

    thresholds_s: list[float] = spec()
    thw_cap_s: float = spec(min=0.1)
    batch_size: int = spec(min=1)
    main_variant: str = spec()
    geometric: GeometricConfig = spec()
    ci: dict[str, Any] = spec()
    collapse_std: float = spec(min=0)

    def __post_init__(self) -> None:
        if not self.thresholds_s or any(t <= 0 for t in self.thresholds_s):
            raise ValueError(
                f"'thresholds_s' must be a non-empty list of positive seconds, got {list(self.thresholds_s)}"
            )
        if len(set(self.thresholds_s)) != len(self.thresholds_s):
            raise ValueError(
                f"'thresholds_s' must be distinct (each names its metrics, at_<t>s), got "
                f"{list(self.thresholds_s)}"
            )

    def check_variants(self, variants: list[str]) -> None:
        """``main_variant`` must be one of the evaluated variants (``risk_model.run_variants``)."""
        if self.main_variant not in variants:
            from traffictwin.config import ConfigError

            raise ConfigError(
                f"params.yaml: 'evaluation.risk.main_variant' must be one of {variants}, got {self.main_variant!r}"
            )
