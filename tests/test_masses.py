"""evidential.masses: the one validator (check_masses), cleaner (clean_masses) and unknown mass."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from traffictwin.evidential.masses import check_masses, clean_masses, unknown_mass


def _grid(f: float, o: float, shape=(3, 4)) -> np.ndarray:
    return np.stack([np.full(shape, f), np.full(shape, o)]).astype(np.float32)


def test_check_masses_accepts_valid_and_converts_ints():
    m = _grid(0.3, 0.5)
    assert check_masses(m, "m") is not None
    np.testing.assert_array_equal(check_masses(m[None]), m[None])
    out = check_masses(np.zeros((2, 2, 2), np.int32))
    assert out.dtype == np.float32
    check_masses(_grid(0.5 + 4e-6, 0.5))  # within the tolerance


@pytest.mark.parametrize(
    "bad, match",
    [
        (np.zeros((3, 4, 4)), r"map2: expected masses \(m_F, m_O\) with a channel axis of size 2"),
        (np.zeros((4, 4)), "got shape"),
        (_grid(0.7, 0.7), r"outside the simplex at 12 cell\(s\).*m_F \+ m_O <= 1"),
        (_grid(-0.2, 0.1), "outside the simplex"),
        (_grid(1.2, 0.0), "outside the simplex"),
    ],
)
def test_check_masses_names_the_input_and_the_expected_form(bad, match):
    with pytest.raises(ValueError, match=match):
        check_masses(bad, "map2")


def test_check_masses_rejects_nan_and_inf_with_their_place():
    m = _grid(0.2, 0.2)
    m[1, 2, 3] = np.nan
    with pytest.raises(
        ValueError, match=r"m1: 1 NaN/inf value\(s\) \(first at index \(1, 2, 3\)\)"
    ):
        check_masses(m, "m1")
    m[1, 2, 3] = np.inf
    with pytest.raises(ValueError, match="NaN/inf"):
        check_masses(m, "m1")
    with pytest.raises(ValueError, match="outside the simplex"):
        check_masses(_grid(0.6, 0.6), "x", tol=1e-4)


def test_clean_masses_clips_and_renormalises_only_cells_over_one():
    m = np.array([[[1.2, 0.3, 0.6]], [[0.1, -0.1, 0.6]]], np.float32)
    c = clean_masses(m)
    assert c.dtype == np.float32
    np.testing.assert_allclose(c[:, 0, 0], [1 / 1.1, 0.1 / 1.1], rtol=1e-6)  # clipped, renormalised
    np.testing.assert_array_equal(
        c[:, 0, 1], np.float32([0.3, 0.0])
    )  # on the simplex after clipping: kept
    np.testing.assert_allclose(c[:, 0, 2], [0.5, 0.5])
    assert clean_masses(m.astype(np.float64)).dtype == np.float64
    t = clean_masses(torch.from_numpy(m))
    assert isinstance(t, torch.Tensor)
    np.testing.assert_allclose(t.numpy(), c, rtol=1e-6)
    good = _grid(0.3, 0.5)
    np.testing.assert_array_equal(clean_masses(good), good)


def test_unknown_mass():
    np.testing.assert_allclose(unknown_mass(_grid(0.3, 0.5)), 0.2, rtol=1e-6)
    assert unknown_mass(_grid(0.3, 0.5)[None]).shape == (1, 3, 4)
    np.testing.assert_array_equal(unknown_mass(_grid(0.7, 0.7)), 0.0)  # clipped at 0
