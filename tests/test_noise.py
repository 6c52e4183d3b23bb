"""Pose-noise model: sigma = r / 2.326 per axis, ~98 % of draws inside the interval."""

import numpy as np
import pytest

from traffictwin.evidential.noise import (
    apply_pose_noise,
    noise_scales,
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


SIGMAS = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 0.1], [2.0, 2.0, 0.2], [4.0, 4.0, 0.3]])


def test_mixture_takes_each_configuration_uniformly_and_reproducibly():
    pid = np.arange(40_000)
    s = noise_scales(3, pid, 0, SIGMAS, "mixture")
    assert s.shape == (len(pid), 3)
    # every row is one configuration's sigmas, each about a quarter of the rows
    hit = (s[:, None, :] == SIGMAS[None]).all(-1)
    assert (hit.sum(1) == 1).all()
    np.testing.assert_allclose(hit.mean(0), 0.25, atol=0.01)
    # row i depends on (seed, pair, draw) only: the same in a subset, another for another draw
    np.testing.assert_array_equal(noise_scales(3, pid[7:9], 0, SIGMAS), s[7:9])
    other = noise_scales(3, pid[:2000], 1, SIGMAS)
    assert (other != s[:2000]).any(axis=1).mean() > 0.5
    assert (noise_scales(4, pid[:2000], 0, SIGMAS) != s[:2000]).any(axis=1).mean() > 0.5


def test_scaled_kind_is_the_largest_noise_times_a_uniform_factor():
    s = noise_scales(0, np.arange(20_000), 0, SIGMAS[-1:], "scaled")
    f = s / SIGMAS[-1]
    np.testing.assert_allclose(f[:, 0], f[:, 2])  # one factor for every axis
    assert f.min() >= 0 and f.max() <= 1 and f[:, 0].mean() == pytest.approx(0.5, abs=0.01)


def test_mixture_rejects_an_unknown_kind_and_no_configuration():
    with pytest.raises(ValueError, match="kind must be one of"):
        noise_scales(0, np.arange(3), 0, SIGMAS, "gaussian")
    with pytest.raises(ValueError, match="at least one"):
        noise_scales(0, np.arange(3), 0, np.zeros((0, 3)))
