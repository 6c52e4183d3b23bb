"""The learned registration network's architecture and search grid, :class:`RegistrationNetSpec`,
without torch: :class:`~traffictwin.fusion.learned_registration.LearnedRegistration` builds from it,
and ``check_params`` validates ``registration_model.architecture`` with it before any stage runs.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class RegistrationNetSpec:
    """Architecture and search grid (units in the names; pixels are full-resolution cells)."""

    coarse_stride: int = 4  # the coarse features' cell is coarse_stride cells (1, 2, 4 or 8)
    coarse_channels: int = 8  # feature channels correlated by the coarse stage
    coarse_width: int = 16  # hidden channels of the coarse encoder
    fine_stride: int = 2  # the fine features' cell is fine_stride cells (1, 2, 4 or 8)
    fine_channels: int = 8  # feature channels of the fine stage
    fine_width: int = 16
    max_rot_deg: float = 26.0  # coarse angle grid ±max_rot_deg …
    rot_step_deg: float = 2.0  # … in steps of rot_step_deg
    max_shift_m: float = 8.0  # coarse shifts within ±max_shift_m per axis
    fine_max_rot_deg: float = 1.5
    fine_rot_step_deg: float = 0.5
    fine_max_shift_px: int = 3  # fine shifts within ±fine_max_shift_px feature cells per axis
    fine_iterations: int = (
        1  # fine steps (warp by the estimate, predict the residual), same weights
    )

    def __post_init__(self) -> None:
        for k, v in asdict(self).items():
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"RegistrationNetSpec.{k} must be a finite number > 0, got {v!r}")
        for k in ("coarse_stride", "fine_stride"):
            if getattr(self, k) not in (1, 2, 4, 8):
                raise ValueError(
                    f"RegistrationNetSpec.{k} must be 1, 2, 4 or 8, got {getattr(self, k)}"
                )
        from traffictwin.io.limits import check_at_most

        # architecture values come from model meta: bounded before any layer or search grid is built
        for k in ("coarse_channels", "coarse_width", "fine_channels", "fine_width"):
            check_at_most("RegistrationNetSpec", k, getattr(self, k), 1024)
        for k in ("max_rot_deg", "fine_max_rot_deg"):
            check_at_most("RegistrationNetSpec", k, getattr(self, k), 180.0)
        check_at_most("RegistrationNetSpec", "max_shift_m", self.max_shift_m, 100.0)
        check_at_most("RegistrationNetSpec", "fine_max_shift_px", self.fine_max_shift_px, 64)
        check_at_most("RegistrationNetSpec", "fine_iterations", self.fine_iterations, 16)
        for top, step in (
            ("max_rot_deg", "rot_step_deg"),
            ("fine_max_rot_deg", "fine_rot_step_deg"),
        ):
            n = 2 * getattr(self, top) / getattr(self, step) + 1
            check_at_most("RegistrationNetSpec", f"{top} / {step} (candidate angles)", n, 3601)

    def angles(self, fine: bool = False) -> np.ndarray:
        """Candidate angles (deg) of the coarse or fine grid."""
        top, step = (
            (self.fine_max_rot_deg, self.fine_rot_step_deg)
            if fine
            else (self.max_rot_deg, self.rot_step_deg)
        )
        k = int(math.floor(top / step + 1e-9))
        return np.arange(-k, k + 1) * step

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> RegistrationNetSpec:
        return cls(**dict(d))
