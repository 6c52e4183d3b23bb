"""ECC refinement of a given pose estimate (the learned registration's coarse pose)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from tests.test_registration import GRID, render, structured_world
from traffictwin.fusion.registration import (
    RefinementParams,
    RegistrationParams,
    ecc_align,
    pose_error,
    refine_pose,
    register_pair,
)
from traffictwin.geometry import relative_pose


def _pair(seed: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    world, pw = structured_world(seed, GRID)
    p1 = np.array([2.0, -3.0, 0.2])
    p2 = np.array([12.0, 4.0, 0.7])
    return render(world, pw, p1, GRID), render(world, pw, p2, GRID), relative_pose(p1, p2)


@pytest.mark.parametrize("levels", [1, 2])
@pytest.mark.parametrize("off", [(0.8, -0.6, 3.0), (-0.7, 0.7, -2.5)])
def test_refines_a_coarse_pose_about_1m_3deg_off(off, levels):
    m1, m2, true = _pair()
    coarse = true + np.array([off[0], off[1], np.radians(off[2])])
    t0, r0 = pose_error(coarse, true)
    assert t0 > 0.9 and r0 > 2.4  # the start fails the success test (0.5 m, 1 deg)
    res = refine_pose(
        m1, m2, coarse, GRID, RefinementParams(ecc_levels=levels, max_trans_m=2.0, max_rot_deg=5.0)
    )
    t, r = pose_error(res.pose, true)
    assert res.accepted and res.ecc_ok
    assert t < 0.25 and r < 0.5, (t, r)
    assert res.cc_est > res.cc_start


def test_falls_back_to_the_start_when_the_refinement_moves_too_far():
    m1, m2, true = _pair()
    coarse = true + np.array([0.8, -0.6, np.radians(3.0)])
    # the right answer is ~1 m away: a bound of 0.3 m rejects it and keeps the start
    res = refine_pose(m1, m2, coarse, GRID, RefinementParams(max_trans_m=0.3, max_rot_deg=5.0))
    assert not res.accepted
    np.testing.assert_array_equal(res.pose, coarse)
    assert pose_error(res.estimate, coarse)[0] > 0.3


def test_falls_back_to_the_start_when_ecc_diverges_or_has_nothing_to_align():
    m1, m2, true = _pair()
    start = true + np.array([0.5, 0.5, 0.02])
    blank = np.zeros_like(m2)
    res = refine_pose(m1, blank, start, GRID)  # no overlap: nothing to align
    assert not res.accepted and not res.ecc_ok
    np.testing.assert_array_equal(res.pose, start)
    # structureless map 2 (a constant known plateau): ECC's correlation is undefined, it raises
    flat = np.stack([np.full(GRID.shape, 0.3, np.float32), np.full(GRID.shape, 0.3, np.float32)])
    res = refine_pose(m1, flat, start, GRID)
    assert not res.accepted
    np.testing.assert_array_equal(res.pose, start)


def test_ecc_align_pyramid_recovers_a_pixel_shift():
    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.random(GRID.shape).astype(np.float32), (0, 0), 3.0)
    shift = np.array([[1.0, 0.0, 2.5], [0.0, 1.0, -1.5], [0.0, 0.0, 1.0]])
    moved = cv2.warpAffine(img, shift[:2], (GRID.cols, GRID.rows), flags=cv2.INTER_LINEAR)
    mask = np.full(GRID.shape, 255, np.uint8)
    mask[:8], mask[-8:], mask[:, :8], mask[:, -8:] = 0, 0, 0, 0
    for levels in (1, 3):
        w, ok = ecc_align(img, moved, mask, mask, np.eye(3), 100, 1e-6, 5, levels)
        assert ok
        np.testing.assert_allclose(w[:2, 2], [2.5, -1.5], atol=0.05)
        np.testing.assert_allclose(w[:2, :2], np.eye(2), atol=1e-3)


def test_register_pair_accepts_a_pyramid_and_checks_its_settings():
    m1, m2, true = _pair()
    noisy = true + np.array([1.5, -2.0, np.radians(8.0)])
    res = register_pair(m1, m2, noisy, GRID, RegistrationParams(ecc_levels=2))
    t, r = pose_error(res.pose, true)
    assert res.accepted and t < 0.25 and r < 0.5
    with pytest.raises(ValueError, match="ecc_levels"):
        RefinementParams(ecc_levels=0)
    with pytest.raises(ValueError, match="map1"):
        refine_pose(np.zeros((2, 4, 4)), m2, true, GRID)
