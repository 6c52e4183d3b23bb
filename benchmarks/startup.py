"""Start-up time of the `traffictwin` command (prints JSON).

    python -m benchmarks.startup [--repeat 5]

- ``help``: wall time of ``traffictwin --help`` (median of ``--repeat`` runs), and which heavy
  packages importing the CLI pulls in (none of torch, Lightning, MLflow may be among them);
- ``fuse_one``: wall time of ``traffictwin fuse`` on one pair with a model folder (params.yaml's
  architecture and grid, random weights: :mod:`benchmarks.cli_load`), end to end: imports, model
  load, prealignment, forward pass, NPZ + PNG written (median of ``--repeat``);
- ``registry_unreachable``: wall time until ``traffictwin status --tracking-uri http://127.0.0.1:<closed
  port>`` gives up with its one-line error (bounded MLflow retries).

Targets: ``--help`` <= 1 s, ``fuse`` on one pair <= 3 s on the 2-core machine.
"""

from __future__ import annotations

import argparse
import json
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.cli_load import (
    ROOT,
    build_fusion_model,
    cli_env,
    load_params,
    machine_info,
    run_measured,
)

HEAVY = ("torch", "lightning", "mlflow", "torchmetrics", "pandas")


def _runs(args: list[str], cwd: Path, repeat: int) -> dict:
    """Median wall / CPU time (s) and peak RSS (MB) of ``repeat`` runs of ``traffictwin ARGS``."""
    runs = [run_measured(args, cwd) for _ in range(repeat)]
    return {
        k: round(float(np.median([r[k] for r in runs])), 3)
        for k in ("wall_s", "cpu_s", "max_rss_mb")
    }


def _dead_registry(args: list[str], cwd: Path, repeat: int) -> float:
    """Median wall time (s) of a run that must fail with exit status 1."""
    walls = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        p = subprocess.run(
            [sys.executable, "-m", "traffictwin.cli", *args],
            cwd=cwd,
            env=cli_env(),
            capture_output=True,
            text=True,
        )
        walls.append(time.perf_counter() - t0)
        if p.returncode != 1 or len(p.stderr.strip().splitlines()) != 1:
            raise RuntimeError(
                f"expected one error line and exit 1, got {p.returncode}: {p.stderr[-800:]}"
            )
    return round(float(np.median(walls)), 3)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--params", default=str(ROOT / "params.yaml"))
    a = ap.parse_args(argv)
    res: dict = {"machine": machine_info()}
    with tempfile.TemporaryDirectory(prefix="tt-startup-") as tmp:
        t = Path(tmp)
        probe = subprocess.run(
            [
                sys.executable,
                "-c",
                "import sys, traffictwin.cli; print(' '.join(sorted(sys.modules)))",
            ],
            cwd=t,
            env=cli_env(),
            capture_output=True,
            text=True,
            check=True,
        ).stdout.split()
        res["help"] = {
            **_runs(["--help"], t, a.repeat),
            "heavy_imports": sorted(m for m in HEAVY if m in probe),
            "target_s": 1.0,
        }
        cfg = load_params(Path(a.params))
        grid = build_fusion_model(t / "model", cfg)
        rng = np.random.default_rng(0)
        for k in (1, 2):
            d = rng.dirichlet([1.0, 1.0, 1.0], size=(grid["rows"], grid["cols"])).astype(np.float32)
            np.savez(t / f"m{k}.npz", m_free=d[..., 0], m_occ=d[..., 1], cell=grid["cell"])
        fuse = [
            "fuse",
            "m1.npz",
            "m2.npz",
            "--pose1",
            "0,0,0",
            "--pose2",
            "2,-1,0.05",
            "--model",
            str(t / "model"),
            "--force",
            "-o",
            "out",
        ]
        res["fuse_one"] = {
            "grid": [grid["rows"], grid["cols"]],
            **_runs(fuse, t, a.repeat),
            "target_s": 3.0,
        }
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        dead = ["status", "--tracking-uri", f"http://127.0.0.1:{port}"]
        res["registry_unreachable"] = {"wall_s": _dead_registry(dead, t, a.repeat)}
    print(json.dumps(res, indent=2))
    return res


if __name__ == "__main__":
    main()
