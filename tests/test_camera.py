"""Stereo camera: exact depth/disparity on planes, rectified rows, faults, texture consistency."""

from __future__ import annotations

import numpy as np
import pytest

from traffictwin.sim.camera import GroundTexture, StereoCamera, value_noise
from traffictwin.sim.scene import Boxes, Cls


def wall_at(cam: StereoCamera, depth: float) -> Boxes:
    """A huge fronto-parallel wall whose near face is ``depth`` m in front of the cameras."""
    return Boxes([[cam.mount_x + depth + 0.5, 0.0]], [[1.0, 400.0, 100.0]], [0.0], [Cls.WALL])


def test_intrinsics_hand_values():
    cam = StereoCamera(width=320, height=160, hfov_deg=90.0)
    assert cam.fx == pytest.approx(160.0)
    assert (cam.cx, cam.cy) == (159.5, 79.5)
    k = cam.intrinsics()
    for key in ("width", "height", "fx", "fy", "cx", "cy", "baseline", "mount_x", "mount_height"):
        assert key in k
    assert k["baseline"] == 0.16


def test_plane_at_known_depth_gives_expected_disparity():
    cam = StereoCamera(noise_std=0.0)
    Z = 10.0
    out = cam.render_pair((0.0, 0.0, 0.0), wall_at(cam, Z))
    expected = cam.fx * cam.baseline / Z
    rows = np.arange(cam.height)
    ground = np.full(cam.height, np.inf)
    below = rows > cam.cy
    ground[below] = cam.mount_height * cam.fy / (rows[below] - cam.cy)
    want_depth = np.minimum(ground, Z)[:, None] * np.ones((1, cam.width))
    np.testing.assert_allclose(out["depth"], want_depth, rtol=1e-5)
    # every pixel that sees the wall has exactly f*B/Z
    wall = want_depth == Z
    assert wall.sum() > cam.width * cam.height / 3
    np.testing.assert_allclose(out["disp_gt"][wall], expected, rtol=1e-5)
    # ground pixels: f*B/Z of the ground depth, all > the wall's disparity
    assert np.all(out["disp_gt"][~wall] > expected)


def test_sky_has_zero_disparity():
    cam = StereoCamera(noise_std=0.0)
    out = cam.render_pair((0.0, 0.0, 0.0), Boxes.empty())
    top = out["disp_gt"][: int(cam.cy)]
    assert np.all(top == 0.0) and np.all(np.isinf(out["depth"][: int(cam.cy)]))


def test_left_right_rows_align_and_shift_by_disparity():
    cam = StereoCamera(noise_std=0.0, width=320, height=160, hfov_deg=60.0)
    d = 8  # integer disparity
    Z = cam.fx * cam.baseline / d
    out = cam.render_pair((0.0, 0.0, 0.0), wall_at(cam, Z), GroundTexture.plain())
    rows = slice(5, int(cam.cy) - 2)  # wall only
    L = out["left"][rows, d + 10 : -10].astype(float)
    R = out["right"][rows, 10 : -10 - d].astype(float)
    diff = np.abs(L - R)
    assert diff.mean() < 0.5
    assert np.mean(diff <= 2) > 0.99
    # a 3-row vertical offset breaks the match: the comparison can fail
    off = np.abs(
        out["left"][8 : int(cam.cy) + 1, d + 10 : -10].astype(float)
        - out["right"][rows, 10 : -10 - d]
    )
    assert off.mean() > 4 * max(diff.mean(), 0.25)


def test_vertical_misalignment_shifts_right_image_rows():
    cam = StereoCamera(noise_std=0.0)
    scene = wall_at(cam, 12.0)
    base = cam.render_eye((0, 0, 0), scene, eye="right")[0]
    shifted = cam.render_eye((0, 0, 0), scene, eye="right", cy_offset=6.0)[0]
    diff = np.abs(shifted[6 + 2 : -2].astype(float) - base[2:-8].astype(float))
    assert diff.mean() < 0.5


def test_box_depth_and_occlusion():
    cam = StereoCamera(noise_std=0.0)
    near = Boxes([[cam.mount_x + 6.0 + 2.25, 0.0]], [[4.5, 1.8, 1.5]], [0.0], [Cls.CAR])
    far = wall_at(cam, 30.0)
    out = cam.render_pair((0.0, 0.0, 0.0), Boxes.concat([near, far]))
    # the centre pixel slightly below the horizon looks at the car's rear face at 6 m
    v, u = int(cam.cy) + 3, int(cam.cx)
    assert out["depth"][v, u] == pytest.approx(6.0, rel=1e-5)
    assert out["disp_gt"][v, u] == pytest.approx(cam.fx * cam.baseline / 6.0, rel=1e-5)
    assert out["depth"][5, 5] == pytest.approx(30.0, rel=1e-5)


def test_pose_and_yaw_move_the_view():
    cam = StereoCamera(noise_std=0.0)
    # the same wall seen from a pose rotated by 90 deg and moved: identical depth map
    wall_rot = Boxes([[0.0, cam.mount_x + 10.5]], [[1.0, 400.0, 100.0]], [np.pi / 2], [Cls.WALL])
    a = cam.render_eye((0.0, 0.0, 0.0), wall_at(cam, 10.0))[1]
    b = cam.render_eye((0.0, 0.0, np.pi / 2), wall_rot)[1]
    np.testing.assert_allclose(a, b, rtol=1e-5)


def test_noise_is_seeded_and_images_are_uint8():
    cam = StereoCamera(noise_std=3.0)
    s = wall_at(cam, 10.0)
    a = cam.render_pair((0, 0, 0), s, rng=np.random.default_rng(1))
    b = cam.render_pair((0, 0, 0), s, rng=np.random.default_rng(1))
    c = cam.render_pair((0, 0, 0), s, rng=np.random.default_rng(2))
    assert a["left"].dtype == np.uint8 and a["left"].shape == (cam.height, cam.width, 3)
    assert np.array_equal(a["left"], b["left"]) and not np.array_equal(a["left"], c["left"])


def test_value_noise_range_and_determinism():
    x = np.linspace(-50, 50, 1000)
    n1 = value_noise(x, x * 0.3, 5, (0.1, 0.5), (1, 1))
    n2 = value_noise(x, x * 0.3, 5, (0.1, 0.5), (1, 1))
    assert np.array_equal(n1, n2) and n1.min() >= 0 and n1.max() <= 1 and n1.std() > 0.05


def test_bad_camera_config_raises():
    with pytest.raises(ValueError, match="hfov"):
        StereoCamera(hfov_deg=200)
    with pytest.raises(ValueError, match="eye"):
        StereoCamera().eye_pose((0, 0, 0), "middle")
