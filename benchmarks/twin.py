"""Twin update time per step vs the number of vehicles N, per twin method (prints JSON).

    python -m benchmarks.twin [--cfg D] [--vehicles 2 3 5 8] [--frames 3] [--repeats 3] [--threads 0]

Simulates one cooperative sequence with max(N) vehicles (:mod:`traffictwin.sim.cooperative`, the
default grid, lidar and ISM of params.yaml), draws the poses' noise of configuration ``--cfg``, and
times :meth:`traffictwin.twin.fuse.Twin.update` with the first N vehicles' maps for every method
whose models exist (``models/registration/<cfg>``, the registered-pairs network of ``<cfg>``):
median ms per step over ``--frames`` frames x ``--repeats`` passes (after one warm-up step). The
issue-19 target: 3 vehicles <= 100 ms per step (10 Hz). The JSON records the CPU, torch threads
and the load average, since figures depend on the load.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
from dataclasses import replace
from pathlib import Path

import torch

from benchmarks.fusion_model import _cpu_name

ROOT = Path(__file__).resolve().parents[1]
METHODS = ("naive", "registered", "learned", "learned+network")


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cfg", default="D")
    ap.add_argument("--vehicles", type=int, nargs="+", default=[2, 3, 5, 8])
    ap.add_argument("--frames", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0 = torch's default)")
    a = ap.parse_args(argv)
    if a.threads > 0:
        torch.set_num_threads(a.threads)
    from pipelines._common import params
    from pipelines.evaluate_twin import method_models
    from traffictwin.fusion.config import (
        fusion_data_config,
        fusion_eval_config,
        grid_config,
        pose_configurations,
    )
    from traffictwin.twin.config import twin_config
    from traffictwin.twin.data import TwinDataParams, sequence_arrays
    from traffictwin.twin.evaluation import noisy_relative_poses
    from traffictwin.twin.fuse import Twin

    cfg = params(ROOT / "params.yaml")
    grid = grid_config(cfg)
    fd = fusion_data_config(cfg).params(grid)
    tc = twin_config(cfg)
    n_max = max(a.vehicles)
    scenario = replace(tc.scenario(), vehicles=n_max, frames=a.frames + 1)
    arrays = sequence_arrays(int(cfg["seed"]), 0, TwinDataParams(grid, fd.lidar, fd.ism, scenario))
    pn = pose_configurations(cfg)[a.cfg]
    rel = noisy_relative_poses(arrays["poses"], arrays["noise_z"], pn.r, pn.alpha)
    models, skipped = method_models(cfg, a.cfg, list(METHODS), grid)
    reg = fusion_eval_config(cfg).registration_params
    out_ms: dict[str, dict[str, float]] = {}
    for m, mod in models.items():
        out_ms[m] = {}
        for n in a.vehicles:
            times = []
            for _ in range(a.repeats):
                twin = Twin(grid, m, models=mod, registration=reg, strategy=tc.strategy)
                twin.update(0.0, arrays["maps"][0, :n], rel[0, :n])  # warm-up
                for t in range(1, a.frames + 1):
                    step = twin.update(float(t), arrays["maps"][t, :n], rel[t, :n])
                    times.append(1000.0 * step.seconds)
            out_ms[m][str(n)] = round(statistics.median(times), 1)
    out = {
        "cfg": a.cfg,
        "grid": [grid.rows, grid.cols, grid.cell],
        "strategy": tc.strategy,
        "ms_per_step": out_ms,
        "skipped": skipped,
        "target_ms_3_vehicles": 100.0,
        "cpu": _cpu_name(),
        "torch_threads": torch.get_num_threads(),
        "load_average": list(os.getloadavg()),
    }
    print(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main()
