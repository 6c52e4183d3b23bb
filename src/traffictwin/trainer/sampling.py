"""Under DDP, this rank's share of a sampler's indices (:class:`RankShardSampler`)."""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import Any

import numpy as np
from torch.utils.data import DistributedSampler, Sampler


def rank_layout(trainer: Any) -> tuple[int, int]:
    """``(world_size, global_rank)`` of the Lightning trainer a DataModule is attached to;
    ``(1, 0)`` when there is none (a DataModule used on its own)."""
    if trainer is None:
        return 1, 0
    return int(trainer.world_size), int(trainer.global_rank)


class RankShardSampler(DistributedSampler):
    """This rank's share of ``base``'s indices under DDP.

    ``base`` is iterated once per epoch on every rank; it must yield the same indices on every
    rank (a seeded sampler: e.g. a ``RandomSampler`` with a generator of a fixed seed, which
    then draws afresh each epoch, the same draw everywhere).

    ``even=True`` (training): ``list(base)[rank::num_replicas]`` without the last
    ``len(base) % num_replicas`` indices of the epoch's draw, so every rank gets
    ``len(base) // num_replicas`` and all ranks run the same number of optimiser steps; an epoch
    draws ``len(base)`` samples in all (e.g. a ``RandomSampler``'s ``num_samples``), not the
    whole dataset per rank.

    ``even=False`` (evaluation): nothing left out or repeated. The indices are cut into
    consecutive blocks of ``block`` (the loader's batch size) dealt round-robin to the ranks, so
    each rank evaluates exactly the batches one process would (same batch composition, same
    float32 arithmetic) and sums reduced over the ranks differ from one process's only in the
    order of the final additions. With fewer batches than ranks the blocks shrink to
    ``ceil(len(base) / num_replicas)``. Ranks may run different numbers of batches (the
    evaluation steps must not communicate per batch); every rank needs at least one index.

    A :class:`~torch.utils.data.DistributedSampler`, so Lightning does not wrap it again.
    """

    def __init__(
        self,
        base: Sampler[int],
        num_replicas: int,
        rank: int,
        *,
        even: bool,
        block: int = 1,
    ) -> None:
        n = len(base)  # type: ignore[arg-type]
        if not 0 <= rank < num_replicas:
            raise ValueError(f"RankShardSampler: rank {rank} not in [0, {num_replicas})")
        if block < 1:
            raise ValueError(f"RankShardSampler: block must be >= 1, got {block}")
        if not even and n < num_replicas:
            raise ValueError(
                f"RankShardSampler: {n} evaluation sample(s) cannot be shared by {num_replicas} "
                f"ranks (every rank needs at least one): use fewer devices or more samples"
            )
        super().__init__(base, num_replicas=num_replicas, rank=rank, shuffle=False)  # type: ignore[arg-type]
        self.base = base
        self.even = even
        self.n = n
        pos = np.arange(n)
        if even:
            self.positions = pos[: n - n % num_replicas][rank::num_replicas]
        else:
            if math.ceil(n / block) < num_replicas:
                block = math.ceil(n / num_replicas)
            self.positions = pos[(pos // block) % num_replicas == rank]
        self.block = block

    def __len__(self) -> int:
        return len(self.positions)

    def __iter__(self) -> Iterator[int]:
        idx = list(self.base)
        if len(idx) != self.n:
            raise RuntimeError(
                f"RankShardSampler: base sampler gave {len(idx)} indices, not {self.n}"
            )
        return iter([idx[p] for p in self.positions.tolist()])
