"""Throughput of the fusion data part (1 core): pair generation, lidar scan, ISM, Dempster.

``python -m benchmarks.fusion_data [--scenarios N] [--repeats R]`` prints JSON: pairs/s for the
whole generation (world, traffic, 2 scans + 2 ISMs per encounter, warps, Dempster labels), ms
per lidar scan and per ISM (VLP-32C-like, 0.2 deg azimuth, 1800 x 32 rays) and ms per Dempster
fusion / warp of a full 256 x 176 grid. Numbers depend on the machine's load: say so with them.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import cv2
import numpy as np

from traffictwin.evidential.dempster import dempster
from traffictwin.evidential.ism import inverse_sensor_model
from traffictwin.evidential.warp import warp_masses
from traffictwin.fusion.pairs import FusionDataParams, generate_shard
from traffictwin.grid import GridSpec
from traffictwin.sim.lidar import LidarSpec, scan
from traffictwin.sim.scene import Boxes
from traffictwin.sim.traffic import sample_scenario
from traffictwin.sim.world import build_world


def _ms(fn, repeats: int) -> float:
    fn()
    t0 = time.perf_counter()
    for _ in range(repeats):
        fn()
    return 1000 * (time.perf_counter() - t0) / repeats


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument(
        "--scenarios", type=int, default=4, help="scenarios for the generation throughput"
    )
    ap.add_argument("--repeats", type=int, default=20)
    a = ap.parse_args(argv)
    cv2.setNumThreads(1)
    grid = GridSpec(256, 176, 0.32)
    lidar = LidarSpec(azimuth_res_deg=0.2, max_range=80.0, dropout=0.02)
    p = FusionDataParams(
        grid=grid, lidar=lidar, scenarios_per_shard=a.scenarios, encounters_per_scenario=4
    )
    t0 = time.perf_counter()
    arrays = generate_shard(0, 0, p)
    t_gen = time.perf_counter() - t0

    w = build_world("cross4", 1)
    sc = sample_scenario(w, 2)
    boxes = Boxes.concat([w.static, sc.agents_at(sc.t_meet, exclude_ids=[0])])
    pose = sc.subject_pose(0, sc.t_meet)
    rng = np.random.default_rng(0)
    s = scan(lidar, pose, boxes, rng)
    m1, m2 = arrays["map1"][0], arrays["map2"][0]
    rel = np.array([12.0, -4.0, 0.6])
    out = {
        "machine": {
            "cpu": platform.processor() or platform.machine(),
            "cores": os.cpu_count(),
            "python": platform.python_version(),
            "load_avg_1min": os.getloadavg()[0],
        },
        "grid": [grid.rows, grid.cols, grid.cell],
        "lidar_rays": int(s.range.size),
        "generation_pairs": int(len(arrays["map1"])),
        "generation_pairs_per_s_1core": round(len(arrays["map1"]) / t_gen, 2),
        "lidar_scan_ms": round(_ms(lambda: scan(lidar, pose, boxes, rng), a.repeats), 2),
        "ism_ms": round(_ms(lambda: inverse_sensor_model(s, grid), a.repeats), 2),
        "dempster_ms": round(_ms(lambda: dempster(m1, m2), a.repeats * 5), 3),
        "warp_ms": round(_ms(lambda: warp_masses(m2, rel, grid), a.repeats * 5), 3),
    }
    print(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main()
