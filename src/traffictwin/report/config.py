"""Schema of the parameters the report stage shows (validated once at stage start with
:func:`traffictwin.config.typed`)."""

from __future__ import annotations

from dataclasses import dataclass

from traffictwin.config import spec
from traffictwin.evidential.noise import PoseNoise


@dataclass
class Profile:
    name: str
    banner: str = ""  # "ci profile: a smoke run; ..." on a smoke profile, shown first everywhere


@dataclass
class ReportParams:
    """``seed``, ``profile`` and ``configurations`` of params.yaml."""

    seed: int = spec(min=0)
    profile: Profile
    configurations: dict[str, PoseNoise]

    @property
    def pose_noise(self) -> dict[str, tuple[float, float]]:
        """``{name: (r m, alpha deg)}`` in params order."""
        return {str(n): (c.r, c.alpha) for n, c in self.configurations.items()}
