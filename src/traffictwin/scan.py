"""A lidar scan as data: what the simulator's lidar returns and the inverse sensor model reads.

It lives below ``sim/`` and ``evidential/`` so the evidential maths need not import the
simulator; ``traffictwin.sim.lidar`` and ``traffictwin.sim.raycast`` re-export these names.
Imports nothing from the package.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

#: ``hit`` code of a ray that hit the ground plane ``z = 0``
HIT_GROUND = -1
#: ``hit`` code of a ray that hit nothing within range
HIT_NOTHING = -2


class ScanSpec(Protocol):
    """What a scan needs of its sensor (``traffictwin.sim.lidar.LidarSpec`` is one)."""

    @property
    def height(self) -> float:
        """Sensor height above the ground (m)."""
        ...


@dataclass
class Scan:
    """One revolution: arrays of shape ``(n_azimuth, 32)`` (column-major in azimuth).

    ``range`` (m along the ray; ``max_range`` for no return), ``hit`` (box index in the boxes
    given to :func:`traffictwin.sim.lidar.scan`, -1 ground, -2 nothing), ``azimuth`` /
    ``elevation`` (rad, sensor frame).
    """

    range: np.ndarray
    hit: np.ndarray
    azimuth: np.ndarray
    elevation: np.ndarray
    spec: ScanSpec

    @property
    def points(self) -> np.ndarray:
        """Sensor-frame points (n_azimuth, 32, 3) (m; z above the ground under the sensor)."""
        r, a, e = self.range, self.azimuth, self.elevation
        ch = r * np.cos(e)
        return np.stack([ch * np.cos(a), ch * np.sin(a), self.spec.height + r * np.sin(e)], -1)

    @property
    def horizontal(self) -> np.ndarray:
        """Horizontal distance (m) of every return from the sensor."""
        return self.range * np.cos(self.elevation)
