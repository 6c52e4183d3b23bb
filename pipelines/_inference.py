"""Torch's CPU threads for the evaluation stages' inference: ``evaluation.num_threads`` of params.yaml.

Torch splits float reductions (convolutions, FFTs, sums) into one chunk per intra-op thread, so a
network's outputs differ in the last bits between thread counts, and torch's default count follows
the machine (its cores, the process's CPU affinity). The evaluation stages fix the count instead,
so their numbers stay the same on a machine with another core count or under another affinity
(``torch.set_num_threads`` also sets MKL's count and turns its dynamic adjustment off).
"""

from __future__ import annotations

from typing import Any

THREADS_KEY = "evaluation.num_threads"


def pin_torch_threads(cfg: Any) -> int:
    """Set torch's intra-op CPU threads to ``evaluation.num_threads`` (an int ≥ 1) of ``cfg``;
    returns it (for the stage's run record: the wall times it records depend on it)."""
    from traffictwin.config import get
    from traffictwin.threads import pin_threads

    n = get(cfg, THREADS_KEY, int, min=1)
    pin_threads(n)
    return n
