"""MLflow around a training run: the run on rank zero only, its Lightning logger, final
metrics, the checkpoint artifact and the network as an MLflow model (weights + JSON).

MLflow, Lightning and torch load inside the functions that use them: the stages' settings
(:class:`TrackingSettings`, :func:`global_rank`) are read by ``check_params`` without them."""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from traffictwin.model_format import (
    CKPT_SHA_KEY,
    MODEL_FORMAT,
    CheckpointError,
    save_model_checkpoint,
)

if TYPE_CHECKING:
    import torch


def global_rank() -> int:
    """This process's global rank from the launcher's environment (0 outside distributed runs)."""
    for var in ("RANK", "SLURM_PROCID"):
        if os.environ.get(var, "").isdigit():
            return int(os.environ[var])
    local = int(os.environ.get("LOCAL_RANK", "0") or 0)
    node = int(os.environ.get("NODE_RANK", os.environ.get("GROUP_RANK", "0")) or 0)
    if node == 0:
        return local
    # world layout unknown here; any process that is not local rank 0 of node 0 is not rank zero
    return node * 1_000_000 + local


@dataclass(frozen=True)
class TrackingSettings:
    """MLflow: experiment, run name, profile and stage tags, params logged once; enabled=False skips MLflow."""

    experiment: str = "fusion"
    run_name: str = "fusion"
    profile: str = "default"
    stage: str = "train_fusion"
    enabled: bool = True
    params: Mapping[str, Any] = field(default_factory=dict)


def mlflow_logger(run: Any) -> Any:
    """Lightning's ``MLFlowLogger`` writing into the already started MLflow ``run`` (``None`` -> ``None``).

    The run's tracking URI is the active one (never Lightning's default ``./mlruns`` file store).
    """
    if run is None:
        return None
    import mlflow
    from lightning.pytorch.loggers import MLFlowLogger

    return MLFlowLogger(run_id=run.info.run_id, tracking_uri=mlflow.get_tracking_uri())


def log_final_metrics(logger: Any, metrics: Mapping[str, Any], step: int = 0) -> None:
    """Log the finite numeric ``metrics`` once (at ``step``) through ``logger`` (``None``: nothing)."""
    if logger is None:
        return
    finite = {
        k: float(v)
        for k, v in metrics.items()
        if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(float(v))
    }
    logger.log_metrics(finite, step=step)


@contextmanager
def tracked_run(
    experiment: str, run_name: str, *, enabled: bool = True, **run: Any
) -> Iterator[Any]:
    """:func:`traffictwin.mlops.tracking.start_run` (project tags, params logged once; ``run``
    holds its keyword arguments) on rank zero; ``None`` elsewhere or when disabled."""
    if not enabled or global_rank() != 0:
        yield None
        return
    from traffictwin.mlops.tracking import start_run

    with start_run(experiment, run_name, **run) as active:
        yield active


def log_checkpoint(path: str | Path, artifact_path: str = "checkpoints") -> None:
    """Log a checkpoint file as an artifact of the active MLflow run."""
    import mlflow

    mlflow.log_artifact(str(path), artifact_path=artifact_path)


def log_model(
    ckpt: Mapping[str, Any],
    meta: Mapping[str, Any],
    model: torch.nn.Module,
    input_example: np.ndarray,
    *,
    name: str = "model",
    metadata: Mapping[str, Any] | None = None,
) -> str:
    """Log a trained network as an MLflow model without pickled code; returns its model URI.

    The model directory (:mod:`traffictwin.mlops.model_artifact`) holds ``ckpt`` (a checkpoint
    of :data:`MODEL_FORMAT`, written with :func:`save_model_checkpoint`; loadable with
    ``weights_only=True``) as ``model.ckpt`` and ``meta`` (the architecture and meta, JSON) as
    ``model_meta.json``; the SHA-256 of every file is recorded on the logged model. The signature
    is inferred from ``input_example`` (float32 numpy) and ``model``'s output on it (``model``
    moved to CPU, eval mode; only run, never stored). Registering is the promotion gate's job
    (:func:`traffictwin.mlops.registry.ensure_version`, outside the cached stages); load it back
    with :func:`traffictwin.mlops.registry.load_registered` and the problem's loader.
    """
    import tempfile

    import torch
    from mlflow.models import infer_signature

    from traffictwin.mlops import model_artifact as art

    info = ckpt.get("traffictwin") if isinstance(ckpt, Mapping) else None
    if not isinstance(info, Mapping) or info.get("format") != MODEL_FORMAT:
        raise CheckpointError(f"log_model: ckpt is not a '{MODEL_FORMAT}' checkpoint")
    model = model.to("cpu").eval()
    x = np.ascontiguousarray(input_example, dtype=np.float32)
    with torch.no_grad():
        y = model(torch.from_numpy(x))
    signature = infer_signature(x, y.float().numpy())
    with tempfile.TemporaryDirectory(prefix="tt-model-") as tmp:
        ck_path = save_model_checkpoint(Path(tmp) / art.CKPT, ckpt)
        meta_path = Path(tmp) / art.META
        from traffictwin.io.shards import sha256_file

        sealed = {**dict(meta), CKPT_SHA_KEY: sha256_file(ck_path)}  # the pair's seal, as on disk
        meta_path.write_text(json.dumps(sealed, indent=2, sort_keys=True, default=str) + "\n")
        uri, _ = art.log_model(
            {art.CKPT: ck_path, art.META: meta_path},
            problem=str(info.get("problem", "")),
            name=name,
            signature=signature,
            input_example=x,
            metadata=metadata,
        )
    return uri
