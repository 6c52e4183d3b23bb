"""Registration speed per pair on this machine: learned vs classical (prints JSON).

    python -m benchmarks.registration [--cfg D] [--pairs 64] [--repeats 5] [--threads 0]

On the first ``--pairs`` test pairs of ``data/prealigned/<cfg>`` (and their raw maps in
``data/fusion``), with the trained ``models/registration/<cfg>`` (run ``dvc repro`` first):

- ``learned_ms_per_pair``: the registry method ``learned`` (estimate, fallback check, warp of
  the raw map 2 by the pose used, Dempster) at batch 1 and batch 8 — the figure the latency target
  (≤ 20 ms per pair) is about; ``learned_estimate_ms_per_pair``: the network's estimate alone;
- ``registered_ms_per_pair``: the classical ``registered`` method (Fourier–Mellin + ECC, warp,
  Dempster), one pair at a time as it always runs.

Each figure is the median over ``--repeats`` passes over the pairs (after one warm-up pass); the
JSON records the CPU, torch threads and the load average, since figures depend on the load.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.fusion_model import _cpu_name
from traffictwin.fusion.learned_registration import rotation_centres
from traffictwin.fusion.methods import METHODS, FusionInput
from traffictwin.fusion.registration_training import load_registration_model
from traffictwin.grid import GridSpec
from traffictwin.io.shards import Dataset
from traffictwin.threads import pin_threads

ROOT = Path(__file__).resolve().parents[1]


def _median_ms(fn, n_pairs: int, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(1000.0 * (time.perf_counter() - t0) / n_pairs)
    return round(statistics.median(times), 2)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cfg", default="D")
    ap.add_argument("--pairs", type=int, default=64)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0 = torch's default)")
    a = ap.parse_args(argv)
    if a.threads > 0:
        pin_threads(a.threads)
    pre = Dataset(ROOT / "data" / "prealigned" / a.cfg, kind="prealigned").load_all("test")
    n = min(a.pairs, len(pre["pair_id"]))
    net = load_registration_model(ROOT / "models" / "registration" / a.cfg)
    g = GridSpec(**net.meta["grid"])
    from traffictwin.fusion.evaluation import load_raw_pairs

    raw = load_raw_pairs(ROOT / "data" / "fusion", pre["pair_id"][:n], "test", g)
    x = FusionInput(
        inputs=pre["inputs"][:n],
        map1=raw["map1"],
        map2=raw["map2"],
        rel_pose_noisy=pre["rel_pose_noisy"][:n],
        rel_pose_true=pre["rel_pose_true"][:n],
        grid=g,
        model=net,
    )

    def learned(batch: int):
        def run() -> None:
            for s in range(0, n, batch):
                METHODS["learned"](x.take(slice(s, s + batch)))

        return run

    inputs = torch.from_numpy(np.ascontiguousarray(pre["inputs"][:n], dtype=np.float32))
    centres = torch.from_numpy(rotation_centres(pre["rel_pose_noisy"][:n], g)).float()

    def estimate() -> None:
        with torch.inference_mode():
            for s in range(0, n, 8):
                net.estimate(inputs[s : s + 8], centres[s : s + 8])

    def registered() -> None:
        METHODS["registered"](x)

    out = {
        "cfg": a.cfg,
        "pairs": n,
        "grid": [g.rows, g.cols, g.cell],
        "fine_iterations": net.fine_iterations,
        "learned_ms_per_pair": {
            "batch_1": _median_ms(learned(1), n, a.repeats),
            "batch_8": _median_ms(learned(8), n, a.repeats),
        },
        "learned_estimate_ms_per_pair": _median_ms(estimate, n, a.repeats),
        "registered_ms_per_pair": _median_ms(registered, n, max(1, a.repeats // 2)),
        "cpu": _cpu_name(),
        "torch_threads": torch.get_num_threads(),
        "load_average": list(os.getloadavg()),
    }
    print(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main()
