"""ORB pair check: the paper's rule over reliable matches."""

from __future__ import annotations

import numpy as np
import pytest

from traffictwin.sim.camera import StereoCamera
from traffictwin.sim.scene import Boxes, Cls
from traffictwin.stereo.orb import OrbResult, check_pair


@pytest.fixture(scope="module")
def pair():
    cam = StereoCamera()
    boxes = Boxes(
        [[12, 0], [20, 3.5], [8, -3.5], [30, -10], [25, 12]],
        [[4.5, 1.8, 1.5], [4.5, 1.8, 1.5], [4.5, 1.8, 1.5], [20, 10, 12], [15, 8, 9]],
        [0, 0.1, 0, 0, 0.3],
        [Cls.CAR, Cls.CAR, Cls.CAR, Cls.BUILDING, Cls.BUILDING],
    )
    return cam.render_pair((0.0, 0.0, 0.0), boxes, rng=np.random.default_rng(0))


def test_good_pair_passes(pair):
    r = check_pair(pair["left"], pair["right"])
    assert isinstance(r, OrbResult)
    assert not r.outlier
    assert r.n_reliable >= 8 and r.n_matches >= r.n_reliable
    assert r.mean_dx >= 1.0 and r.mean_dy < 1.0


def test_vertical_shift_of_8px_fails(pair):
    right = np.zeros_like(pair["right"])
    right[8:] = pair["right"][:-8]
    r = check_pair(pair["left"], right)
    assert r.outlier and r.mean_dy > 5.0


def test_identical_images_fail(pair):
    r = check_pair(pair["left"], pair["left"].copy())
    assert r.outlier and r.mean_dx < 1.0


def test_featureless_pair_is_flagged_unverifiable():
    flat = np.full((80, 160, 3), 128, np.uint8)
    r = check_pair(flat, flat)
    assert r.outlier and r.n_reliable == 0 and np.isnan(r.mean_dx)


def test_reliable_filter_limits_matches(pair):
    r = check_pair(pair["left"], pair["right"], best_n=10)
    assert r.n_reliable == 10
    r = check_pair(pair["left"], pair["right"], max_hamming=0)
    assert r.n_reliable <= r.n_matches


def test_bad_input_raises(pair):
    with pytest.raises(ValueError, match="differ in size"):
        check_pair(pair["left"], pair["right"][:-2])
    with pytest.raises(ValueError, match="statistic"):
        check_pair(pair["left"], pair["right"], statistic="mode")
