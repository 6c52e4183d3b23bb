"""Reading the risk dataset (``data/risk``, written by :mod:`traffictwin.risk.dataset`): its
splits and one checked stereo shard. Kept apart from the generator so that the stages that only
read the data do not import the simulator."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from traffictwin.io.shards import Dataset

#: the splits, assigned per sequence (:func:`traffictwin.risk.dataset.assign_splits`)
SPLITS = ("train", "val", "test")


def load_stereo_shard(
    ds: Dataset, index: int, keys: tuple[str, ...] = ("left", "right")
) -> dict[str, np.ndarray]:
    """Shard ``index`` of a ``data/risk`` dataset, checked: every array of ``keys`` present and
    left/right images of one size. Raises :class:`DatasetError` naming the shard file."""
    from traffictwin.io.shards import DatasetError

    sh = ds.load_shard(index)
    name = ds.root / ds.shards[index]["name"]
    for key in keys:
        if key not in sh:
            raise DatasetError(f"{name}: array '{key}' missing (has {sorted(sh)})")
    if sh["left"].shape != sh["right"].shape:
        raise DatasetError(
            f"{name}: left {sh['left'].shape} and right {sh['right'].shape} differ in size"
        )
    return sh
