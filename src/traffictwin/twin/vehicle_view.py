"""Risk for every vehicle: the twin read in each vehicle's own frame, not only the ego's.

The twin is built in the reference (ego) frame (:mod:`traffictwin.twin.fuse`). Vehicle ``k``'s
view of it (:func:`vehicle_view`) fuses ``k``'s own map, unwarped, with the map of every other
vehicle the twin used, each placed in ``k``'s frame by the twin's poses (the pose of ``j`` in
``k``'s frame: :func:`traffictwin.geometry.relative_pose` of the twin's pose of ``k`` and of ``j``;
the reference sits at the origin), with Dempster's rule — each map once, whichever method
registered them. A vehicle the twin left out (its pose in doubt) sees only its own map. The
risk read from a view is the ego's (:func:`traffictwin.twin.evaluation.map_thw`) along that
vehicle's own path ahead, against its own truth (``vehicle_thw_true`` of the twin data).
Units: m, rad.
"""

from __future__ import annotations

import numpy as np

from traffictwin.evidential.dempster import dempster
from traffictwin.evidential.warp import warp_masses
from traffictwin.geometry import relative_pose
from traffictwin.grid import GridSpec

__all__ = ["vehicle_view"]


def vehicle_view(
    maps: np.ndarray, poses: np.ndarray, used: np.ndarray, k: int, grid: GridSpec
) -> np.ndarray:
    """The twin in vehicle ``k``'s frame: ``maps (N, 2, H, W)`` each in its own sensor frame,
    ``poses (N, 3)`` the twin's pose of every vehicle in the reference frame (x m, y m, yaw rad;
    the reference's row zeros), ``used (N,)`` the vehicles the twin fused. ``(2, H, W)`` float32."""
    maps = np.asarray(maps, dtype=np.float32)
    n = len(maps)
    if not 0 <= k < n:
        raise ValueError(f"vehicle {k} not in 0..{n - 1}")
    view = maps[k].copy()
    if not used[k]:
        return view
    for j in range(n):
        if j != k and used[j]:
            view = dempster(view, warp_masses(maps[j], relative_pose(poses[k], poses[j]), grid))
    return np.asarray(view, dtype=np.float32)
