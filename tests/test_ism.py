"""Inverse sensor model: a wall ahead is occupied, free before it, unknown behind it."""

import numpy as np
import pytest

from traffictwin.evidential.ism import IsmParams, inverse_sensor_model
from traffictwin.grid import GridSpec
from traffictwin.sim.lidar import LidarSpec, scan
from traffictwin.sim.scene import Boxes, Cls

G = GridSpec(128, 96, 0.32)


def wall_map(params: IsmParams | None = None):
    params = params or IsmParams()
    spec = LidarSpec(azimuth_res_deg=0.4, max_range=60.0, range_noise=0.0)
    # a 30 m wide, 4 m tall wall whose near face is 10 m ahead (+x)
    wall = Boxes([[10.5, 0.0]], [[1.0, 30.0, 4.0]], [0.0], [Cls.WALL])
    return inverse_sensor_model(scan(spec, np.zeros(3), wall), G, params)


def cell(x, y):
    r, c = G.xy_to_rc(x, y)
    return int(round(float(r))), int(round(float(c)))


def test_wall_ahead():
    m = wall_map()
    assert m.shape == (2, 128, 96) and m.dtype == np.float32
    r, c = cell(10.0 + 0.16, 0.0)  # the cell holding the wall face
    assert m[1, r, c] > 0.5 and m[0, r, c] < 0.1
    for x in (3.0, 6.0, 9.0):  # before the wall: free, nothing occupied
        r, c = cell(x, 0.0)
        assert m[0, r, c] >= 0.6 and m[1, r, c] == 0.0
    for x in (12.0, 15.0, 19.0):  # behind the wall: unknown
        r, c = cell(x, 0.0)
        assert m[0, r, c] == 0.0 and m[1, r, c] == 0.0
    # behind the sensor the ground is seen: free, nothing occupied anywhere there
    assert m[1, 64:].max() == 0.0 and (m[0, 70:90, 40:56] > 0.5).all()


def test_masses_on_simplex_and_params():
    m = wall_map(IsmParams(p_free=0.3, p_ground=0.2, p_occ=0.9))
    assert m.min() >= 0 and (m.sum(0) <= 1 + 1e-6).all()
    r, c = cell(6.0, 0.0)
    assert m[0, r, c] >= 0.3
    with pytest.raises(ValueError, match="p_occ"):
        IsmParams(p_occ=1.0)
