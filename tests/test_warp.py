"""SE(2) warping of mass grids: identity, inverse, a 90 deg turn, the simplex."""

import numpy as np
import pytest

from traffictwin.evidential.warp import warp_masses
from traffictwin.geometry import relative_pose
from traffictwin.grid import GridSpec

G = GridSpec(64, 48, 0.5)


def random_map(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    a = rng.dirichlet([1, 1, 1], size=G.shape)
    # smooth blocks so bilinear resampling is nearly exact away from edges
    a = a[::4, ::4].repeat(4, 0).repeat(4, 1)
    return np.moveaxis(a[..., :2], -1, 0).astype(np.float32)


def test_identity_is_noop():
    m = random_map()
    np.testing.assert_allclose(warp_masses(m, [0, 0, 0], G), m, atol=1e-6)


def test_translation_moves_cells():
    m = np.zeros((2, *G.shape), np.float32)
    m[1, 20, 10] = 0.9
    # map 2's sensor 2 m ahead (+x) of map 1's: its cell (20,10) appears 4 rows further up (front)
    out = warp_masses(m, [2.0, 0.0, 0.0], G)
    assert out[1, 16, 10] == pytest.approx(0.9, abs=1e-5)
    # bottom rows of map 1 lie behind map 2's extent -> unknown
    assert np.all(out[:, -4:, :] == 0)


def test_quarter_turn():
    m = np.zeros((2, *G.shape), np.float32)
    x, y = 4.25, -0.25  # a cell centre 4.25 m ahead of sensor 2
    r, c = G.xy_to_rc(x, y)
    m[0, int(r), int(c)] = 0.7
    # sensor 2 turned +90 deg (facing map 1's +y): its +x axis is map 1's +y
    out = warp_masses(m, [0.0, 0.0, np.pi / 2], G)
    r1, c1 = G.xy_to_rc(-y, x)  # rotate (x, y) by +90 deg
    assert out[0, int(round(float(r1))), int(round(float(c1)))] == pytest.approx(0.7, abs=1e-5)
    assert out[0].sum() == pytest.approx(0.7, abs=1e-4)


def test_warp_then_inverse_restores_overlap():
    import cv2

    rng = np.random.default_rng(1)
    smooth = [cv2.GaussianBlur(rng.random(G.shape).astype(np.float32), (0, 0), 4) for _ in range(2)]
    smooth = [(s - s.min()) / (s.max() - s.min()) for s in smooth]
    m = np.stack([0.5 * smooth[0], 0.5 * smooth[1]])
    p1, p2 = np.array([10.0, 5.0, 0.3]), np.array([12.0, 3.5, 0.5])
    rel = relative_pose(p1, p2)
    there = warp_masses(m, rel, G)
    assert np.abs(there - m).mean() > 0.05  # the warp did move things
    back = warp_masses(there, relative_pose(p2, p1), G)
    inner = np.zeros(G.shape, bool)
    inner[16:-16, 12:-12] = True  # inside the overlap, away from the borders
    diff = np.abs(back - m)[:, inner]
    assert diff.max() < 0.02 and diff.mean() < 0.003


def test_output_on_simplex_and_bad_input():
    m = random_map(2)
    out = warp_masses(m, [1.3, -0.7, 0.4], G)
    assert out.dtype == np.float32 and out.min() >= 0 and (out.sum(0) <= 1 + 1e-6).all()
    with pytest.raises(ValueError, match="shape"):
        warp_masses(m[:, :10], [0, 0, 0], G)
    with pytest.raises(ValueError, match="rel_pose"):
        warp_masses(m, [0, np.nan, 0], G)
