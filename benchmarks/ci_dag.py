"""Wall time of the whole DAG on the ``ci`` profile, and where it goes (prints JSON).

    python -m benchmarks.ci_dag [--keep DIR]

Clones the repository's committed ``HEAD`` (``git clone``: uncommitted changes are not measured)
into a temp folder, composes ``params.yaml`` for ``profile=ci`` and runs ``dvc repro`` there with
its own MLflow database, as the README's Quick start does. Reports:

- ``wall_s`` / ``cpu_s``: the ``dvc repro`` (CPU = user + system of DVC and every stage process);
- ``stages``: how many stage commands ran; ``in_stage_s``: the sum of the stages' own timed work
  (``seconds`` of each run record ``reports/timings/<stage>.json``: after the stage's imports);
- ``outside_stage_s`` = wall - in-stage: process start, imports, DVC hashing and lock writes;
- ``per_stage``: each run record's ``seconds`` (and ``train_seconds`` for trainings);
- ``imports_s``: wall time of ``python -c "import X"`` for the heavy packages a stage may load;
- ``noop_s``: a second ``dvc repro`` with nothing to do.

Target: <= 90 s wall on the 2-core machine.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.cli_load import ROOT, machine_info

HEAVY = ("numpy", "cv2", "torch", "lightning", "mlflow")


def _env(repo: Path) -> dict[str, str]:
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    env["PYTHONPATH"] = os.pathsep.join((str(repo / "src"), str(repo)))  # the clone's code
    env["MLFLOW_TRACKING_URI"] = f"sqlite:///{repo / 'mlflow.db'}"
    env["TQDM_DISABLE"] = "1"
    return env


def _timed(cmd: list[str], repo: Path) -> tuple[float, float, str]:
    """Wall and CPU seconds (user + system of the command and its children) and its output."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    p = subprocess.run(cmd, cwd=repo, env=_env(repo), capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if p.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({p.returncode}):\n{p.stderr[-3000:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, p.stdout + p.stderr


def _import_s(module: str) -> float:
    """Median wall time (s) of three ``python -c "import MODULE"``."""
    walls = []
    for _ in range(3):
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-c", f"import {module}"], check=True)
        walls.append(time.perf_counter() - t0)
    return round(sorted(walls)[1], 2)


def per_stage(repo: Path) -> dict[str, dict[str, float]]:
    """``seconds`` (and ``train_seconds``) of every run record in ``repo/reports/timings``."""
    out = {}
    for f in sorted((repo / "reports" / "timings").glob("*.json")):
        rec = json.loads(f.read_text())
        if isinstance(rec, dict) and "seconds" in rec:
            out[f.stem] = {k: rec[k] for k in ("seconds", "train_seconds") if k in rec}
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--keep", help="clone into this folder (must not exist) and keep it")
    a = ap.parse_args(argv)
    res: dict = {"machine": machine_info(), "target_s": 90.0}
    tmp = None if a.keep else tempfile.mkdtemp(prefix="tt-ci-dag-")
    repo = Path(a.keep) if a.keep else Path(tmp) / "repo"
    try:
        subprocess.run(["git", "clone", "-q", str(ROOT), str(repo)], check=True)
        res["commit"] = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=repo, capture_output=True, text=True
        ).stdout.strip()
        # committed run records are the default profile's: only this run's count
        shutil.rmtree(repo / "reports" / "timings", ignore_errors=True)
        _timed([sys.executable, "-m", "pipelines.compose_params", "profile=ci"], repo)
        wall, cpu, log = _timed(["dvc", "repro"], repo)
        stages = per_stage(repo)
        in_stage = sum(s["seconds"] for s in stages.values())
        res.update(
            wall_s=round(wall, 1),
            cpu_s=round(cpu, 1),
            stages=log.count("Running stage '"),
            in_stage_s=round(in_stage, 1),
            outside_stage_s=round(wall - in_stage, 1),
            per_stage=stages,
        )
        res["noop_s"] = round(_timed(["dvc", "repro"], repo)[0], 1)
    finally:
        if tmp:
            shutil.rmtree(tmp, ignore_errors=True)
    res["imports_s"] = {m: _import_s(m) for m in HEAVY}
    print(json.dumps(res, indent=2))
    return res


if __name__ == "__main__":
    main()
