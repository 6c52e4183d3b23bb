"""The risk network's data: the risk frames that passed the ORB check, read and cross-checked
(:class:`RiskSource`), one split at the model resolution in compact arrays (:func:`prepare_split`,
:class:`RiskArrays`); the Lightning loaders over them are :mod:`traffictwin.risk.data_module`
(this module imports no Lightning: the evaluation stages read their data here).

Data: ``data/risk`` (kind "risk": ``left``/``right`` BGR images, ``disp_gt``, ``frames.csv``),
``data/disparity`` (kind "disparity": ``disp_sgm`` shards aligned 1:1 with data/risk), optionally
``data/stereo_learned`` (kind "stereo_learned": the learned stereo network's ``disp_learned``,
aligned the same way) and the ORB
pair check ``data/orb/orb.csv``. Only frames whose stereo pair passed the ORB check
(``outlier == False``) are used, in the train/val/test splits of ``frames.csv`` (by scenario).
Arrays: uint8 RGB, float16 disparity (~92 kB a frame at 66×200), normalised per batch on the
device by the LightningModule.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch
from torch.utils.data import TensorDataset

from traffictwin.io.shards import Dataset, DatasetError
from traffictwin.risk.dave2 import Dave2Config, prepare_channels
from traffictwin.risk.stereo_shards import SPLITS

_FRAME_COLS = ("frame_id", "shard", "idx", "split", "speed")
#: the disparity arrays read from a dataset beside data/risk: array name → dataset kind
SIDE_DISPARITIES = {"disp_sgm": "disparity", "disp_learned": "stereo_learned"}


# --------------------------------------------------------------------------------------------
# data
# --------------------------------------------------------------------------------------------


class RiskSource:
    """The risk frames that passed the ORB check, with their images and disparities.

    ``risk_root``: data/risk; ``disparity_root``: data/disparity (``None`` if no model input or
    baseline needs SGM disparity); ``orb_csv``: data/orb/orb.csv (``None`` = keep every frame);
    ``learned_root``: data/stereo_learned (the learned stereo network's disparity; ``None``: not
    read). Raises :class:`DatasetError` naming the file and the problem when they disagree.
    """

    def __init__(
        self,
        risk_root: str | Path,
        disparity_root: str | Path | None = None,
        orb_csv: str | Path | None = None,
        learned_root: str | Path | None = None,
    ) -> None:
        self.risk = Dataset(risk_root, kind="risk")
        self.disparity = (
            Dataset(disparity_root, kind="disparity") if disparity_root is not None else None
        )
        self.learned = (
            Dataset(learned_root, kind=SIDE_DISPARITIES["disp_learned"])
            if learned_root is not None
            else None
        )
        #: array name → the dataset beside data/risk it is read from
        self._side = {
            k: d
            for k, d in (("disp_sgm", self.disparity), ("disp_learned", self.learned))
            if d is not None
        }
        frames = self.risk.table("frames.csv")
        fpath = self.risk.root / "frames.csv"
        missing = [c for c in _FRAME_COLS if c not in frames.columns]
        if missing:
            raise DatasetError(f"{fpath}: column(s) {missing} missing (has {list(frames.columns)})")
        self._names = [s["name"] for s in self.risk.shards]
        counts = [int(s["count"]) for s in self.risk.shards]
        # frames.csv 'shard' is the writer's shard index; map it to the manifest position by name
        from traffictwin.io.shards import shard_name

        pos = {name: i for i, name in enumerate(self._names)}
        frames = frames.copy()
        frames["_pos"] = frames["shard"].map(lambda s: pos.get(shard_name(int(s)), -1))
        bad = frames[frames["_pos"] < 0]
        if len(bad):
            raise DatasetError(
                f"{fpath}: frame {bad['frame_id'].iloc[0]} refers to shard {bad['shard'].iloc[0]}, not in the manifest"
            )
        over = frames["idx"].to_numpy() >= np.asarray(counts)[frames["_pos"].to_numpy()]
        if over.any():
            r = frames[over].iloc[0]
            raise DatasetError(
                f"{fpath}: frame {r['frame_id']} has idx {r['idx']} beyond its shard's {counts[int(r['_pos'])]} frames"
            )
        bad_split = sorted(set(frames["split"]) - set(SPLITS))
        if bad_split:
            raise DatasetError(
                f"{fpath}: unknown split value(s) {bad_split} (expected {list(SPLITS)})"
            )
        for side in self._side.values():
            dnames = [s["name"] for s in side.shards]
            dcounts = [int(s["count"]) for s in side.shards]
            if dnames != self._names or dcounts != counts:
                raise DatasetError(
                    f"{side.root / 'manifest.json'}: shards/counts {list(zip(dnames, dcounts))[:3]}… do not match "
                    f"{self.risk.root / 'manifest.json'} {list(zip(self._names, counts))[:3]}… (must be aligned 1:1)"
                )
        if orb_csv is not None:
            orb_path = Path(orb_csv)
            if not orb_path.exists():
                raise DatasetError(
                    f"{orb_path}: ORB check table not found (run the stage that writes it first)"
                )
            orb = read_orb_table(orb_path)
            outlier = orb.set_index("frame_id")["outlier"].map(_as_bool)
            flag = frames["frame_id"].map(outlier)
            if flag.isna().any():
                fid = frames.loc[flag.isna(), "frame_id"].iloc[0]
                raise DatasetError(
                    f"{orb_path}: no ORB result for frame {fid} of {fpath} ({int(flag.isna().sum())} frames lack one)"
                )
            self.n_orb_outliers = int(flag.astype(bool).sum())
            frames = frames[~flag.astype(bool).to_numpy()]
        else:
            self.n_orb_outliers = 0
        self.n_total = int(len(self.risk.table("frames.csv")))
        self.frames = frames.sort_values(["_pos", "idx"]).reset_index(drop=True)

    @property
    def disparity_keys(self) -> set[str]:
        """The disparity arrays this source can read: ``disp_gt`` and each given side dataset's."""
        return {"disp_gt", *self._side}

    @property
    def camera(self) -> dict[str, float]:
        """The camera intrinsics of data/risk's manifest (``camera`` key)."""
        cam = self.risk.manifest.get("camera")
        if not isinstance(cam, dict):
            raise DatasetError(
                f"{self.risk.root / 'manifest.json'}: key 'camera' (intrinsics) missing"
            )
        return cam

    def split_frames(self, split: str) -> pd.DataFrame:
        if split not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
        return self.frames[self.frames["split"] == split].reset_index(drop=True)

    def iter_arrays(
        self, frames: pd.DataFrame, keys: Sequence[str]
    ) -> Iterator[tuple[pd.DataFrame, dict[str, np.ndarray]]]:
        """Per shard: the rows of ``frames`` in it and their arrays ``keys`` (left, right, disp_gt,
        disp_sgm, disp_learned).

        Checks that every array of a frame has the image's height and width.
        """
        keys = list(keys)
        for p, rows in frames.groupby("_pos", sort=True):
            idx = rows["idx"].to_numpy()
            arrays: dict[str, np.ndarray] = {}
            need_risk = [k for k in keys if k not in SIDE_DISPARITIES]
            if need_risk:
                shard = self.risk.load_shard(int(p))
                for k in need_risk:
                    if k not in shard:
                        raise DatasetError(
                            f"{self.risk.root / self._names[int(p)]}: array '{k}' missing (has {sorted(shard)})"
                        )
                    arrays[k] = shard[k][idx]
            for k in (k for k in keys if k in SIDE_DISPARITIES):
                side = self._side.get(k)
                if side is None:
                    raise ValueError(
                        f"RiskSource: {k!r} requested but no {SIDE_DISPARITIES[k]} dataset was given"
                    )
                dshard = side.load_shard(int(p))
                if k not in dshard:
                    raise DatasetError(f"{side.root / self._names[int(p)]}: array {k!r} missing")
                arrays[k] = dshard[k][idx]
            shapes = {k: tuple(v.shape[1:3]) for k, v in arrays.items()}
            if len(set(shapes.values())) > 1:
                files = " / ".join(
                    str(d.root / self._names[int(p)]) for d in (self.risk, *self._side.values())
                )
                raise DatasetError(
                    f"{files}: image and disparity sizes disagree {shapes} (H, W); "
                    "disparity maps must have the left image's size"
                )
            yield rows, arrays


