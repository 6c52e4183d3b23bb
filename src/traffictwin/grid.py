"""Grid geometry shared by the fusion and risk parts (docs/design.md "Grid").

A grid is ``rows x cols`` cells of ``cell`` metres, the sensor at the centre.
Array index ``[row, col]``: row 0 is the front-most (+x, vehicle forward), col 0 the
left-most (+y). Cell ``(r, c)`` has its centre at
``x = (rows/2 - r - 0.5) * cell``, ``y = (cols/2 - c - 0.5) * cell`` in the sensor frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class GridSpec:
    """Shape (cells) and resolution (m/cell) of a vehicle-centred grid map."""

    rows: int = 256
    cols: int = 176
    cell: float = 0.32

    def __post_init__(self) -> None:
        if self.rows <= 0 or self.cols <= 0:
            raise ValueError(
                f"grid rows/cols must be positive, got rows={self.rows}, cols={self.cols}"
            )
        if self.cell <= 0:
            raise ValueError(f"grid cell size must be positive (m), got cell={self.cell}")

    @property
    def shape(self) -> tuple[int, int]:
        return (self.rows, self.cols)

    @property
    def length(self) -> float:
        """Extent along x (m)."""
        return self.rows * self.cell

    @property
    def width(self) -> float:
        """Extent along y (m)."""
        return self.cols * self.cell

    def check_divisible(self, factor: int = 16, name: str = "grid") -> None:
        """Raise if rows/cols are not divisible by ``factor`` (the network's output stride)."""
        if self.rows % factor or self.cols % factor:
            raise ValueError(
                f"{name}: rows={self.rows} and cols={self.cols} must both be divisible by {factor} "
                f"(the DeepLabV3+ output stride)"
            )

    def xy_to_rc(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Sensor-frame metres -> fractional (row, col) indices (cell centres at integers)."""
        r = self.rows / 2 - np.asarray(x) / self.cell - 0.5
        c = self.cols / 2 - np.asarray(y) / self.cell - 0.5
        return r, c

    def rc_to_xy(self, r: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(row, col) indices -> sensor-frame metres of the cell centres."""
        x = (self.rows / 2 - np.asarray(r) - 0.5) * self.cell
        y = (self.cols / 2 - np.asarray(c) - 0.5) * self.cell
        return x, y

    def cell_centers(self) -> tuple[np.ndarray, np.ndarray]:
        """Sensor-frame x, y (m) of every cell centre, each of shape ``(rows, cols)``."""
        r, c = np.meshgrid(np.arange(self.rows), np.arange(self.cols), indexing="ij")
        return self.rc_to_xy(r, c)
