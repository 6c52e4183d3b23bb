"""Tiny models logged to MLflow the way the trainers log theirs (weights + JSON, SHA-256 sealed).

A ``Linear(in, out)`` stands for a network: :func:`log_linear` logs it with
:func:`traffictwin.trainer.log_model` (problem ``linear``), :func:`load_linear` is its problem
loader (``weights_only`` checkpoint, like fusion/risk ``model_io``) for
:func:`traffictwin.mlops.registry.load_registered`.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from traffictwin.trainer import log_model, model_checkpoint, net_state_dict, read_model_checkpoint

PROBLEM = "linear"


def linear(weight: np.ndarray | float, in_features: int = 2) -> torch.nn.Linear:
    """``Linear(in_features, 1)`` without bias, weights ``weight`` (broadcast)."""
    m = torch.nn.Linear(in_features, 1, bias=False)
    with torch.no_grad():
        m.weight.copy_(torch.as_tensor(np.broadcast_to(weight, (1, in_features)).copy()))
    return m


def log_linear(
    weight: np.ndarray | float,
    *,
    in_features: int = 2,
    experiment: str = "fusion",
    meta: Mapping[str, Any] | None = None,
    params: Mapping[str, Any] | None = None,
) -> str:
    """Log ``linear(weight)`` in a new run of ``experiment``; returns the run id."""
    import mlflow

    m = linear(weight, in_features)
    arch = {"in_features": in_features, "out_features": 1}
    meta = {"architecture": arch, **dict(meta or {})}
    mlflow.set_experiment(experiment)
    with mlflow.start_run() as run:
        if params:
            mlflow.log_params(dict(params))
        log_model(
            model_checkpoint(PROBLEM, arch, m.state_dict(), meta),
            meta,
            m,
            np.zeros((1, in_features), np.float32),
        )
    return run.info.run_id


def load_linear(folder: str | Path) -> torch.nn.Linear:
    """The problem loader of :func:`log_linear`'s models (``weights_only=True``)."""
    ck = read_model_checkpoint(Path(folder) / "model.ckpt", PROBLEM)
    arch = ck["traffictwin"]["architecture"]
    m = torch.nn.Linear(arch["in_features"], arch["out_features"], bias=False)
    m.load_state_dict(net_state_dict(ck))
    m.meta = dict(ck["traffictwin"])  # type: ignore[attr-defined]
    return m.eval()
