"""Where the evaluation stages keep the arrays of the figures plot_data draws (apart from
:mod:`pipelines._paths`, which every stage imports: only these three stages depend on it)."""

from __future__ import annotations

from pathlib import Path

from ._paths import DATA

FIGURE_INPUTS = DATA / "figure_inputs"


def figure_input(name: str) -> Path:
    """data/figure_inputs/<name>.npz (:mod:`traffictwin.io.figure_inputs`)."""
    return FIGURE_INPUTS / f"{name}.npz"
