"""Tiny models and inputs for the CLI / API tests (no pipeline outputs needed).

- :func:`save_fusion_model`: a small DeepLabV3+ saved as a model folder (``model.ckpt`` +
  ``model_meta.json``) trained-grid ``rows x cols`` / ``cell``;
- :func:`save_risk` : a DAVE-2 risk model folder with the given metadata (``domain``...);
- :func:`masses` / :func:`save_map`: random grids on the simplex as ``.npz``;
- :func:`textured_pair`: a rectified stereo pair, the right image shifted by 6 px;
- :func:`fuse_args`: the argument list of one ``traffictwin fuse`` call (poses :data:`POSE1`,
  :data:`POSE2`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from traffictwin.fusion.deeplab import DeepLabSpec, DeepLabV3Plus
from traffictwin.fusion.model_io import CKPT_FORMAT
from traffictwin.fusion.resnet import ResNetSpec
from traffictwin.model_format import save_model_files
from traffictwin.risk.dave2 import Dave2, Dave2Config
from traffictwin.risk.model_io import save_risk_model

H, W, CELL = 32, 48, 0.5
POSE1, POSE2 = "1.0,2.0,0.1", "4.0,1.0,-0.05"  # world x,y,yaw (m, m, rad) of the two maps


def fuse_args(
    map1: Path | str, map2: Path | str, model: Path | str, out: Path | str, *extra: str
) -> list[str]:
    """``traffictwin fuse MAP1 MAP2 --pose1 POSE1 --pose2 POSE2 --model MODEL -o OUT EXTRA...``."""
    return [
        "fuse",
        str(map1),
        str(map2),
        "--pose1",
        POSE1,
        "--pose2",
        POSE2,
        "--model",
        str(model),
        "-o",
        str(out),
        *extra,
    ]


def tiny_spec() -> DeepLabSpec:
    return DeepLabSpec(
        backbone=ResNetSpec(layers=(1, 1, 1, 1), base_width=8),
        aspp_channels=8,
        aspp_rates=(1, 2, 3),
        low_level_channels=4,
        decoder_channels=8,
    )


def save_fusion_model(
    folder: Path, rows: int = H, cols: int = W, cell: float = CELL, seed: int = 0
) -> Path:
    """A tiny fusion network in the checkpoint format of traffictwin.fusion.model_io."""
    torch.manual_seed(seed)
    spec = tiny_spec()
    net = DeepLabV3Plus(spec).eval()
    info = {
        "format": CKPT_FORMAT,
        "problem": "fusion",
        "cfg": "D",
        "architecture": spec.as_dict(),
        "grid": {"rows": rows, "cols": cols, "cell": cell},
        "data_manifest_hash": "test",
    }
    folder.mkdir(parents=True, exist_ok=True)
    save_model_files(  # the sealed pair, as the training stage writes it
        folder / "model.ckpt",
        {"state_dict": {f"net.{k}": v for k, v in net.state_dict().items()}, "traffictwin": info},
        folder / "model_meta.json",
        info,
    )
    return folder


def save_risk(folder: Path, meta: dict[str, Any] | None = None, seed: int = 1, **cfg: Any) -> Path:
    """A DAVE-2 risk model folder (``Dave2Config(**cfg)``) with metadata ``meta``."""
    torch.manual_seed(seed)
    return save_risk_model(Dave2(Dave2Config(**cfg)).eval(), folder, meta or {"label": "risk"})


def masses(seed: int, h: int = H, w: int = W) -> tuple[np.ndarray, np.ndarray]:
    a = np.random.default_rng(seed).dirichlet([1.0, 1.0, 1.0], size=(h, w)).astype(np.float32)
    return a[..., 0], a[..., 1]


def save_map(path: Path, mf: np.ndarray, mo: np.ndarray, **extra: Any) -> Path:
    np.savez(path, m_free=mf, m_occ=mo, **extra)
    return path


def textured_pair(
    seed: int = 3, w: int = 320, h: int = 160, shift: int = 6
) -> tuple[np.ndarray, np.ndarray]:
    """A textured rectified pair of ``w x h`` px: the right image is the left shifted by ``shift`` px."""
    rng = np.random.default_rng(seed)
    big = w + 16 + shift
    tex = cv2.resize(
        rng.integers(0, 256, size=(h // 4, big // 4, 3), dtype=np.uint8),
        (big, h),
        interpolation=cv2.INTER_NEAREST,
    )
    tex = cv2.GaussianBlur(tex, (3, 3), 0)
    return np.ascontiguousarray(tex[:, 10 : 10 + w]), np.ascontiguousarray(
        tex[:, 10 + shift : 10 + shift + w]
    )


def write_pair(folder: Path, pid: str, left: np.ndarray, right: np.ndarray) -> tuple[Path, Path]:
    folder.mkdir(parents=True, exist_ok=True)
    lp, rp = folder / f"{pid}_left.png", folder / f"{pid}_right.png"
    cv2.imwrite(str(lp), left)
    cv2.imwrite(str(rp), right)
    return lp, rp
