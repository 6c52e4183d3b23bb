"""Run every benchmark and write ``reports/benchmarks.json`` (``make bench``).

Each benchmark module prints one JSON object; they run one after another as subprocesses
(so their thread settings don't interfere) on an otherwise idle machine. The README quotes
the figures with the machine recorded here. Usage:
``python -m benchmarks.run [--only fusion_data risk_data ...] [--out reports/benchmarks.json]``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from traffictwin.io.atomic import write_json_atomic

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = (
    "fusion_data",
    "risk_data",
    "fusion_model",
    "registration",
    "twin",
    "cli_latency",
    "startup",
    "cli_load",
    "ci_dag",
)


def _last_json(text: str) -> dict:
    """The JSON object a benchmark printed (it may log other lines before it)."""
    lines = text.splitlines()
    for i, ln in enumerate(lines):
        if ln.strip() == "{" or ln.startswith("{"):
            try:
                return json.loads("\n".join(lines[i:]))
            except json.JSONDecodeError:
                continue
    raise ValueError("benchmark printed no JSON object")


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", nargs="*", choices=BENCHMARKS, default=list(BENCHMARKS))
    ap.add_argument("--out", default=str(ROOT / "reports" / "benchmarks.json"))
    a = ap.parse_args(argv)
    from pipelines.environment import collect

    results: dict = {"environment": collect(), "benchmarks": {}}
    out = Path(a.out)
    if (
        set(a.only) != set(BENCHMARKS) and out.exists()
    ):  # --only: keep the other benchmarks' figures
        results["benchmarks"] = dict(json.loads(out.read_text()).get("benchmarks", {}))
    for name in a.only:
        t0 = time.perf_counter()
        proc = subprocess.run(
            [sys.executable, "-m", f"benchmarks.{name}"], cwd=ROOT, capture_output=True, text=True
        )
        if proc.returncode != 0:
            raise SystemExit(f"benchmark {name} failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
        results["benchmarks"][name] = _last_json(proc.stdout)
        print(f"{name}: done in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    write_json_atomic(a.out, results)
    print(json.dumps(results["benchmarks"], indent=2))
    return results


if __name__ == "__main__":
    main()
