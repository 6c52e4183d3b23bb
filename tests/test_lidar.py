"""The VLP-32C-like lidar: beam elevations, geometry of returns, sector culling = brute force."""

import numpy as np
import pytest

from traffictwin.sim.lidar import VLP32C_ELEVATIONS_DEG, LidarSpec, scan
from traffictwin.sim.raycast import HIT_GROUND, cast_rays
from traffictwin.sim.scene import Boxes, Cls
from traffictwin.sim.traffic import sample_scenario
from traffictwin.sim.world import build_world


def test_elevations_match_vlp32c():
    spec = LidarSpec()
    el = np.rad2deg(spec.elevations)
    assert len(el) == 32 and np.all(np.diff(el) > 0)
    assert el[0] == pytest.approx(-25.0) and el[-1] == pytest.approx(15.0)
    np.testing.assert_allclose(el, sorted(VLP32C_ELEVATIONS_DEG))
    # dense around the horizon: 1/3 deg spacing between -4 and +2 deg in the datasheet table
    band = el[(el >= -4.0) & (el <= 1.7)]
    np.testing.assert_allclose(np.diff(band), 1 / 3, atol=0.01)
    u = np.rad2deg(LidarSpec(uniform=True).elevations)
    np.testing.assert_allclose(np.diff(u), 40 / 31)


def test_azimuth_grid_and_spec_errors():
    spec = LidarSpec(azimuth_res_deg=0.4)
    assert spec.n_azimuth == 900 and np.allclose(np.diff(spec.azimuths), np.deg2rad(0.4))
    with pytest.raises(ValueError, match="azimuth_res_deg"):
        LidarSpec(azimuth_res_deg=0.7)
    with pytest.raises(ValueError, match="max_range"):
        LidarSpec(max_range=0.5, min_range=1.0)


def test_ground_ranges_in_empty_world():
    spec = LidarSpec(azimuth_res_deg=2.0, max_range=100.0, range_noise=0.0)
    s = scan(spec, np.array([5.0, -3.0, 0.7]), Boxes.empty())
    el = spec.elevations
    ground_ch = spec.height / np.sin(-el[el < 0]) < spec.max_range
    # every downward channel within range hits the ground at height / sin(-elevation)
    exp = spec.height / np.sin(-el[el < 0][ground_ch])
    got = s.range[:, : ground_ch.sum()]
    assert (s.hit[:, : ground_ch.sum()] == HIT_GROUND).all()
    np.testing.assert_allclose(got, np.broadcast_to(exp, got.shape), rtol=1e-9)
    np.testing.assert_allclose(s.points[s.hit == HIT_GROUND][:, 2], 0.0, atol=1e-9)


def test_wall_ahead_in_sensor_frame():
    spec = LidarSpec(azimuth_res_deg=1.0, max_range=60.0, range_noise=0.0)
    pose = np.array([100.0, 50.0, np.pi / 2])  # facing world +y
    wall = Boxes(
        [[100.0, 60.5]], [[40.0, 1.0, 6.0]], [0.0], [Cls.WALL]
    )  # face at world y = 60, 10 m ahead
    s = scan(spec, pose, wall)
    fwd = np.abs(s.azimuth[:, 0]) < np.deg2rad(1.0)
    horiz = s.elevation == 0.0
    ray = fwd[:, None] & horiz
    assert (s.hit[ray] == 0).all()
    np.testing.assert_allclose(
        s.points[ray][:, 0], 10.0, atol=1e-3
    )  # x forward in the sensor frame


def test_sector_culling_matches_brute_force_in_a_world():
    w = build_world("cross4", 2)
    sc = sample_scenario(w, 3)
    boxes = Boxes.concat([w.static, sc.agents_at(sc.t_meet, exclude_ids=[0])])
    spec = LidarSpec(azimuth_res_deg=1.0, max_range=80.0, range_noise=0.0)
    pose = sc.subject_pose(0, sc.t_meet)
    s = scan(spec, pose, boxes)
    a = s.azimuth.ravel() + pose[2]
    e = s.elevation.ravel()
    dirs = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], 1)
    d, h = cast_rays(
        np.tile([pose[0], pose[1], spec.height], (len(dirs), 1)), dirs, boxes, spec.max_range
    )
    np.testing.assert_array_equal(s.hit.ravel(), h)
    np.testing.assert_allclose(s.range.ravel(), d, atol=1e-4)
    assert (h >= 0).mean() > 0.1


def test_noise_and_dropout_are_seeded():
    spec = LidarSpec(azimuth_res_deg=2.0, range_noise=0.05, dropout=0.1)
    pose = np.zeros(3)
    a = scan(spec, pose, Boxes.empty(), np.random.default_rng(4))
    b = scan(spec, pose, Boxes.empty(), np.random.default_rng(4))
    np.testing.assert_array_equal(a.range, b.range)
    clean = scan(spec, pose, Boxes.empty())
    ret = (a.hit == HIT_GROUND) & (clean.hit == HIT_GROUND)
    assert 0.03 < np.std(a.range[ret] - clean.range[ret]) < 0.07
    dropped = (clean.hit == HIT_GROUND) & (a.hit != HIT_GROUND)
    assert 0.05 < dropped.sum() / (clean.hit == HIT_GROUND).sum() < 0.15
