"""TorchScript export of the two networks (``traffictwin export``).

The exported file runs with ``torch.jit.load`` alone (no traffictwin, Lightning or MLflow):

- fusion (:func:`export_fusion`): input ``(N, 4, H, W)`` float32 =
  ``[m_F1, m_O1, m_F2', m_O2']`` (map 2 already prealigned into map 1's frame, as
  :func:`traffictwin.fusion.pairs.prealign` does); output ``(N, 3, H, W)`` =
  ``(m_F, m_O, u)`` of the fused grid (evidence -> masses included);
- risk (:func:`export_risk`): input ``(N, C, h, w)`` float32, the normalised channel stack of
  :func:`traffictwin.risk.dave2.preprocess` (plus, for a model with speed input, one more plane
  holding the subject speed in m/s: :func:`traffictwin.risk.dave2.pack_input`); output ``(N,)``
  normalised risk in [0, 1].

The networks are traced on an input of the shape they were trained on (fusion: the training
grid; risk: the configured resolution); a traced fusion network is meant for that grid size.
The model's metadata goes into the file as the extra file ``traffictwin.json`` (input layout,
output layout, training grid / config, source), readable with
``torch.jit.load(path, _extra_files={"traffictwin.json": ""})``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch
from torch import nn

META_FILE = "traffictwin.json"


class FusionMasses(nn.Module):
    """The fusion network with its evidence -> masses head: ``(N, 4, H, W) -> (N, 3, H, W)``."""

    def __init__(self, net: nn.Module) -> None:
        super().__init__()
        self.net = net

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        e = self.net(x)
        s = (e + 1.0).sum(dim=1, keepdim=True)
        return torch.cat([e / s, 2.0 / s], dim=1)


def _trace(module: nn.Module, example: torch.Tensor) -> torch.jit.ScriptModule:
    import warnings

    module = module.to("cpu").eval()
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")  # tracer / deprecation chatter, not the user's business
        return torch.jit.trace(module, example, check_trace=False)


def export_fusion(net: nn.Module, grid: dict[str, Any]) -> tuple[torch.jit.ScriptModule, dict]:
    """Trace :class:`FusionMasses` of ``net`` on a ``(1, 4, rows, cols)`` input; returns the
    traced module and its metadata."""
    rows, cols = int(grid["rows"]), int(grid["cols"])
    example = torch.rand(1, 4, rows, cols) * 0.5
    traced = _trace(FusionMasses(net), example)
    meta = {
        "problem": "fusion",
        "input": "(N, 4, H, W) float32 [m_F1, m_O1, m_F2', m_O2'], map 2 prealigned into map 1's frame",
        "output": "(N, 3, H, W) float32 (m_F, m_O, u)",
        "grid": {k: grid[k] for k in ("rows", "cols", "cell") if k in grid},
    }
    return traced, meta


def export_risk(rmodel: Any) -> tuple[torch.jit.ScriptModule, dict]:
    """Trace :class:`~traffictwin.risk.dave2.PackedDave2` of a
    :class:`~traffictwin.risk.model_io.RiskModel`; returns the traced module and its metadata."""
    from traffictwin.risk.dave2 import PackedDave2

    cfg = rmodel.net.cfg
    c = cfg.in_channels + (1 if cfg.use_speed else 0)
    example = torch.rand(1, c, cfg.height, cfg.width)
    if cfg.use_speed:
        example[:, -1] = 10.0
    traced = _trace(PackedDave2(rmodel.net), example)
    meta = {
        "problem": "risk",
        "input": f"(N, {c}, {cfg.height}, {cfg.width}) float32: channels {list(cfg.inputs)} "
        "normalised as traffictwin.risk.dave2.preprocess"
        + (" + one plane of subject speed (m/s)" if cfg.use_speed else ""),
        "output": "(N,) float32 normalised risk in [0, 1]",
        "config": cfg.to_dict(),
        "domain": rmodel.meta.get("domain"),
    }
    return traced, meta


def save(module: torch.jit.ScriptModule, path: str | Path, meta: dict[str, Any]) -> None:
    """Write the TorchScript file with ``meta`` as its extra file :data:`META_FILE`.

    Serialised in memory first, then written with Python's file API: a full disk is an
    ``OSError`` the caller can report (``torch.jit.save`` to a path aborts the process there)."""
    import io

    buf = io.BytesIO()
    torch.jit.save(module, buf, _extra_files={META_FILE: json.dumps(meta, default=str)})
    Path(path).write_bytes(buf.getvalue())


def load(path: str | Path) -> tuple[torch.jit.ScriptModule, dict[str, Any]]:
    """Read an exported file back: the module (eval mode) and its metadata."""
    extra = {META_FILE: ""}
    module = torch.jit.load(str(path), map_location="cpu", _extra_files=extra)
    return module.eval(), json.loads(extra[META_FILE] or "{}")
