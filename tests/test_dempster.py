"""Dempster's rule and the pignistic transform: hand cases and algebraic properties."""

import numpy as np
import pytest
import torch

from traffictwin.evidential.dempster import conflict, dempster, pignistic


def grid(f, o):
    return np.array([[[f]], [[o]]], dtype=np.float64)


def random_masses(rng, shape=(5, 7), n=None):
    lead = (n,) if n else ()
    a = rng.dirichlet([1, 1, 1], size=lead + shape)  # (…, H, W, 3) on the simplex
    return np.moveaxis(a[..., :2], -1, -3)


def test_hand_case():
    # m1 = (0.6, 0.2, u .2), m2 = (0.3, 0.5, u .2)
    # K = .6*.5 + .2*.3 = .36 ; F = .18 + .12 + .06 = .36 ; O = .10 + .04 + .10 = .24
    m = dempster(grid(0.6, 0.2), grid(0.3, 0.5))
    assert m[0, 0, 0] == pytest.approx(0.36 / 0.64)
    assert m[1, 0, 0] == pytest.approx(0.24 / 0.64)
    assert conflict(grid(0.6, 0.2), grid(0.3, 0.5))[0, 0] == pytest.approx(0.36)


def test_agreeing_free_sources():
    m = dempster(grid(0.5, 0.0), grid(0.5, 0.0))
    np.testing.assert_allclose(m[:, 0, 0], [0.75, 0.0])


def test_vacuous_is_identity():
    rng = np.random.default_rng(0)
    m = random_masses(rng)
    np.testing.assert_allclose(dempster(m, np.zeros_like(m)), m, atol=1e-12)
    np.testing.assert_allclose(dempster(np.zeros_like(m), m), m, atol=1e-12)


def test_commutative_associative_and_on_simplex():
    rng = np.random.default_rng(1)
    a, b, c = (random_masses(rng) for _ in range(3))
    np.testing.assert_allclose(dempster(a, b), dempster(b, a), atol=1e-12)
    np.testing.assert_allclose(dempster(dempster(a, b), c), dempster(a, dempster(b, c)), atol=1e-9)
    m = dempster(a, b)
    assert m.min() >= 0 and m.max() <= 1 and (m.sum(0) <= 1 + 1e-12).all()


def test_total_conflict_returns_vacuous():
    m = dempster(grid(1.0, 0.0), grid(0.0, 1.0))
    np.testing.assert_array_equal(m[:, 0, 0], [0.0, 0.0])
    # mixed grid: one conflicting cell, one ordinary cell
    m1 = np.concatenate([grid(1.0, 0.0), grid(0.5, 0.0)], axis=2)
    m2 = np.concatenate([grid(0.0, 1.0), grid(0.5, 0.0)], axis=2)
    out = dempster(m1, m2)
    np.testing.assert_allclose(out[:, 0, :], [[0.0, 0.75], [0.0, 0.0]])


@pytest.mark.parametrize("as_torch", [False, True])
def test_near_total_conflict_is_stable_in_float32(as_torch):
    # K -> 1: m1 ≈ (1, 0), m2 ≈ (0, 1) with remainders 1e-7..1e-3, in float32. Reference: the
    # rule in float64 on the same float32 inputs. Dividing by 1 - K (the old denominator) loses
    # about twice as much as dividing by n_F + n_O + n_Θ (the unnormalised product's sum).
    rng = np.random.default_rng(0)
    e = 10 ** rng.uniform(-7, -3, (4, 2000))
    m1 = np.stack([1 - e[0] - e[1], e[1]])[:, None, :].astype(np.float32)
    m2 = np.stack([e[2], 1 - e[2] - e[3]])[:, None, :].astype(np.float32)
    ref = dempster(m1.astype(np.float64), m2.astype(np.float64))
    f1, o1, f2, o2 = m1[0], m1[1], m2[0], m2[1]
    u1, u2 = 1 - f1 - o1, 1 - f2 - o2
    one_minus_k = 1 - (f1 * o2 + o1 * f2)
    old = np.stack([f1 * f2 + f1 * u2 + u1 * f2, o1 * o2 + o1 * u2 + u1 * o2]) / one_minus_k
    got = dempster(torch.from_numpy(m1), torch.from_numpy(m2)) if as_torch else dempster(m1, m2)
    got = np.asarray(got)
    assert got.dtype == np.float32 and (got.sum(0) <= 1 + 1e-6).all()
    assert np.abs(got - ref).max() < 0.6 * np.abs(old - ref).max()
    assert (old.sum(0) > 1 + 1e-6).mean() > 0.2  # the old form left the simplex in many cells


def test_batched_float32_and_torch_agree():
    rng = np.random.default_rng(2)
    a = random_masses(rng, n=3).astype(np.float32)
    b = random_masses(rng, n=3).astype(np.float32)
    m = dempster(a, b)
    assert m.shape == (3, 2, 5, 7) and m.dtype == np.float32
    np.testing.assert_allclose(m[1], dempster(a[1], b[1]), atol=1e-7)
    mt = dempster(torch.from_numpy(a), torch.from_numpy(b))
    assert isinstance(mt, torch.Tensor)
    np.testing.assert_allclose(mt.numpy(), m, atol=1e-6)


def test_bad_shapes():
    with pytest.raises(ValueError, match="channel axis"):
        dempster(np.zeros((3, 4, 4)), np.zeros((3, 4, 4)))
    with pytest.raises(ValueError, match="grid shapes differ"):
        dempster(np.zeros((2, 4, 4)), np.zeros((2, 4, 5)))


def test_pignistic_hand_cases():
    np.testing.assert_allclose(pignistic(grid(0.0, 0.0)), [[0.5]])
    np.testing.assert_allclose(pignistic(grid(0.0, 1.0)), [[1.0]])
    np.testing.assert_allclose(pignistic(grid(1.0, 0.0)), [[0.0]])
    np.testing.assert_allclose(pignistic(grid(0.2, 0.4)), [[0.4 + 0.2]])
    assert pignistic(np.zeros((4, 2, 3, 3))).shape == (4, 3, 3)
