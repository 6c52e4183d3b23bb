"""Yager's rule and Denœux's normalised cautious rule on Θ = {F, O}: hand cases and properties."""

from __future__ import annotations

import numpy as np
import pytest

from traffictwin.evidential.rules import cautious, conjunctive_weights, yager


def cell(f: float, o: float) -> np.ndarray:
    return np.array([f, o], dtype=np.float64).reshape(2, 1, 1)


def random_masses(
    rng: np.random.Generator, shape=(5, 2, 7, 6), dogmatic_frac: float = 0.0
) -> np.ndarray:
    d = rng.dirichlet([1.0, 1.0, 1.0], size=(shape[0], shape[2], shape[3]))  # (N,H,W,3) = F, O, Θ
    m = np.moveaxis(d[..., :2], -1, 1).astype(np.float32)
    return m


def test_yager_hand_case():
    # m1 = (0.6, 0.3, u=0.1), m2 = (0.2, 0.5, u=0.3)
    m = yager(cell(0.6, 0.3), cell(0.2, 0.5))[:, 0, 0]
    mf = 0.6 * 0.2 + 0.6 * 0.3 + 0.1 * 0.2  # 0.32
    mo = 0.3 * 0.5 + 0.3 * 0.3 + 0.1 * 0.5  # 0.29
    k = 0.6 * 0.5 + 0.3 * 0.2  # 0.36 -> to Θ
    np.testing.assert_allclose(m, [mf, mo], atol=1e-6)
    assert abs((1 - m.sum()) - (0.1 * 0.3 + k)) < 1e-6


def test_yager_total_conflict_is_unknown_and_vacuous_is_neutral():
    np.testing.assert_allclose(yager(cell(1, 0), cell(0, 1))[:, 0, 0], [0, 0], atol=1e-7)
    rng = np.random.default_rng(0)
    m = random_masses(rng)
    np.testing.assert_allclose(yager(m, np.zeros_like(m)), m, atol=1e-6)


def test_yager_commutative_and_valid():
    rng = np.random.default_rng(1)
    a, b = random_masses(rng), random_masses(rng)
    np.testing.assert_allclose(yager(a, b), yager(b, a), atol=1e-7)
    c = yager(a, b)
    assert c.min() >= 0 and (c.sum(axis=1) <= 1 + 1e-6).all()
    assert c.shape == a.shape and c.dtype == np.float32


def test_cautious_weights_hand_case():
    wf, wo = conjunctive_weights(cell(0.6, 0.3))
    np.testing.assert_allclose([wf.item(), wo.item()], [0.1 / 0.7, 0.1 / 0.4])


def test_cautious_hand_case():
    # m1 = (0.6, 0.3, 0.1): w_F = 1/7, w_O = 1/4; m2 = (0.2, 0.5, 0.3): w_F = 0.6, w_O = 0.375
    # min: w_F = 1/7, w_O = 0.25; Z = 1/7 + 1/4 - 1/28 = 10/28
    # m_F = (6/7)(1/4)/Z = 0.6, m_O = (1/7)(3/4)/Z = 0.3, u = (1/28)/Z = 0.1
    m = cautious(cell(0.6, 0.3), cell(0.2, 0.5))[:, 0, 0]
    np.testing.assert_allclose(m, [0.6, 0.3], atol=1e-6)
    # m1 = (0.5, 0, 0.5) (w_F = 0.5, w_O = 1), m2 = (0, 0.5, 0.5) (w_F = 1, w_O = 0.5)
    # → w = (0.5, 0.5): Z = 0.75; m_F = 0.25/0.75, m_O = 0.25/0.75, u = 0.25/0.75
    m = cautious(cell(0.5, 0.0), cell(0.0, 0.5))[:, 0, 0]
    np.testing.assert_allclose(m, [1 / 3, 1 / 3], atol=1e-6)


def test_cautious_idempotent():
    rng = np.random.default_rng(2)
    m = random_masses(rng)
    np.testing.assert_allclose(cautious(m, m), m, atol=1e-5)
    # dogmatic and vacuous cells as limits
    d = np.stack([cell(1, 0), cell(0, 1), cell(0, 0), cell(0.5, 0.5)])
    np.testing.assert_allclose(cautious(d, d), d, atol=1e-5)


def test_cautious_commutative_vacuous_neutral_and_weaker_than_dempster():
    rng = np.random.default_rng(3)
    a, b = random_masses(rng), random_masses(rng)
    np.testing.assert_allclose(cautious(a, b), cautious(b, a), atol=1e-6)
    np.testing.assert_allclose(cautious(a, np.zeros_like(a)), a, atol=1e-5)
    c = cautious(a, b)
    assert c.min() >= 0 and (c.sum(axis=1) <= 1 + 1e-5).all()
    # agreeing evidence is not counted twice: cautious(m, m) = m while Dempster would sharpen it
    m = cell(0.6, 0.0)
    assert cautious(m, m)[0, 0, 0] == pytest.approx(0.6, abs=1e-6)


def test_cautious_contradicting_dogmatic_limit():
    np.testing.assert_allclose(cautious(cell(1, 0), cell(0, 1))[:, 0, 0], [0.5, 0.5], atol=1e-6)


@pytest.mark.parametrize("bad", [np.zeros((3, 4, 4)), np.full((2, 3, 3), 0.7), -np.ones((2, 2, 2))])
def test_rules_reject_bad_masses(bad):
    good = np.zeros((2,) + bad.shape[1:])
    for rule in (yager, cautious):
        with pytest.raises(ValueError, match="m1"):
            rule(bad, good if bad.shape[0] == 2 else bad)
