"""Stage `environment`: record the software and hardware the pipeline ran on (reports/environment.json).

The report quotes it next to every timing, so figures always say which machine made them.
"""

from __future__ import annotations

import os
import platform
from importlib import metadata

from traffictwin.io.atomic import write_json_atomic

from ._common import ROOT, run_stage

PACKAGES = (
    "torch",
    "lightning",
    "mlflow",
    "dvc",
    "hydra-core",
    "omegaconf",
    "opencv-python-headless",
    "numpy",
    "pandas",
    "matplotlib",
)


def collect() -> dict:
    versions = {}
    for p in PACKAGES:
        try:
            versions[p] = metadata.version(p)
        except metadata.PackageNotFoundError:
            versions[p] = None
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            names = [ln.split(":", 1)[1].strip() for ln in fh if ln.startswith("model name")]
        cpu = names[0] if names else cpu
    except OSError:
        pass
    mem_gb = None
    try:
        mem_gb = round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30, 1)
    except (ValueError, OSError, AttributeError):
        pass
    import torch

    return {
        "python": platform.python_version(),
        "platform": platform.platform(terse=True),
        "cpu": cpu,
        "cpu_count": os.cpu_count(),
        "memory_gb": mem_gb,
        "cuda_available": bool(torch.cuda.is_available()),
        "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
        "packages": versions,
    }


def main() -> None:
    write_json_atomic(ROOT / "reports" / "environment.json", collect())


if __name__ == "__main__":
    run_stage(main, "environment")
