"""Scene primitives shared by the lidar, the stereo camera and the risk metric.

Everything in the world is an oriented 3D box standing on the ground plane z = 0 (or
lifted by ``z0``). Arrays are struct-of-arrays so ray casting and rasterising stay
vectorised. Units: metres, radians, m/s.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np

# pose maths live in traffictwin.geometry (below sim/ and evidential/); re-exported here
from traffictwin.geometry import relative_pose as relative_pose
from traffictwin.geometry import se2_matrix as se2_matrix


class Cls(IntEnum):
    """Class label of a box."""

    CAR = 0
    TRUCK = 1
    MOTORCYCLE = 2
    PEDESTRIAN = 3
    BUILDING = 4
    WALL = 5
    VEGETATION = 6
    POLE = 7


VEHICLE_CLASSES = (Cls.CAR, Cls.TRUCK, Cls.MOTORCYCLE)


@dataclass
class Boxes:
    """N oriented boxes in the world frame.

    center: (N, 2) x, y of the footprint centre (m); z0: (N,) bottom height (m);
    size: (N, 3) length (along heading), width, height (m); yaw: (N,) heading (rad);
    cls: (N,) int class (:class:`Cls`); velocity: (N, 2) world-frame velocity (m/s);
    ids: (N,) int identity, stable over time for moving agents.
    """

    center: np.ndarray
    size: np.ndarray
    yaw: np.ndarray
    cls: np.ndarray
    z0: np.ndarray = field(default=None)  # type: ignore[assignment]
    velocity: np.ndarray = field(default=None)  # type: ignore[assignment]
    ids: np.ndarray = field(default=None)  # type: ignore[assignment]

    def __post_init__(self) -> None:
        self.center = np.asarray(self.center, dtype=np.float64).reshape(-1, 2)
        n = len(self.center)
        self.size = np.asarray(self.size, dtype=np.float64).reshape(n, 3)
        self.yaw = np.asarray(self.yaw, dtype=np.float64).reshape(n)
        self.cls = np.asarray(self.cls, dtype=np.int64).reshape(n)
        self.z0 = (
            np.zeros(n) if self.z0 is None else np.asarray(self.z0, dtype=np.float64).reshape(n)
        )
        self.velocity = (
            np.zeros((n, 2))
            if self.velocity is None
            else np.asarray(self.velocity, dtype=np.float64).reshape(n, 2)
        )
        self.ids = (
            np.arange(n) if self.ids is None else np.asarray(self.ids, dtype=np.int64).reshape(n)
        )
        if np.any(self.size <= 0):
            raise ValueError("Boxes.size: every length, width and height must be > 0 m")

    def __len__(self) -> int:
        return len(self.center)

    @staticmethod
    def empty() -> Boxes:
        return Boxes(np.zeros((0, 2)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=np.int64))

    @staticmethod
    def concat(parts: list[Boxes]) -> Boxes:
        parts = [p for p in parts if len(p)]
        if not parts:
            return Boxes.empty()
        return Boxes(
            np.concatenate([p.center for p in parts]),
            np.concatenate([p.size for p in parts]),
            np.concatenate([p.yaw for p in parts]),
            np.concatenate([p.cls for p in parts]),
            z0=np.concatenate([p.z0 for p in parts]),
            velocity=np.concatenate([p.velocity for p in parts]),
            ids=np.concatenate([p.ids for p in parts]),
        )

    def subset(self, mask: np.ndarray) -> Boxes:
        return Boxes(
            self.center[mask],
            self.size[mask],
            self.yaw[mask],
            self.cls[mask],
            z0=self.z0[mask],
            velocity=self.velocity[mask],
            ids=self.ids[mask],
        )

    def corners(self) -> np.ndarray:
        """Footprint corners (N, 4, 2) in the world frame, counter-clockwise (m)."""
        hl, hw = self.size[:, 0] / 2, self.size[:, 1] / 2
        local = np.stack(
            [
                np.stack([hl, hw], -1),
                np.stack([-hl, hw], -1),
                np.stack([-hl, -hw], -1),
                np.stack([hl, -hw], -1),
            ],
            1,
        )
        c, s = np.cos(self.yaw)[:, None], np.sin(self.yaw)[:, None]
        x = c * local[..., 0] - s * local[..., 1] + self.center[:, None, 0]
        y = s * local[..., 0] + c * local[..., 1] + self.center[:, None, 1]
        return np.stack([x, y], -1)