def read_orb_table(path: str | Path) -> pd.DataFrame:
    """The ORB check table (``frame_id``, ``outlier``, ...), checked: readable CSV, both columns
    present, ``frame_id`` integral and unique, ``outlier`` boolean. The only data file without a
    manifest hash, so every way it can be corrupt ends in a DatasetError naming file and column."""
    path = Path(path)
    try:
        orb = pd.read_csv(path)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError, ValueError) as exc:
        msg = " ".join(str(exc).split())
        raise DatasetError(
            f"{path}: not a readable CSV table ({type(exc).__name__}: {msg})"
        ) from None
    for c in ("frame_id", "outlier"):
        if c not in orb.columns:
            raise DatasetError(f"{path}: column '{c}' missing (has {list(orb.columns)})")
    fid = pd.to_numeric(orb["frame_id"], errors="coerce")
    if fid.isna().any() or not np.all(fid == np.round(fid)):
        row = int(np.flatnonzero(fid.isna() | (fid != np.round(fid)))[0])
        raise DatasetError(
            f"{path}: column 'frame_id' must hold integers, row {row + 2} has "
            f"{orb['frame_id'].iloc[row]!r}"
        )
    if fid.duplicated().any():
        dup = int(fid[fid.duplicated()].iloc[0])
        raise DatasetError(f"{path}: column 'frame_id' repeats frame {dup}")
    orb = orb.assign(frame_id=fid.astype(np.int64))
    bad = [v for v in orb["outlier"] if not _is_bool_like(v)]
    if bad:
        raise DatasetError(
            f"{path}: column 'outlier' must hold booleans (True/False, 1/0), got {bad[0]!r}"
        )
    return orb


