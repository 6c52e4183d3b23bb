"""The risk network's Lightning loaders (:class:`RiskDataModule`) over the compact arrays of
:mod:`traffictwin.risk.source`; only training imports it (it imports Lightning)."""

from __future__ import annotations

import lightning as L
import torch
from torch.utils.data import DataLoader, SequentialSampler

from traffictwin.risk.source import RiskArrays
from traffictwin.trainer.sampling import RankShardSampler, rank_layout


class RiskDataModule(L.LightningDataModule):
    """Train/val/test loaders over in-memory :class:`RiskArrays` (shuffled train, seeded)."""

    def __init__(
        self,
        train: RiskArrays,
        val: RiskArrays,
        test: RiskArrays | None = None,
        batch_size: int = 10,
        eval_batch_size: int = 256,
        num_workers: int = 0,
        seed: int = 0,
    ) -> None:
        super().__init__()
        if len(train) == 0:
            raise ValueError(
                "RiskDataModule: the training split has no frames (after the ORB check)"
            )
        if len(val) == 0:
            raise ValueError(
                "RiskDataModule: the validation split has no frames (after the ORB check)"
            )
        self.train, self.val, self.test = train, val, test
        self.batch_size, self.eval_batch_size = int(batch_size), int(eval_batch_size)
        self.num_workers, self.seed = int(num_workers), int(seed)

    def _loader(self, arrays: RiskArrays, shuffle: bool, bs: int) -> DataLoader:
        g = torch.Generator()
        g.manual_seed(self.seed)
        ds = arrays.tensors()
        world, rank = rank_layout(self.trainer)
        # DDP evaluation: every frame on exactly one rank, in one process's batches (Lightning's
        # DistributedSampler would repeat frames to even out the ranks and bias the summed
        # metrics); training keeps Lightning's shuffled DistributedSampler
        sampler = (
            RankShardSampler(SequentialSampler(ds), world, rank, even=False, block=bs)
            if world > 1 and not shuffle
            else None
        )
        return DataLoader(
            ds,
            batch_size=bs,
            shuffle=shuffle,
            sampler=sampler,
            generator=g if shuffle else None,
            num_workers=self.num_workers,
            persistent_workers=self.num_workers > 0,
            drop_last=False,
        )

    def train_dataloader(self) -> DataLoader:
        return self._loader(self.train, True, self.batch_size)

    def val_dataloader(self) -> DataLoader:
        return self._loader(self.val, False, self.eval_batch_size)

    def test_dataloader(self) -> DataLoader:
        if self.test is None:
            raise ValueError("RiskDataModule: no test split given")
        return self._loader(self.test, False, self.eval_batch_size)
