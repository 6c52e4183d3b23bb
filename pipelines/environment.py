"""Stage `environment`: record the software the pipeline ran with (reports/environment.json, a DVC
output) and the machine it ran on (its run record reports/timings/environment.json, outside DVC).

The machine is a property of the run, not of the results: on a virtual machine the CPU model, the
kernel build and the memory total can change between two identical runs (live migration, memory
ballooning), so they go to the run record, beside the wall times, and an identical `dvc repro -f`
leaves dvc.lock unchanged.
"""

from __future__ import annotations

import os
import platform
from importlib import metadata

from traffictwin.io.atomic import write_json_atomic

from ._common import ROOT, cpu_model, run_stage, stage_timer

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


#: keys of :func:`collect` that describe the machine (run record only)
MACHINE_KEYS = ("platform", "cpu", "cpu_count", "memory_gb", "cuda_available", "gpu")


def collect() -> dict:
    """Software versions and machine facts (memory in GiB)."""
    versions = {}
    for p in PACKAGES:
        try:
            versions[p] = metadata.version(p)
        except metadata.PackageNotFoundError:
            versions[p] = None
    cpu = cpu_model()
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
    env = collect()
    with stage_timer("environment") as record:
        record.update({k: env[k] for k in MACHINE_KEYS})
        software = {k: v for k, v in env.items() if k not in MACHINE_KEYS}
        write_json_atomic(ROOT / "reports" / "environment.json", software)


if __name__ == "__main__":
    run_stage(main, "environment")
