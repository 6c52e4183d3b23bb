"""What the fusion network trains on: the prealigned pairs in memory and their augmentation.

- :class:`TrainingSet` — the pairs' folder and what they stand for (pose-noise configuration,
  grid, seed), shared by the fusion network's and the learned registration's trainings.
- :func:`augment` — random horizontal/vertical flips and a random rotation in
  ``[-max_rotation_deg, max_rotation_deg]`` applied with one ``grid_sample`` to inputs and
  label together (paper III-D). Bilinear sampling with zero padding mixes masses convexly with
  "unknown" (0, 0), so every cell stays on the simplex (``m_F, m_O >= 0``, ``m_F + m_O <= 1``).
- :class:`FusionDataModule` — the ``prealigned`` dataset's ``train``/``val`` splits held in memory;
  a seeded random subset of ``train_samples_per_epoch`` pairs per epoch (a fresh draw each epoch),
  a fixed evenly spaced subset of ``val_samples`` validation pairs. Under DDP the ranks split
  each epoch's draw (``train_samples_per_epoch`` pairs in all, not per rank) and the validation
  pairs (each on exactly one rank): :class:`~traffictwin.trainer.RankShardSampler`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
import torch.nn.functional as F
from torch.utils.data import (
    DataLoader,
    RandomSampler,
    Sampler,
    SequentialSampler,
    Subset,
    TensorDataset,
)

from traffictwin import trainer as common
from traffictwin.evidential.masses import check_masses
from traffictwin.fusion.pairs import evenly_spaced
from traffictwin.grid import GridSpec
from traffictwin.io.shards import Dataset, DatasetError


@dataclass(frozen=True)
class TrainingSet:
    """The prealigned pairs a run trains on and what they stand for: ``root`` (the dataset
    folder), the pose-noise configuration ``cfg_name`` and its ``noise`` description (r m,
    alpha deg), the ``grid``, the run's ``seed`` and the network's ``inputs`` (the data kind the
    pairs come from, e.g. ``prealigned``)."""

    root: str | Path
    cfg_name: str
    noise: Mapping[str, Any]
    grid: GridSpec
    seed: int
    inputs: str = "prealigned"

    def manifest_hash(self) -> str:
        """The dataset's manifest hash (shards are checked as the loaders read them)."""
        return Dataset(self.root, kind="prealigned", verify=False).manifest_hash()

    def grid_dict(self) -> dict[str, Any]:
        """The grid as the model meta records it (rows, cols, cell in m)."""
        return {"rows": self.grid.rows, "cols": self.grid.cols, "cell": self.grid.cell}


# ---------------------------------------------------------------------------------------------
# augmentation


