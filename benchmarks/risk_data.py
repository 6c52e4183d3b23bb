"""Throughput of the risk data part: stereo rendering, SGM, ORB check, risk metric (frames/s, 1 core).

``python -m benchmarks.risk_data [--frames N] [--width W --height H]`` prints JSON. Frames come
from real driving sequences (world + traffic) at the default camera resolution.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import numpy as np

from traffictwin.grid import GridSpec
from traffictwin.risk.metric import RiskCalculator, RiskConfig
from traffictwin.sim.camera import GroundTexture, StereoCamera
from traffictwin.sim.driving import DrivingConfig, generate_sequence
from traffictwin.stereo.orb import check_pair
from traffictwin.stereo.sgm import compute_disparity, make_matcher


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=160)
    ap.add_argument("--num-disparities", type=int, default=32)
    a = ap.parse_args(argv)
    cam = StereoCamera(width=a.width, height=a.height)
    cfg = DrivingConfig(frames=10)
    frames = []
    i = 0
    while len(frames) < a.frames:
        s = generate_sequence(0, i, cfg)
        g = GroundTexture.from_world(s.world)
        frames += [(f, g) for f in s.frames]
        i += 1
    frames = frames[: a.frames]
    rng = np.random.default_rng(0)
    t0 = time.perf_counter()
    pairs = [cam.render_pair(f.pose, f.boxes, g, rng=rng) for f, g in frames]
    t_render = time.perf_counter() - t0
    m = make_matcher(a.num_disparities, 5, 3)
    t0 = time.perf_counter()
    for p in pairs:
        compute_disparity(p["left"], p["right"], matcher=m)
    t_sgm = time.perf_counter() - t0
    t0 = time.perf_counter()
    for p in pairs:
        check_pair(p["left"], p["right"])
    t_orb = time.perf_counter() - t0
    calc = RiskCalculator(GridSpec(), RiskConfig(subject_length=4.8, subject_width=1.9))
    t0 = time.perf_counter()
    for f, _ in frames:
        calc(f.pose, f.speed, f.boxes)
    t_risk = time.perf_counter() - t0
    n = len(frames)
    out = {
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cpus",
        "resolution": f"{a.width}x{a.height}",
        "frames": n,
        "render_pairs_per_s": n / t_render,
        "sgm_frames_per_s": n / t_sgm,
        "orb_frames_per_s": n / t_orb,
        "risk_metric_frames_per_s": n / t_risk,
        "render_ms_per_pair": 1000 * t_render / n,
        "sgm_ms_per_frame": 1000 * t_sgm / n,
        "orb_ms_per_frame": 1000 * t_orb / n,
        "risk_metric_ms_per_frame": 1000 * t_risk / n,
    }
    print(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main()
