"""Ray casting: analytic distances to a box and to the ground, culling, ids."""

import numpy as np
import pytest

from traffictwin.sim.raycast import HIT_GROUND, HIT_NOTHING, cast_rays
from traffictwin.sim.scene import Boxes, Cls


def box(cx, cy, length, w, h, yaw=0.0, z0=0.0):
    return Boxes([[cx, cy]], [[length, w, h]], [yaw], [Cls.BUILDING], z0=[z0])


def test_distance_to_box_face():
    # box from x = 8 to 12, sensor at height 1 looking along +x
    d, h = cast_rays(
        np.array([[0.0, 0.0, 1.0]]), np.array([[1.0, 0.0, 0.0]]), box(10, 0, 4, 2, 3), 50.0
    )
    assert d[0] == pytest.approx(8.0, abs=1e-4) and h[0] == 0


def test_distance_to_rotated_box():
    # a square of side 2 rotated 45 deg: its corner points at the sensor at x = 10 - sqrt(2)
    d, h = cast_rays(
        np.array([[0.0, 0.0, 1.0]]),
        np.array([[1.0, 0.0, 0.0]]),
        box(10, 0, 2, 2, 3, yaw=np.pi / 4),
        50.0,
    )
    assert d[0] == pytest.approx(10 - np.sqrt(2), abs=1e-4) and h[0] == 0


def test_oblique_ray_hits_top_and_side():
    b = box(10, 0, 4, 4, 2)  # x 8..12, height 2
    o = np.array([[0.0, 0.0, 4.0]])
    # descending ray that reaches z = 2 at x = 9 (inside the footprint): top face
    v = np.array([9.0, 0.0, -2.0])
    d, h = cast_rays(o, (v / np.linalg.norm(v))[None], b, 50.0)
    assert d[0] == pytest.approx(np.linalg.norm(v), abs=1e-4) and h[0] == 0
    # ray at 45 deg left, horizontal: misses the box, nothing within range
    d, h = cast_rays(o, np.array([[np.sqrt(0.5), np.sqrt(0.5), 0.0]]), b, 50.0)
    assert h[0] == HIT_NOTHING and d[0] == 50.0


def test_ground_plane_distance():
    el = np.deg2rad(-10.0)
    dirs = np.array([[np.cos(el), 0.0, np.sin(el)]])
    d, h = cast_rays(np.array([[0.0, 0.0, 1.9]]), dirs, Boxes.empty(), 100.0)
    assert h[0] == HIT_GROUND and d[0] == pytest.approx(1.9 / np.sin(-el), rel=1e-9)
    # beyond max range -> nothing
    d, h = cast_rays(np.array([[0.0, 0.0, 1.9]]), dirs, Boxes.empty(), 5.0)
    assert h[0] == HIT_NOTHING and d[0] == 5.0


def test_nearest_of_several_boxes_and_box_before_ground():
    boxes = Boxes.concat([box(20, 0, 2, 2, 5), box(10, 0, 2, 2, 5), box(5, 5, 1, 1, 1)])
    el = np.deg2rad(-3.0)
    d, h = cast_rays(
        np.array([[0.0, 0.0, 1.9]]), np.array([[np.cos(el), 0.0, np.sin(el)]]), boxes, 100.0
    )
    assert h[0] == 1 and d[0] == pytest.approx(9.0 / np.cos(el), abs=1e-3)


def test_origin_inside_box_ignores_it_and_lifted_box():
    own = box(0, 0, 4.8, 1.9, 1.5)  # sensor inside its own vehicle? (height 1.0 < 1.5)
    d, h = cast_rays(np.array([[0.0, 0.0, 1.0]]), np.array([[1.0, 0.0, 0.0]]), own, 30.0)
    assert h[0] == HIT_NOTHING
    lifted = box(10, 0, 2, 2, 1, z0=3.0)  # hovering 3..4 m: a horizontal ray at 1 m passes below
    d, h = cast_rays(np.array([[0.0, 0.0, 1.0]]), np.array([[1.0, 0.0, 0.0]]), lifted, 30.0)
    assert h[0] == HIT_NOTHING


def test_chunking_gives_same_result():
    rng = np.random.default_rng(0)
    n = 40
    boxes = Boxes(
        rng.uniform(-30, 30, (n, 2)),
        rng.uniform(0.5, 6, (n, 3)),
        rng.uniform(-3, 3, n),
        np.zeros(n),
    )
    dirs = rng.normal(size=(500, 3))
    dirs[:, 2] = -np.abs(dirs[:, 2]) * 0.2
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    o = np.tile([[0.0, 0.0, 1.9]], (500, 1))
    d1, h1 = cast_rays(o, dirs, boxes, 60.0)
    d2, h2 = cast_rays(o, dirs, boxes, 60.0, chunk=97)
    np.testing.assert_array_equal(h1, h2)
    np.testing.assert_allclose(d1, d2)
    assert (h1 >= 0).any() and (h1 == HIT_GROUND).any()


def test_bad_input():
    with pytest.raises(ValueError, match="origins"):
        cast_rays(np.zeros((3, 2)), np.zeros((3, 2)), Boxes.empty(), 10.0)
    with pytest.raises(ValueError, match="max_range"):
        cast_rays(np.zeros((3, 3)), np.ones((3, 3)), Boxes.empty(), -1.0)
