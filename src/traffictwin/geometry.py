"""SE(2) pose maths shared by the simulator, the evidential warps and the problems.

A pose is ``(x, y, yaw)`` in a world frame (m, m, rad). This module sits below ``sim/`` and
``evidential/`` and imports nothing from the package (checked by ``tests/test_architecture.py``).
"""

from __future__ import annotations

import numpy as np


def se2_matrix(x: float, y: float, yaw: float) -> np.ndarray:
    """3x3 homogeneous matrix of the SE(2) pose (x, y in m, yaw in rad): local -> world."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


def relative_pose(pose_from: np.ndarray, pose_to: np.ndarray) -> np.ndarray:
    """Pose of ``pose_to`` expressed in the frame of ``pose_from``; both (x, y, yaw) world (m, rad)."""
    m = np.linalg.inv(se2_matrix(*pose_from)) @ se2_matrix(*pose_to)
    return np.array([m[0, 2], m[1, 2], np.arctan2(m[1, 0], m[0, 0])])
