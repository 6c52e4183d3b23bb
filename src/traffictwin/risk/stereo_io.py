"""The trained stereo network outside training: the sealed, weights-only loader
(:func:`load_stereo_model`), batch inference (:func:`predict`) and the MLflow pyfunc module
(:class:`PackedStereo`, :func:`pack_pairs`). Torch only, no Lightning: the stages and the CLI that
run the network import this; :mod:`traffictwin.risk.stereo_training` writes what it reads (and
re-exports these names)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from traffictwin.model_format import (
    check_model_pair,
    net_state_dict,
    read_model_checkpoint,
    read_model_meta,
)
from traffictwin.stereo.network import StereoNet, StereoNetSpec, to_input

PROBLEM = "stereo"

#: meta keys the loader trusts (the checkpoint's own copy must match model_meta.json)
SEALED_META = ("architecture", "data_manifest_hash", "spread_threshold_px", "image_size")


class StereoModelError(RuntimeError):
    """A stereo model folder that cannot be used (missing, edited, wrong architecture)."""


@torch.no_grad()
def predict(
    net: StereoNet,
    left: np.ndarray,
    right: np.ndarray,
    batch_size: int = 8,
    sgm: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Disparity and spread (N, H, W) float32 px of BGR uint8 pairs (N, H, W, 3), in batches;
    image sides are padded (edge) to a multiple of the network's stride and cropped back. In
    ``base: sgm`` mode ``sgm`` (N, H, W) px (-1 invalid) is the input refined (padded with -1)."""
    if left.shape != right.shape or left.ndim != 4:
        raise ValueError(f"left {left.shape} and right {right.shape} must be equal (N, H, W, 3)")
    net.eval()
    n, h, w, _ = left.shape
    if net.spec.base == "sgm" and (sgm is None or sgm.shape != (n, h, w)):
        raise ValueError(
            f"predict: base 'sgm' needs the SGM disparity (N, H, W) = {(n, h, w)}, got "
            f"{None if sgm is None else sgm.shape}"
        )
    s = net.spec.stride if net.spec.base == "cost_volume" else net.spec.refine_stride
    ph, pw = (-h) % s, (-w) % s
    disp = np.empty((n, h, w), np.float32)
    spread = np.empty((n, h, w), np.float32)
    for a in range(0, n, batch_size):
        lt, rt = to_input(left[a : a + batch_size]), to_input(right[a : a + batch_size])
        if ph or pw:
            lt = torch.nn.functional.pad(lt, (0, pw, 0, ph), mode="replicate")
            rt = torch.nn.functional.pad(rt, (0, pw, 0, ph), mode="replicate")
        st = None
        if net.spec.base == "sgm":
            st = torch.from_numpy(np.ascontiguousarray(sgm[a : a + batch_size], np.float32))[
                :, None
            ]
            if ph or pw:
                st = torch.nn.functional.pad(st, (0, pw, 0, ph), value=-1.0)
        out = net(lt, rt, st)
        disp[a : a + batch_size] = out["disparity"][:, 0, :h, :w].numpy()
        spread[a : a + batch_size] = out["spread"][:, 0, :h, :w].numpy()
    return disp, spread


class PackedStereo(torch.nn.Module):
    """The network as one-input module for the MLflow pyfunc flavour: input (N, 6[+1], H, W)
    float32 = the left then the right image's B, G, R planes (0-255) and, for a ``base: sgm``
    network, SGM's disparity plane (px, -1 invalid); output (N, 2, H, W) = the disparity (px,
    -1 where the spread exceeds ``threshold`` px, as :func:`predict` + the ``stereo_learned``
    stage) and the spread (px)."""

    def __init__(self, net: StereoNet, threshold: float) -> None:
        super().__init__()
        self.net = net
        self.threshold = float(threshold)
        self.channels = 7 if net.spec.base == "sgm" else 6

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.ndim != 4 or x.shape[1] != self.channels:
            raise ValueError(
                f"packed stereo input must be (N, {self.channels}, H, W) = left BGR, right BGR"
                f"{', SGM disparity' if self.channels == 7 else ''}, got {tuple(x.shape)}"
            )
        left = x[:, 0:3].flip(1) / 255.0  # BGR -> RGB in [0, 1], as to_input
        right = x[:, 3:6].flip(1) / 255.0
        sgm = x[:, 6:7] if self.channels == 7 else None
        out = self.net(left, right, sgm)
        disp, spread = out["disparity"], out["spread"]
        disp = torch.where(spread <= self.threshold, disp, torch.full_like(disp, -1.0))
        return torch.cat([disp, spread], dim=1)


def pack_pairs(left: np.ndarray, right: np.ndarray, sgm: np.ndarray | None = None) -> np.ndarray:
    """The :class:`PackedStereo` input (N, 6[+1], H, W) float32 of BGR uint8 pairs (N, H, W, 3)
    and, for a ``base: sgm`` network, their SGM disparity (N, H, W) px."""
    planes = [np.moveaxis(np.asarray(a, np.float32), -1, 1) for a in (left, right)]
    if sgm is not None:
        planes.append(np.asarray(sgm, np.float32)[:, None])
    return np.ascontiguousarray(np.concatenate(planes, axis=1))


def load_stereo_model(path: str | Path) -> StereoNet:
    """The trained :class:`StereoNet` (eval mode) from ``model.ckpt`` (file or folder) through the
    sealed, weights-only path; ``net.meta`` holds its meta (``spread_threshold_px``). Errors name
    the file."""
    path = Path(path)
    if path.is_dir():
        path = path / "model.ckpt"
    if not path.exists():
        raise StereoModelError(
            f"{path}: stereo model checkpoint not found (run `dvc repro train_stereo` first)"
        )
    ck = read_model_checkpoint(path, PROBLEM, StereoModelError)
    info = ck["traffictwin"]
    meta = read_model_meta(path.parent / "model_meta.json", StereoModelError)
    check_model_pair(path, meta, StereoModelError, info, SEALED_META)
    try:
        net = StereoNet(StereoNetSpec.from_dict(info["architecture"]))
        net.load_state_dict(net_state_dict(ck), strict=True)
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        raise StereoModelError(
            f"{path}: weights do not fit the stereo architecture ({str(exc)[:300]})"
        ) from None
    net.meta = dict(info)  # type: ignore[attr-defined]
    return net.eval()
