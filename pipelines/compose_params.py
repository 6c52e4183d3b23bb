"""Write params.yaml = the Hydra composition of conf/ (``make params``).

Usage: ``python -m pipelines.compose_params [override ...]`` e.g. ``profile=ci``.
"""

from __future__ import annotations

import sys
from pathlib import Path

from traffictwin.config import compose_config, dump_params

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> None:
    overrides = sys.argv[1:] if argv is None else argv
    cfg = compose_config(ROOT / "conf", overrides)
    dump_params(cfg, ROOT / "params.yaml")
    print(f"params.yaml composed from conf/ (overrides: {overrides or 'none'})")


if __name__ == "__main__":
    from pipelines._common import run_stage

    run_stage(main, "compose_params")  # a bad override: one line naming it, exit 2
