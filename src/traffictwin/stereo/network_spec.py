"""The learned stereo network's architecture, :class:`StereoNetSpec` (disparities in
full-resolution px), without torch: :class:`~traffictwin.stereo.network.StereoNet` builds from it,
and ``check_params`` validates ``stereo_model.architecture`` with it before any stage runs.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

BASES = ("cost_volume", "sgm")


@dataclass(frozen=True)
class StereoNetSpec:
    """Architecture (disparities in full-resolution px)."""

    max_disparity: int = 48  # px at full resolution; the cost volume covers [0, max_disparity)
    stride: int = 2  # feature / cost-volume resolution: 1/stride (1, 2 or 4)
    feature_channels: int = 16
    groups: int = 4  # group-wise correlation: the cost volume has this many channels
    aggregation_channels: int = 8
    aggregation_layers: int = 3  # 3-D convolutions after the first
    refine_channels: int = 16
    refine_dilations: tuple[int, ...] = (1, 2, 4, 1)
    refine_stride: int = 2  # the refinement runs at 1/refine_stride resolution (1 or 2)
    # "cost_volume": the whole matcher above; "sgm": only the refinement, on an SGM disparity input,
    # adding a residual bounded by max_residual_px (px) on SGM's valid pixels
    base: str = "cost_volume"
    max_residual_px: float = 1.5
    # sgm mode, a local search around SGM's pixel-locked estimate (0 = none): the matching cost
    # mean_c |left - right warped by SGM + o| at o = k * local_cost_step_px, k = -offsets..offsets,
    # aggregated over a local_cost_window (px) box (learned), plus learned logits; the soft-argmin of
    # its negative adds a sub-pixel offset to SGM (the distribution's spread is reported, but it is no
    # confidence: peaked and wrong where SGM is off by more than the search reaches)
    local_cost_offsets: int = 0
    local_cost_step_px: float = 0.25
    local_cost_window: int = 7

    def __post_init__(self) -> None:
        from traffictwin.io.limits import check_at_most

        if self.base not in BASES:
            raise ValueError(f"StereoNetSpec.base must be one of {list(BASES)}, got {self.base!r}")
        if not isinstance(self.max_residual_px, (int, float)) or not (
            0.0 < float(self.max_residual_px) <= 8.0
        ):
            raise ValueError(
                f"StereoNetSpec.max_residual_px must be in (0, 8] px, got {self.max_residual_px!r}"
            )

        if self.stride not in (1, 2, 4):
            raise ValueError(f"StereoNetSpec.stride must be 1, 2 or 4, got {self.stride}")
        if self.refine_stride not in (1, 2) or self.refine_stride > self.stride:
            raise ValueError(
                f"StereoNetSpec.refine_stride must be 1 or 2 and <= stride ({self.stride}), "
                f"got {self.refine_stride}"
            )
        for k in (
            "max_disparity",
            "feature_channels",
            "groups",
            "aggregation_channels",
            "refine_channels",
        ):
            v = getattr(self, k)
            if not isinstance(v, int) or v < 1:
                raise ValueError(f"StereoNetSpec.{k} must be an integer >= 1, got {v!r}")
            check_at_most("StereoNetSpec", k, v, 512)
        if self.aggregation_layers < 0:
            raise ValueError(
                f"StereoNetSpec.aggregation_layers must be >= 0, got {self.aggregation_layers}"
            )
        check_at_most("StereoNetSpec", "aggregation_layers", self.aggregation_layers, 16)
        if self.max_disparity % self.stride or self.max_disparity // self.stride < 2:
            raise ValueError(
                f"StereoNetSpec.max_disparity ({self.max_disparity} px) must be a multiple of "
                f"stride ({self.stride}) with >= 2 cost-volume levels"
            )
        if self.feature_channels % self.groups:
            raise ValueError(
                f"StereoNetSpec.feature_channels ({self.feature_channels}) must be a multiple of "
                f"groups ({self.groups})"
            )
        dil = tuple(self.refine_dilations)
        if not dil or any(not isinstance(d, int) or not 1 <= d <= 64 for d in dil):
            raise ValueError(
                f"StereoNetSpec.refine_dilations must be 1..64 px each, at least one, got {list(dil)}"
            )
        check_at_most("StereoNetSpec", "refine_dilations (count)", len(dil), 16)
        k, step, win = self.local_cost_offsets, self.local_cost_step_px, self.local_cost_window
        if not isinstance(k, int) or not 0 <= k <= 16:
            raise ValueError(
                f"StereoNetSpec.local_cost_offsets must be an integer in [0, 16], got {k!r}"
            )
        if not isinstance(step, (int, float)) or not 0.0 < float(step) <= 2.0:
            raise ValueError(f"StereoNetSpec.local_cost_step_px must be in (0, 2] px, got {step!r}")
        if not isinstance(win, int) or not 1 <= win <= 31 or win % 2 == 0:
            raise ValueError(
                f"StereoNetSpec.local_cost_window must be an odd integer in [1, 31] px, got {win!r}"
            )

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> StereoNetSpec:
        """From a config / meta mapping (lists become tuples); unknown keys raise TypeError."""
        d = dict(d)
        if "refine_dilations" in d:
            d["refine_dilations"] = tuple(int(x) for x in d["refine_dilations"])
        return cls(**d)

    def as_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["refine_dilations"] = list(self.refine_dilations)
        return out

    @property
    def sgm_spread_bound_px(self) -> float:
        """sgm mode: the largest spread the network can report (px), so the threshold that keeps
        every SGM pixel: the local search's half-width, else the residual's bound."""
        if self.local_cost_offsets:
            return float(self.local_cost_offsets * self.local_cost_step_px)
        return float(self.max_residual_px)

    @property
    def levels(self) -> int:
        """Cost-volume disparity levels (at 1/stride resolution)."""
        return self.max_disparity // self.stride
