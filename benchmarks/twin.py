"""Twin update time per step vs the number of vehicles N, per twin method (prints JSON).

    python -m benchmarks.twin [--cfg D] [--vehicles 2 3 5 8] [--frames 3] [--repeats 3] [--threads 0]
        [--methods naive learned]

Simulates one cooperative sequence with max(N) vehicles (:mod:`traffictwin.sim.cooperative`, the
default grid, lidar and ISM of params.yaml), draws the poses' noise of configuration ``--cfg``, and
times :meth:`traffictwin.twin.fuse.Twin.update` with the first N vehicles' maps for every method
whose models exist (``models/registration/<cfg>``, the registered-pairs network of ``<cfg>``):
median ms per step over ``--frames`` frames x ``--repeats`` passes (after one warm-up step). Each
step includes the predictive hazard measure (:mod:`traffictwin.twin.predict`: optical flow between
the previous and the new twin, ego-motion compensated, and the time to conflict; its own median
``ttc_ms``, and ``ms_per_step_without_ttc``). The twin's target: 3 vehicles <= 100 ms per
step (10 Hz), motion estimation included. The JSON records the CPU, torch threads
and the load average, since figures depend on the load.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from dataclasses import replace
from pathlib import Path

import torch

from benchmarks.fusion_model import _cpu_name
from traffictwin.threads import pin_threads

ROOT = Path(__file__).resolve().parents[1]
METHODS = ("naive", "registered", "learned", "learned+network")


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cfg", default="D")
    ap.add_argument("--vehicles", type=int, nargs="+", default=[2, 3, 5, 8])
    ap.add_argument("--frames", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0 = torch's default)")
    ap.add_argument(
        "--methods",
        nargs="+",
        default=None,
        help="twin methods (default: twin.methods of params.yaml)",
    )
    a = ap.parse_args(argv)
    if a.threads > 0:
        pin_threads(a.threads)
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
    from traffictwin.twin.evaluation import noisy_relative_poses, ttc_reader
    from traffictwin.twin.fuse import Twin, TwinOptions

    cfg = params(ROOT / "params.yaml")
    grid = grid_config(cfg)
    fd = fusion_data_config(cfg).params(grid)
    tc = twin_config(cfg)
    n_max = max(a.vehicles)
    scenario = replace(tc.scenario(), vehicles=n_max, frames=a.frames + 1, hidden_s=0.0)
    arrays = sequence_arrays(int(cfg["seed"]), 0, TwinDataParams(grid, fd.lidar, fd.ism, scenario))
    pn = pose_configurations(cfg)[a.cfg]
    rel = noisy_relative_poses(arrays["poses"], arrays["noise_z"], pn.r, pn.alpha)
    models, skipped = method_models(cfg, a.cfg, list(a.methods or tc.methods), grid)
    reg = fusion_eval_config(cfg).registration_params
    read_ttc = ttc_reader(grid, tc.settings(), float(scenario.fps))
    ego = arrays["poses"][:, 0]
    out_ms: dict[str, dict[str, float]] = {}
    out_twin: dict[str, dict[str, float]] = {}
    out_ttc: dict[str, dict[str, float]] = {}
    for m, mod in models.items():
        out_ms[m], out_twin[m], out_ttc[m] = {}, {}, {}
        for n in a.vehicles:
            times, twin_t, ttc_t = [], [], []
            for _ in range(a.repeats):
                twin = Twin(grid, TwinOptions(m, tc.strategy, models=mod, registration=reg))
                prev = twin.update(0.0, arrays["maps"][0, :n], rel[0, :n]).masses  # warm-up
                for t in range(1, a.frames + 1):
                    step = twin.update(float(t), arrays["maps"][t, :n], rel[t, :n])
                    t0 = time.perf_counter()
                    read_ttc(
                        prev,
                        step.masses,
                        ego[t - 1],
                        ego[t],
                        float(arrays["speeds"][t, 0]),
                        arrays["path"][t],
                        float(arrays["lane_width"][t]),
                    )
                    dt = time.perf_counter() - t0
                    prev = step.masses
                    times.append(1000.0 * (step.seconds + dt))
                    twin_t.append(1000.0 * step.seconds)
                    ttc_t.append(1000.0 * dt)
            out_ms[m][str(n)] = round(statistics.median(times), 1)
            out_twin[m][str(n)] = round(statistics.median(twin_t), 1)
            out_ttc[m][str(n)] = round(statistics.median(ttc_t), 1)
    out = {
        "cfg": a.cfg,
        "grid": [grid.rows, grid.cols, grid.cell],
        "strategy": tc.strategy,
        "ms_per_step": out_ms,
        "ms_per_step_without_ttc": out_twin,
        "ttc_ms": out_ttc,
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
