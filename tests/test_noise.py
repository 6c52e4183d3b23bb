"""Pose-noise model: sigma = r / 2.326 per axis, ~98 % of draws inside the interval."""

import numpy as np
import pytest

from traffictwin.evidential.noise import (
    apply_pose_noise,
    noise_sigmas,
    scale_noise,
    standard_normal_draws,
)


def test_sigmas():
    s, sy = noise_sigmas(2.326, 2.326)
    assert s == pytest.approx(1.0)
    assert sy == pytest.approx(np.deg2rad(1.0))
    with pytest.raises(ValueError, match="r"):
        noise_sigmas(-1.0, 0.0)


def test_sample_statistics_and_coverage():
    r, alpha = 5.0, 20.0
    n = 200_000
    x = scale_noise(np.random.default_rng(0).standard_normal((n, 3)), r, alpha)
    assert x[:, 0].std() == pytest.approx(r / 2.326, rel=0.01)
    assert x[:, 1].std() == pytest.approx(r / 2.326, rel=0.01)
    assert x[:, 2].std() == pytest.approx(np.deg2rad(alpha) / 2.326, rel=0.01)
    assert abs(x.mean(0)[0]) < 0.02
    inside_xy = (np.abs(x[:, :2]) <= r).mean()
    inside_yaw = (np.abs(x[:, 2]) <= np.deg2rad(alpha)).mean()
    assert inside_xy == pytest.approx(0.98, abs=0.002)
    assert inside_yaw == pytest.approx(0.98, abs=0.002)


def test_draws_depend_only_on_seed_pair_and_draw():
    a = standard_normal_draws(1, np.array([5, 6, 7]))
    b = standard_normal_draws(1, np.array([7, 5]))
    np.testing.assert_array_equal(a[0], b[1])
    np.testing.assert_array_equal(a[2], b[0])
    assert not np.allclose(standard_normal_draws(1, [5], draw=1), a[:1])
    # configuration A (r = alpha = 0) is exactly noise-free
    np.testing.assert_array_equal(scale_noise(a, 0.0, 0.0), 0.0)


def test_apply_wraps_yaw():
    p = apply_pose_noise(np.array([1.0, 2.0, 3.0]), np.array([0.5, -0.5, 0.5]))
    np.testing.assert_allclose(p, [1.5, 1.5, 3.5 - 2 * np.pi])
