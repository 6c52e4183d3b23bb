"""World templates and traffic scenarios."""

import numpy as np
import pytest

from traffictwin.sim.scene import Cls
from traffictwin.sim.traffic import sample_scenario
from traffictwin.sim.world import TEMPLATES, build_world


@pytest.mark.parametrize("template", TEMPLATES)
def test_every_template_builds_and_keeps_roads_clear(template):
    w = build_world(template, 1)
    assert (
        w.template == template
        and len(w.lanes) >= 2
        and len(w.static) > 10
        and len(w.sidewalks) >= 2
    )
    xmin, ymin, xmax, ymax = w.bounds
    assert 250 <= max(xmax - xmin, ymax - ymin) <= 450  # about 400 m
    assert set(np.unique(w.static.cls)) <= {Cls.BUILDING, Cls.WALL, Cls.VEGETATION, Cls.POLE}
    # no occluder stands on a lane centreline (the roundabout's island is inside the ring)
    pts = np.concatenate([ln.centerline for ln in w.lanes])
    assert w.surface_at(w.static.center[w.static.cls == Cls.BUILDING]).max(initial=0) == 0
    assert w.surface_at(pts[::10]).min() == 1
    sc = sample_scenario(w, 5)
    for t in sc.encounter_times:
        p0, p1 = sc.subject_pose(0, t), sc.subject_pose(1, t)
        assert 6.0 <= np.hypot(*(p0[:2] - p1[:2])) <= 40.0
    b = sc.agents_at(sc.t_meet)
    assert {0, 1} <= set(b.ids.tolist()) and len(np.unique(b.ids)) == len(b)


def test_scenario_classes_velocity_and_determinism():
    w = build_world("cross4", 3)
    a = sample_scenario(w, 9).agents_at(4.0)
    b = sample_scenario(build_world("cross4", 3), 9).agents_at(4.0)
    np.testing.assert_array_equal(a.center, b.center)
    assert {Cls.CAR, Cls.PEDESTRIAN} <= set(a.cls.tolist())
    assert (np.hypot(*a.velocity.T) > 0).sum() > 5
    # velocities are consistent with motion: positions 0.1 s later
    sc = sample_scenario(w, 9)
    b0, b1 = sc.agents_at(4.0), sc.agents_at(4.1)
    common, i0, i1 = np.intersect1d(b0.ids, b1.ids, return_indices=True)
    moved = (b1.center[i1] - b0.center[i0]) / 0.1
    assert np.median(np.linalg.norm(moved - b0.velocity[i0], axis=1)) < 0.2
    # exclude the subject itself
    assert 0 not in sc.agents_at(4.0, exclude_ids=[0]).ids
    # different seeds differ
    c = sample_scenario(w, 10).agents_at(4.0)
    assert len(c) != len(a) or not np.allclose(c.center, a.center)


def test_bad_input():
    with pytest.raises(ValueError, match="unknown road template 'spaghetti'"):
        build_world("spaghetti", 0)
    with pytest.raises(ValueError, match="seed"):
        build_world("cross4", -1)
    with pytest.raises(ValueError, match="unknown density"):
        sample_scenario(build_world("cross4", 0), 0, cars_per_km=3)
    with pytest.raises(ValueError, match="subject index"):
        sample_scenario(build_world("cross4", 0), 0).subject_pose(2, 0.0)
