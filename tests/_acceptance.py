"""The acceptance thresholds of the committed params.yaml (conf/acceptance, composed), for tests
that judge targets the way the stages do."""

from __future__ import annotations

from functools import cache
from pathlib import Path

from traffictwin.acceptance import Threshold, for_problem
from traffictwin.config import load_params

ROOT = Path(__file__).resolve().parents[1]


@cache
def thresholds(problem: str) -> dict[str, Threshold]:
    """``acceptance.<problem>`` of params.yaml as thresholds."""
    return for_problem(load_params(ROOT / "params.yaml"), problem)
