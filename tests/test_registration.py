"""Classical registration (Fourier–Mellin + phase correlation + ECC) and the registered baseline."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from traffictwin.evidential.warp import pixel_from_metric, warp_masses
from traffictwin.fusion.registration import (
    RegistrationParams,
    pixel_affine_to_pose,
    pose_error,
    pose_to_pixel_affine,
    register_pair,
    warp_image,
)
from traffictwin.geometry import relative_pose, se2_matrix
from traffictwin.grid import GridSpec

GRID = GridSpec(128, 96, 0.5)


def structured_world(seed: int, grid: GridSpec, scale: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """A crossroads with random buildings and cars on a canvas ``scale`` times the grid; (masses, metric→pixel)."""
    rng = np.random.default_rng(seed)
    h, w = grid.rows * scale, grid.cols * scale
    road = np.zeros((h, w), np.uint8)
    hw = int(7 / grid.cell)
    cv2.rectangle(road, (w // 2 - hw, 0), (w // 2 + hw, h), 1, -1)
    cv2.rectangle(road, (0, h // 2 - hw), (w, h // 2 + hw), 1, -1)
    mo = np.zeros((h, w), np.float32)
    for _ in range(80):
        cx, cy = int(rng.integers(0, w)), int(rng.integers(0, h))
        size = (float(rng.integers(6, 30)), float(rng.integers(6, 30)))
        box = cv2.boxPoints(((cx, cy), size, float(rng.uniform(-25, 25)))).astype(np.int32)
        if not road[cy, cx]:
            cv2.fillPoly(mo, [box], 0.85)
    for _ in range(30):
        cx, cy = int(rng.integers(0, w)), int(rng.integers(0, h))
        if road[cy, cx]:
            box = cv2.boxPoints(
                ((cx, cy), (4.5 / grid.cell, 1.9 / grid.cell), float(rng.choice([0, 90])))
            ).astype(np.int32)
            cv2.fillPoly(mo, [box], 0.9)
    mf = np.where(road > 0, 0.8, 0.15).astype(np.float32)
    mf[mo > 0] = 0
    return np.stack([mf, mo]), pixel_from_metric(GridSpec(h, w, grid.cell))


def render(
    world: np.ndarray, pw: np.ndarray, pose: np.ndarray, grid: GridSpec, radius: float = 28.0
) -> np.ndarray:
    """The map a sensor at world ``pose`` sees: the world within ``radius`` (m), unknown beyond."""
    m = pw @ se2_matrix(*pose) @ np.linalg.inv(pixel_from_metric(grid))
    out = np.stack(
        [
            cv2.warpAffine(
                c, m[:2], (grid.cols, grid.rows), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
            )
            for c in world
        ]
    )
    x, y = grid.cell_centers()
    out[:, np.hypot(x, y) > radius] = 0
    return out


def test_pixel_affine_roundtrip_and_consistent_with_warp_masses():
    pose = np.array([3.2, -1.7, np.radians(14.0)])
    np.testing.assert_allclose(
        pixel_affine_to_pose(pose_to_pixel_affine(pose, GRID), GRID), pose, atol=1e-9
    )
    rng = np.random.default_rng(0)
    m = cv2.GaussianBlur(rng.random((GRID.rows, GRID.cols)).astype(np.float32), (0, 0), 3)
    masses = np.stack([0.5 * m, 0.5 * (1 - m)]).astype(np.float32)
    a = warp_masses(masses, pose, GRID)[1]
    b = warp_image(masses[1], pose_to_pixel_affine(pose, GRID), GRID.shape)
    inner = np.zeros(GRID.shape, bool)
    inner[20:-20, 20:-20] = True
    np.testing.assert_allclose(
        a[inner], b[inner], atol=2e-3
    )  # OpenCV bilinear weights are 1/32 fixed point


def test_pose_error_wraps_yaw():
    t, r = pose_error(np.array([1.0, 1.0, np.pi - 0.01]), np.array([1.0, 4.0, -np.pi + 0.01]))
    assert t == pytest.approx(3.0) and r == pytest.approx(np.degrees(0.02))


@pytest.mark.parametrize("noise", [(1.5, -2.0, 8.0), (-3.0, 2.5, -15.0), (0.4, 0.3, 2.0)])
def test_recovers_known_shift_and_rotation(noise):
    world, pw = structured_world(1, GRID)
    p1 = np.array([2.0, -3.0, 0.2])
    p2 = np.array([12.0, 4.0, 0.7])
    m1, m2 = render(world, pw, p1, GRID), render(world, pw, p2, GRID)
    true = relative_pose(p1, p2)
    noisy = true + np.array([noise[0], noise[1], np.radians(noise[2])])
    res = register_pair(m1, m2, noisy, GRID, RegistrationParams())
    t, r = pose_error(res.pose, true)
    assert res.accepted
    assert t < 0.25 and r < 0.5, (t, r)  # ≤ half a cell and half a degree
    assert res.cc_est > res.cc_noisy


def test_falls_back_to_noisy_pose_without_overlap_or_structure():
    blank = np.zeros((2, *GRID.shape), np.float32)
    noisy = np.array([1.0, 2.0, 0.1])
    res = register_pair(blank, blank, noisy, GRID)
    assert not res.accepted
    np.testing.assert_array_equal(res.pose, noisy)
    # unrelated content (random blobs vs a crossroads): whatever the estimate, it must not be accepted
    world, pw = structured_world(2, GRID)
    m1 = render(world, pw, np.zeros(3), GRID)
    rng = np.random.default_rng(4)
    blobs = cv2.GaussianBlur(rng.random(GRID.shape).astype(np.float32), (0, 0), 2.0)
    occ = (blobs > np.quantile(blobs, 0.8)).astype(np.float32) * 0.9
    m2 = np.stack([(0.8 - occ) * (occ == 0), occ]).astype(np.float32)
    res = register_pair(m1, m2, noisy, GRID, RegistrationParams(min_cc=0.5))
    assert not res.accepted and np.array_equal(res.pose, noisy)


def test_bad_inputs_name_the_argument():
    with pytest.raises(ValueError, match="map2"):
        register_pair(np.zeros((2, *GRID.shape)), np.zeros((2, 10, 10)), np.zeros(3), GRID)
    with pytest.raises(ValueError, match="feature"):
        RegistrationParams(feature="edges")


@pytest.mark.parametrize("noise", [(2.0, -1.5, 12.0), (-3.5, 2.5, -17.0)])
def test_recovers_known_shift_and_rotation_of_a_generated_lidar_pair(noise):
    """The project's own generator (world, traffic, VLP-32C-like lidar, ISM) at the ci grid."""
    from traffictwin.fusion.pairs import FusionDataParams, scenario_maps
    from traffictwin.sim.lidar import LidarSpec

    grid = GridSpec(128, 96, 0.64)
    p = FusionDataParams(
        grid=grid, lidar=LidarSpec(azimuth_res_deg=0.4, max_range=50.0), encounters_per_scenario=1
    )
    sm = scenario_maps(7, 5, p)
    m1, m2 = sm["maps"][0, 0], sm["maps"][0, 1]
    true = relative_pose(sm["poses"][0, 0], sm["poses"][0, 1])
    noisy = true + np.array([noise[0], noise[1], np.radians(noise[2])])
    res = register_pair(m1, m2, noisy, grid)
    t, r = pose_error(res.pose, true)
    assert res.accepted
    assert t < grid.cell and r < 1.0, (
        t,
        r,
    )  # within one cell and one degree (noise: ~2.5-4.3 m, 12-17°)
