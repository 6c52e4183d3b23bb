"""Loading a trained fusion network and predicting fused masses (evaluation, CLI).

``models/fusion/<cfg>/model.ckpt`` is in the one checkpoint format of
:mod:`traffictwin.trainer` (``state_dict`` with ``net.`` prefixes, ``epoch``, ``global_step`` and
a ``traffictwin`` block: format, problem, architecture, cfg, grid, data manifest hash, ...); ``model_meta.json`` beside it says the same in JSON. :func:`load_fusion_model`
checks the two agree (the checkpoint's SHA-256 recorded in the meta, and the keys both hold) and, when given, that they match what the caller expects (configuration,
architecture, grid), and fails with a message naming the file and the mismatch otherwise.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from traffictwin.evidential.masses import evidence_to_masses
from traffictwin.fusion.deeplab import DeepLabSpec, DeepLabV3Plus
from traffictwin.model_format import (
    MODEL_FORMAT,
    check_model_pair,
    net_state_dict,
    read_model_checkpoint,
    read_model_meta,
)

# meta keys the loaders trust, sealed against the checkpoint's own copy (check_model_pair)
SEALED_META = ("cfg", "architecture", "grid", "data_manifest_hash", "noise", "inputs")

CKPT_FORMAT = MODEL_FORMAT  # the one format of traffictwin.trainer, problem "fusion"
META_NAME = "model_meta.json"


class FusionModelError(RuntimeError):
    """A fusion checkpoint is missing, unreadable, or not the one the caller expects."""


def _describe_arch(a: Mapping[str, Any]) -> str:
    bb = a.get("backbone", {})
    return (
        f"{bb.get('block')} ResNet layers={bb.get('layers')} base_width={bb.get('base_width')}, "
        f"aspp={a.get('aspp_channels')}, decoder={a.get('decoder_channels')}, "
        f"residual={a.get('residual', 'none')}"
    )


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """The checkpoint dict (tensors on CPU); errors name the file."""
    path = Path(path)
    if not path.exists():
        raise FusionModelError(
            f"{path}: fusion checkpoint not found (run `dvc repro train_fusion` first)"
        )
    return read_model_checkpoint(path, "fusion", FusionModelError)


def load_fusion_model(
    path: str | Path,
    *,
    expected_cfg: str | None = None,
    expected_architecture: Mapping[str, Any] | DeepLabSpec | None = None,
    expected_grid: Mapping[str, Any] | Any | None = None,
    device: str | torch.device = "cpu",
) -> DeepLabV3Plus:
    """Load ``model.ckpt`` (path to the file or its folder) as an eval-mode :class:`DeepLabV3Plus`.

    ``model.meta`` (dict) on the returned network holds the checkpoint's meta. Raises
    :class:`FusionModelError` when the checkpoint and ``model_meta.json`` disagree, or the
    checkpoint's configuration / architecture / grid differ from the expected ones.
    """
    path = Path(path)
    if path.is_dir():
        path = path / "model.ckpt"
    ck = read_checkpoint(path)
    info = ck["traffictwin"]
    meta = read_model_meta(path.parent / META_NAME, FusionModelError)
    check_model_pair(path, meta, FusionModelError, info, SEALED_META)
    if expected_cfg is not None and info.get("cfg") != expected_cfg:
        raise FusionModelError(
            f"{path}: trained on the pose noise of '{info.get('cfg')}' ({info.get('noise', {})}), "
            f"expected '{expected_cfg}'"
        )
    arch = info.get("architecture")
    try:  # a model written before an option existed has no key for it: the option's default
        spec = DeepLabSpec.from_dict(arch)
    except (TypeError, ValueError) as exc:
        raise FusionModelError(f"{path}: invalid architecture block ({exc})") from None
    if expected_architecture is not None:
        exp = (
            expected_architecture.as_dict()
            if isinstance(expected_architecture, DeepLabSpec)
            else DeepLabSpec.from_dict(expected_architecture).as_dict()
        )
        if spec.as_dict() != exp:
            raise FusionModelError(
                f"{path}: architecture mismatch: checkpoint has {_describe_arch(spec.as_dict())}, expected {_describe_arch(exp)}"
            )
    if expected_grid is not None:
        g = (
            expected_grid
            if isinstance(expected_grid, Mapping)
            else {
                "rows": expected_grid.rows,
                "cols": expected_grid.cols,
                "cell": expected_grid.cell,
            }
        )
        got = info.get("grid", {})
        if any(abs(float(got.get(k, -1)) - float(g[k])) > 1e-9 for k in ("rows", "cols", "cell")):
            raise FusionModelError(f"{path}: trained on grid {got}, expected grid {dict(g)}")
    net = DeepLabV3Plus(spec)
    state = net_state_dict(ck)
    try:
        net.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        raise FusionModelError(
            f"{path}: weights do not fit the architecture {_describe_arch(arch)}: {str(exc)[:500]}"
        ) from None
    net.meta = dict(info)  # type: ignore[attr-defined]
    return net.to(device).eval()


@torch.no_grad()
def predict_evidence(
    model: torch.nn.Module, inputs: np.ndarray, batch_size: int = 16
) -> np.ndarray:
    """Evidences ``(N, 2, H, W)`` float32 for ``inputs (N, 4, H, W)`` float32 masses."""
    x = np.asarray(inputs)
    if x.ndim != 4 or x.shape[1] != 4:
        raise ValueError(
            f"inputs must be (N, 4, H, W) = [m_F1, m_O1, m_F2', m_O2'], got shape {x.shape}"
        )
    model.eval()
    dev = next(model.parameters()).device
    out = np.empty((x.shape[0], 2, *x.shape[2:]), dtype=np.float32)
    for i in range(0, x.shape[0], batch_size):
        xb = torch.from_numpy(np.ascontiguousarray(x[i : i + batch_size], dtype=np.float32)).to(dev)
        out[i : i + batch_size] = model(xb).float().cpu().numpy()
    return out


def predict_masses(
    model: torch.nn.Module, inputs: np.ndarray, batch_size: int = 16
) -> tuple[np.ndarray, np.ndarray]:
    """Fused masses ``m (N, 2, H, W)`` (free, occupied) and uncertainty ``u (N, H, W)``, float32."""
    m, u = evidence_to_masses(predict_evidence(model, inputs, batch_size))
    return m.astype(np.float32), u.astype(np.float32)
