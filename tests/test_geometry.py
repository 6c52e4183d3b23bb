"""SE(2) pose maths (traffictwin.geometry): hand-computed cases and the compose/inverse round trip."""

import numpy as np
import pytest

from traffictwin.geometry import relative_pose, se2_matrix


def test_se2_matrix_of_a_quarter_turn():
    # local +x is world +y after a +90 deg yaw; the origin moves to (1, 2)
    expected = np.array([[0.0, -1.0, 1.0], [1.0, 0.0, 2.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(se2_matrix(1.0, 2.0, np.pi / 2), expected, atol=1e-15)
    np.testing.assert_array_equal(se2_matrix(0.0, 0.0, 0.0), np.eye(3))


@pytest.mark.parametrize(
    ("pose_from", "pose_to", "expected"),
    [
        # from the world origin, the relative pose is the pose itself
        ((0.0, 0.0, 0.0), (3.0, -1.0, 0.5), (3.0, -1.0, 0.5)),
        # facing world +y at (1, 2): the point 2 m further along +y is 2 m straight ahead
        ((1.0, 2.0, np.pi / 2), (1.0, 4.0, np.pi), (2.0, 0.0, np.pi / 2)),
        # a pose 1 m to the world's +x of one facing +y lies 1 m to its right (-y)
        ((0.0, 0.0, np.pi / 2), (1.0, 0.0, np.pi / 2), (0.0, -1.0, 0.0)),
        # yaw is wrapped to (-pi, pi]: 3 rad to -3 rad is +0.283 rad, not -6 rad
        ((0.0, 0.0, 3.0), (0.0, 0.0, -3.0), (0.0, 0.0, 2 * np.pi - 6.0)),
    ],
)
def test_relative_pose_hand_cases(pose_from, pose_to, expected):
    got = relative_pose(np.array(pose_from), np.array(pose_to))
    assert got.shape == (3,)
    np.testing.assert_allclose(got, expected, atol=1e-12)


def test_compose_and_inverse_round_trip():
    rng = np.random.default_rng(0)
    for _ in range(20):
        a = np.array([*rng.uniform(-50, 50, 2), rng.uniform(-np.pi, np.pi)])
        b = np.array([*rng.uniform(-50, 50, 2), rng.uniform(-np.pi, np.pi)])
        rel = relative_pose(a, b)
        # composing a with the relative pose gives b
        np.testing.assert_allclose(se2_matrix(*a) @ se2_matrix(*rel), se2_matrix(*b), atol=1e-9)
        # the relative pose the other way round is its inverse
        back = se2_matrix(*relative_pose(b, a))
        np.testing.assert_allclose(se2_matrix(*rel) @ back, np.eye(3), atol=1e-9)
        np.testing.assert_allclose(relative_pose(a, a), np.zeros(3), atol=1e-12)


def test_sim_scene_reexports_the_same_functions():
    from traffictwin.sim import scene

    assert scene.se2_matrix is se2_matrix and scene.relative_pose is relative_pose
