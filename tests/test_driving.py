"""Driving sequences: determinism, speeds, situations, faults, no overlap with the subject."""

from __future__ import annotations

import numpy as np
import pytest

from traffictwin.sim.driving import (
    SITUATIONS,
    DrivingConfig,
    draw_situation,
    generate_sequence,
)
from traffictwin.sim.traffic import SUBJECT_SIZE

CFG = DrivingConfig(frames=6, fps=4.0, warmup=2.0)


def test_deterministic_for_seed_and_index():
    a = generate_sequence(7, 3, CFG)
    b = generate_sequence(7, 3, CFG)
    c = generate_sequence(7, 4, CFG)
    assert a.situation == b.situation and a.world.template == b.world.template
    for fa, fb in zip(a.frames, b.frames):
        np.testing.assert_array_equal(fa.pose, fb.pose)
        assert fa.speed == fb.speed and fa.fault == fb.fault
        np.testing.assert_array_equal(fa.boxes.center, fb.boxes.center)
    assert not np.allclose(a.frames[0].pose, c.frames[0].pose)


def test_frames_rate_speeds_and_kinematics():
    seq = generate_sequence(1, 0, CFG)
    assert len(seq.frames) == CFG.frames
    t = np.array([f.t for f in seq.frames])
    np.testing.assert_allclose(np.diff(t), 1 / CFG.fps)
    for f in seq.frames:
        assert 0.0 <= f.speed <= CFG.max_speed + 1e-6
    # the subject moves about speed * dt between frames
    p = np.array([f.pose[:2] for f in seq.frames])
    v = np.array([f.speed for f in seq.frames])
    step = np.linalg.norm(np.diff(p, axis=0), axis=1)
    np.testing.assert_allclose(step, (v[:-1] + v[1:]) / 2 / CFG.fps, atol=0.6)


@pytest.mark.parametrize("allowed", [("cut_in",), ("free", "pedestrian")])
def test_situation_weights_control_situations(allowed):
    weights = tuple((n, 1.0 if n in allowed else 0.0) for n in SITUATIONS)
    cfg = DrivingConfig(frames=2, warmup=1.0, situations=weights)
    for i in range(4):
        seq = generate_sequence(2, i, cfg)
        assert seq.situation in allowed
        assert seq.situation == draw_situation(2, i, weights)  # known before simulating


def test_situation_draw_follows_weights():
    weights = (("free", 3.0), ("cut_in", 1.0))
    got = [draw_situation(0, i, weights) for i in range(2000)]
    assert got.count("free") / len(got) == pytest.approx(0.75, abs=0.03)


def test_frames_carry_the_lane_path_ahead():
    seq = generate_sequence(1, 2, CFG)
    for f in seq.frames:
        assert f.path.shape[1] == 2 and len(f.path) > 20
        np.testing.assert_allclose(f.path[0], f.pose[:2], atol=1e-6)  # starts at the subject
        step = np.linalg.norm(np.diff(f.path, axis=0), axis=1)
        np.testing.assert_allclose(step, 0.5, atol=0.05)  # 0.5 m of arc between points
        assert 2.5 <= f.lane_width <= 4.5


def test_faults_are_injected_as_configured():
    cfg = DrivingConfig(
        frames=40, warmup=1.0, fault_delay=0.5, fault_vertical=0.5, vertical_px=(6.0, 9.0)
    )
    seq = generate_sequence(3, 0, cfg)
    faults = [f.fault for f in seq.frames]
    assert set(faults) <= {"delay", "vertical"} and "delay" in faults and "vertical" in faults
    for f in seq.frames:
        if f.fault == "vertical":
            assert 6.0 <= abs(f.right_cy_offset) <= 9.0
            np.testing.assert_array_equal(f.pose_right, f.pose)
        else:
            assert f.right_cy_offset == 0.0
            if f.speed > 1.0:  # one frame (88 ms) later, the subject moved forward
                assert np.linalg.norm(f.pose_right[:2] - f.pose[:2]) == pytest.approx(
                    f.speed * cfg.delay, rel=0.2
                )
    clean = generate_sequence(
        3, 0, DrivingConfig(frames=10, warmup=1.0, fault_delay=0.0, fault_vertical=0.0)
    )
    assert all(f.fault == "none" for f in clean.frames)


def test_no_agent_overlaps_the_subject():
    for i in range(3):
        seq = generate_sequence(5, i, CFG)
        for f in seq.frames:
            b = f.boxes.subset(f.boxes.ids < 1_000_000)
            c, s = np.cos(f.pose[2]), np.sin(f.pose[2])
            d = b.center - f.pose[:2]
            x, y = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]
            hit = (np.abs(x) < (SUBJECT_SIZE[0] + b.size[:, 0]) / 2) & (
                np.abs(y) < (SUBJECT_SIZE[1] + b.size[:, 1]) / 2
            )
            assert not hit.any()


def test_bad_config_raises():
    with pytest.raises(ValueError, match="unknown situations"):
        DrivingConfig(situations=(("joyride", 1.0),))
    with pytest.raises(ValueError, match="weights"):
        DrivingConfig(situations=(("free", 0.0),))
    with pytest.raises(ValueError, match="parked_prob"):
        DrivingConfig(parked_prob=(0.5, 0.2))
    with pytest.raises(ValueError, match="templates"):
        DrivingConfig(templates=("moon_base",))
