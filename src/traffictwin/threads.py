"""CPU threads of a process: torch's intra-op thread count and OpenMP's wait policy.

Torch splits float reductions into one chunk per intra-op thread, so outputs differ in the last
bits between thread counts (``docs/design.md``, *Data*: evaluation pins its count). Torch is
imported only when a count is set, so importing this module costs nothing at CLI start-up.
"""

from __future__ import annotations

import os

__all__ = ["passive_omp_wait", "pin_threads"]


def pin_threads(n: int | None) -> int:
    """Set torch's intra-op CPU threads to ``n`` (also MKL's; ``None`` or 0: leave torch's
    default); returns the count torch uses now. A negative ``n`` is a ``ValueError``."""
    if n is not None and n < 0:
        raise ValueError(f"pin_threads: thread count must be >= 0 (0: torch's default), got {n}")
    import torch

    if n:
        torch.set_num_threads(int(n))
    return torch.get_num_threads()


def passive_omp_wait() -> None:
    """``OMP_WAIT_POLICY=PASSIVE`` unless already set: OpenMP threads sleep instead of spinning
    while they wait (on a shared, busy machine spinning made one forward pass 30x slower).
    OpenMP reads it when torch loads its runtime, so call it before any torch import."""
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
