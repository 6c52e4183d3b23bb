"""Typed configuration of the risk problem: the ``risk_data`` and ``evaluation.risk`` groups.

Stages validate each group once at start with :func:`traffictwin.config.typed` (unknown, missing,
mistyped or out-of-range keys fail with a :class:`~traffictwin.config.ConfigError` naming the
dotted key) and hand the library these objects. The SGM and ORB settings (``risk_data.sgm``,
``risk_data.orb``) are the stereo package's :class:`~traffictwin.stereo.sgm.SgmParams` and
:class:`~traffictwin.stereo.orb.OrbParams`.
"""

from __future__ import annotations

from dataclasses import dataclass

from traffictwin.config import spec
from traffictwin.grid import GridSpec
from traffictwin.risk.baselines import GeometricParams
from traffictwin.risk.dataset import LABELS, RiskDataSpec
from traffictwin.risk.metric import RiskConfig
from traffictwin.sim.camera import StereoCamera
from traffictwin.sim.driving import DrivingConfig
from traffictwin.stereo.check import StereoCheckParams
from traffictwin.stereo.orb import OrbParams
from traffictwin.stereo.sgm import SgmParams


@dataclass
class CameraParams:
    """``risk_data.camera``: image size (px), field of view (deg), baseline and mount (m), range (m),
    sensor noise (DN)."""

    width: int = spec(min=16)
    height: int = spec(min=16)
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
        if len(self.vertical_px) != 2:
            raise ValueError(
                f"'faults.vertical_px' must be [low, high] px, got {list(self.vertical_px)}"
            )


@dataclass
class MetricParams:
    """``risk_data.metric``: the subject's footprint (m), the grid fill and whether pedestrians count."""

    subject_length: float = spec(min=0.5)
    subject_width: float = spec(min=0.3)
    fill: str = spec(choices=("border", "filled"))
    include_pedestrians: bool = spec()


@dataclass
class RiskDataConfig:
    """``risk_data``: the driving sequences, stereo camera, faults, risk metric, SGM and ORB check."""

    seed: int = spec(min=0)
    sequences: int = spec(min=1)
    frames_per_sequence: int = spec(min=1)
    fps: float = spec(min=0.1)
    warmup: float = spec(min=0)
    max_speed: float = spec(min=1)
    critical_share: float = spec(min=0, max=1)
    templates: list[str] = spec()
    label: str = spec(choices=LABELS)
    splits: list[float] = spec()
    workers: int = spec(min=1)
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

    def data_seed(self, global_seed: int) -> int:
        """The dataset seed from the global ``seed`` and this group's ``seed`` offset."""
        return int(global_seed) + 1_000_003 * int(self.seed)

    def split_fractions(self) -> tuple[float, float, float]:
        a, b, c = (float(x) for x in self.splits)
        return a, b, c

    def data_spec(self, grid: GridSpec) -> RiskDataSpec:
        """The generation spec: driving config, camera, ``grid`` and risk metric settings."""
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
            critical_share=self.critical_share,
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
        )
        return RiskDataSpec(drv, cam, grid, risk, label=self.label, ground_res=self.ground_res)


@dataclass
class GeometricConfig:
    """``evaluation.risk.geometric``: the corridor baseline (:class:`GeometricParams` without the
    subject footprint, which comes from ``risk_data.metric``)."""

    corridor_half_width: float = spec()
    min_height: float = spec()
    max_height: float = spec()
    min_pixels: int = spec()
    max_range: float = spec()

    def __post_init__(self) -> None:
        try:  # GeometricParams' own checks, at validation time
            self.params(1.0, 1.0)
        except ValueError as exc:
            raise ValueError(f"'geometric': {exc}") from None

    def params(self, subject_length: float, subject_width: float) -> GeometricParams:
        return GeometricParams(
            corridor_half_width=self.corridor_half_width,
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
    the inference batch size, the variant shown in the figures and the geometric baseline."""

    thresholds_s: list[float] = spec()
    thw_cap_s: float = spec(min=0.1)
    batch_size: int = spec(min=1)
    main_variant: str = spec()
    geometric: GeometricConfig = spec()

    def __post_init__(self) -> None:
        if not self.thresholds_s or any(t <= 0 for t in self.thresholds_s):
            raise ValueError(
                f"'thresholds_s' must be a non-empty list of positive seconds, got {list(self.thresholds_s)}"
            )

    def check_variants(self, variants: list[str]) -> None:
        """``main_variant`` must be one of the evaluated variants (``risk_model.run_variants``)."""
        if self.main_variant not in variants:
            from traffictwin.config import ConfigError

            raise ConfigError(
                f"params.yaml: 'evaluation.risk.main_variant' must be one of {variants}, got {self.main_variant!r}"
            )