def augmentation_matrices(
    n: int,
    height: int,
    width: int,
    *,
    flip: bool,
    max_rotation_deg: float,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """``(n, 2, 3)`` ``affine_grid`` matrices: random flips (p = 0.5 per axis) and rotation about the centre.

    The rotation is in metric (cell) space — cells are square — so the normalised-coordinate
    matrix is ``D^-1 R Fl D`` with ``D = diag(W/2, H/2)``.
    """
    g = generator
    ang = (torch.rand(n, generator=g, dtype=torch.float64) * 2.0 - 1.0) * math.radians(
        max_rotation_deg
    )
    if flip:
        fx = torch.where(torch.rand(n, generator=g) < 0.5, -1.0, 1.0).double()
        fy = torch.where(torch.rand(n, generator=g) < 0.5, -1.0, 1.0).double()
    else:
        fx = torch.ones(n, dtype=torch.float64)
        fy = torch.ones(n, dtype=torch.float64)
    c, s = torch.cos(ang), torch.sin(ang)
    sx, sy = width / 2.0, height / 2.0
    a = torch.zeros(n, 2, 3, dtype=torch.float64)
    # [x_in; y_in]_pix = R @ diag(fx, fy) @ [x_out; y_out]_pix, then normalised
    a[:, 0, 0] = c * fx
    a[:, 0, 1] = -s * fy * sy / sx
    a[:, 1, 0] = s * fx * sx / sy
    a[:, 1, 1] = c * fy
    return a.float()


def augment(
    inputs: torch.Tensor,
    label: torch.Tensor,
    *,
    flip: bool = True,
    max_rotation_deg: float = 20.0,
    mode: str = "bilinear",
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Apply the same random flip + rotation to ``inputs (N, C, H, W)`` and ``label (N, 2, H, W)``.

    Outside the rotated map the masses are (0, 0) (unknown). ``generator`` (CPU) makes the draw
    reproducible.
    """
    if inputs.shape[0] != label.shape[0] or inputs.shape[-2:] != label.shape[-2:]:
        raise ValueError(
            f"inputs {tuple(inputs.shape)} and label {tuple(label.shape)} must share N, H, W"
        )
    n, c, h, w = inputs.shape
    if not flip and max_rotation_deg <= 0:
        return inputs, label
    theta = augmentation_matrices(
        n, h, w, flip=flip, max_rotation_deg=max_rotation_deg, generator=generator
    )
    theta = theta.to(device=inputs.device, dtype=inputs.dtype)
    both = torch.cat([inputs, label.to(inputs.dtype)], dim=1)
    grid = F.affine_grid(theta, list(both.shape), align_corners=False)
    out = F.grid_sample(both, grid, mode=mode, padding_mode="zeros", align_corners=False)
    return out[:, :c], out[:, c:].to(label.dtype)


# ---------------------------------------------------------------------------------------------
# data


@dataclass(frozen=True)
class DataSettings:
    """How the prealigned dataset feeds training.

    batch_size: pairs per step; train_samples_per_epoch: pairs drawn (without replacement) per
    epoch, 0 = all; val_samples: fixed validation pairs, 0 = all; num_workers: loader workers.
    """

    batch_size: int = 8
    train_samples_per_epoch: int = 0
    val_samples: int = 0
    num_workers: int = 0


def load_prealigned(
    root: str | Path, split: str, grid: GridSpec | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """``inputs (N, 4, H, W)``, ``label (N, 2, H, W)`` float32 tensors of ``split`` (checked against
    ``grid``). Every shard read is checked against the manifest's SHA-256 and its masses (finite,
    on the simplex) as it is loaded (:meth:`~traffictwin.io.shards.Dataset.load_all`)."""

    def masses_ok(name: str, a: dict[str, np.ndarray]) -> None:
        # NaN, negative or off-simplex masses fail here, before any training
        for key, arr in (("inputs", a["inputs"][:, 0:2]), ("inputs", a["inputs"][:, 2:4])):
            _check_masses(arr, f"{root}/{name}: split '{split}' array '{key}'")
        _check_masses(a["label"], f"{root}/{name}: split '{split}' array 'label'")

    ds = Dataset(root, kind="prealigned", verify=False)  # each shard's hash: checked as it is read
    arrays = ds.load_all(split, keys=["inputs", "label"], check=masses_ok)
    x, y = arrays["inputs"], arrays["label"]
    if x.ndim != 4 or x.shape[1] != 4:
        raise DatasetError(f"{root}: array 'inputs' must be (N, 4, H, W), got {x.shape}")
    if y.shape != (x.shape[0], 2, *x.shape[2:]):
        raise DatasetError(
            f"{root}: array 'label' must be (N, 2, H, W) = {(x.shape[0], 2, *x.shape[2:])}, got {y.shape}"
        )
    if grid is not None and tuple(x.shape[2:]) != grid.shape:
        raise DatasetError(
            f"{root}: maps are {tuple(x.shape[2:])} cells but the grid parameter says {grid.shape} (rows, cols)"
        )
    return torch.from_numpy(np.ascontiguousarray(x, dtype=np.float32)), torch.from_numpy(
        np.ascontiguousarray(y, dtype=np.float32)
    )


def _check_masses(arr: np.ndarray, name: str) -> None:
    """:func:`~traffictwin.evidential.masses.check_masses` as a :class:`DatasetError`."""
    try:
        check_masses(arr, name=name)
    except ValueError as exc:
        raise DatasetError(str(exc)) from None


class FusionDataModule(L.LightningDataModule):
    """Prealigned pairs in memory; seeded per-epoch training subsets, a fixed validation subset."""

    def __init__(
        self,
        root: str | Path,
        settings: DataSettings,
        seed: int,
        grid: GridSpec | None = None,
        tensors: Mapping[str, tuple[torch.Tensor, torch.Tensor]] | None = None,
    ) -> None:
        super().__init__()
        self.root = Path(root)
        self.settings = settings
        self.seed = int(seed)
        self.grid = grid
        self._tensors = dict(tensors) if tensors else {}
        self.train_set: TensorDataset | None = None
        self.val_set: Subset | TensorDataset | None = None

    def setup(self, stage: str | None = None) -> None:
        if self.train_set is not None:
            return
        for split in ("train", "val"):
            if split not in self._tensors:
                self._tensors[split] = load_prealigned(self.root, split, self.grid)
        self.train_set = TensorDataset(*self._tensors["train"])
        val = TensorDataset(*self._tensors["val"])
        self.val_set = Subset(val, evenly_spaced(len(val), self.settings.val_samples).tolist())
        if len(self.train_set) < self.settings.batch_size:
            raise DatasetError(
                f"{self.root}: {len(self.train_set)} training pairs < batch_size {self.settings.batch_size}"
            )

    def train_dataloader(self) -> DataLoader:
        assert self.train_set is not None
        n = len(self.train_set)
        k = self.settings.train_samples_per_epoch
        k = n if k <= 0 else min(k, n)
        gen = torch.Generator().manual_seed(self.seed)
        sampler: Sampler[int] = RandomSampler(
            self.train_set, replacement=False, num_samples=k, generator=gen
        )
        world, rank = common.rank_layout(self.trainer)
        if world > 1:  # DDP: the same k-pair draw on every rank, k // world pairs each
            sampler = common.RankShardSampler(sampler, world, rank, even=True)
        return DataLoader(
            self.train_set,
            batch_size=self.settings.batch_size,
            sampler=sampler,
            drop_last=True,
            num_workers=self.settings.num_workers,
            persistent_workers=self.settings.num_workers > 0,
        )

    def val_dataloader(self) -> DataLoader:
        assert self.val_set is not None
        world, rank = common.rank_layout(self.trainer)
        # DDP: every validation pair on exactly one rank (no padding repeats), in the batches one
        # process would use, so the metrics reduced over the ranks are those of one process
        sampler = (
            common.RankShardSampler(
                SequentialSampler(self.val_set),
                world,
                rank,
                even=False,
                block=self.settings.batch_size,
            )
            if world > 1
            else None
        )
        return DataLoader(
            self.val_set,
            batch_size=self.settings.batch_size,
            shuffle=False,
            sampler=sampler,
            num_workers=self.settings.num_workers,
            persistent_workers=self.settings.num_workers > 0,
        )