def _is_bool_like(v: Any) -> bool:
    if isinstance(v, (bool, np.bool_)):
        return True
    if isinstance(v, str):
        return v.strip().lower() in ("true", "false", "1", "0", "yes", "no")
    return isinstance(v, (int, np.integer, float, np.floating)) and v in (0, 1)


def _as_bool(v: Any) -> bool:
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, str):
        s = v.strip().lower()
        if s in ("true", "1", "yes"):
            return True
        if s in ("false", "0", "no"):
            return False
        raise DatasetError(f"orb.csv: 'outlier' value {v!r} is not a boolean")
    return bool(v)


def input_keys(cfg: Dave2Config) -> list[str]:
    """Dataset arrays a model config needs: left (for rgb), disp_sgm, disp_gt."""
    return ["left" if c == "rgb" else c for c in cfg.inputs]


@dataclass
class RiskArrays:
    """One split at the model resolution (see :func:`prepare_channels`)."""

    frame_id: np.ndarray  # (N,)
    rgb: np.ndarray  # (N, 3 or 0, h, w) uint8
    disp: np.ndarray  # (N, k, h, w) float16 (k = disparity inputs, may be 0)
    speed: np.ndarray  # (N,) float32 m/s
    y: np.ndarray  # (N,) float32 normalised risk label

    def __len__(self) -> int:
        return len(self.frame_id)

    def tensors(self) -> TensorDataset:
        return TensorDataset(
            *(
                torch.from_numpy(np.ascontiguousarray(a))
                for a in (self.rgb, self.disp, self.speed, self.y)
            )
        )


def check_label(frames: pd.DataFrame, label: str, source: str = "frames.csv") -> np.ndarray:
    """The label column as float32; errors if missing, non-finite or outside [0, 1]."""
    if label not in frames.columns:
        raise DatasetError(f"{source}: label column '{label}' missing (has {list(frames.columns)})")
    y = frames[label].to_numpy(dtype=np.float64)
    if not np.all(np.isfinite(y)) or (len(y) and (y.min() < 0 or y.max() > 1)):
        raise DatasetError(
            f"{source}: label '{label}' must be finite and in [0, 1] (normalised risk)"
        )
    return y.astype(np.float32)


def prepare_split(
    source: RiskSource,
    cfg: Dave2Config,
    split: str,
    label: str,
    max_frames: int | None = None,
    seed: int = 0,
) -> RiskArrays:
    """Load ``split`` (ORB-passed frames) at the model resolution; ``max_frames`` subsamples (seeded)."""
    frames = source.split_frames(split)
    if max_frames is not None and len(frames) > max_frames:
        keep = np.sort(
            np.random.default_rng(seed).choice(len(frames), size=max_frames, replace=False)
        )
        frames = frames.iloc[keep].reset_index(drop=True)
    h, w = cfg.height, cfg.width
    n_disp = sum(1 for c in cfg.inputs if c != "rgb")
    rgb_parts, disp_parts, order = [], [], []
    for rows, arrays in source.iter_arrays(frames, input_keys(cfg)):
        rgb, disp = prepare_channels(
            cfg, arrays.get("left"), arrays.get("disp_sgm"), arrays.get("disp_gt")
        )
        n = len(rows)
        rgb_parts.append(rgb if rgb is not None else np.zeros((n, 0, h, w), np.uint8))
        disp_parts.append(disp if disp is not None else np.zeros((n, 0, h, w), np.float16))
        order.append(rows.index.to_numpy())
    if not order:
        return RiskArrays(
            np.zeros(0, np.int64),
            np.zeros((0, 3 if "rgb" in cfg.inputs else 0, h, w), np.uint8),
            np.zeros((0, n_disp, h, w), np.float16),
            np.zeros(0, np.float32),
            np.zeros(0, np.float32),
        )
    ix = np.concatenate(order)
    frames = frames.loc[ix].reset_index(drop=True)
    return RiskArrays(
        frame_id=frames["frame_id"].to_numpy(),
        rgb=np.concatenate(rgb_parts),
        disp=np.concatenate(disp_parts),
        speed=frames["speed"].to_numpy(dtype=np.float32),
        y=check_label(frames, label, str(source.risk.root / "frames.csv")),
    )
