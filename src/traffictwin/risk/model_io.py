"""Save and load trained risk networks: ``<dir>/model.ckpt`` + ``<dir>/model_meta.json``.

``model.ckpt`` is in the one checkpoint format of :mod:`traffictwin.trainer` (problem ``risk``,
``architecture`` = ``Dave2Config.to_dict()``, ``state_dict`` with ``net.`` prefixes), loadable
with ``weights_only=True`` (no pickled code). ``model_meta.json``
repeats the config and adds what a user of the model needs: the training label column, the
variant name, parameter count, best validation error, the MLflow run/model URI (when tracked),
the data manifest hash. :func:`load_risk_model` returns a :class:`RiskModel` that preprocesses raw
frames exactly like training did.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from traffictwin.model_format import (
    MODEL_FORMAT,
    check_model_pair,
    model_checkpoint,
    net_state_dict,
    read_model_checkpoint,
    read_model_meta,
    save_model_files,
)
from traffictwin.risk.dave2 import Dave2, Dave2Config, count_parameters, preprocess
from traffictwin.risk.predictor import RiskFrames, RiskPredictor

CKPT = "model.ckpt"
META = "model_meta.json"


# meta keys the loaders and the API trust (stereo domain, label, objective), sealed against the
# checkpoint's own copy (check_model_pair); the meta's ``config`` is the checkpoint's architecture
SEALED_META = ("domain", "label", "objective")


class RiskModelError(RuntimeError):
    """A risk model file is missing, unreadable or inconsistent."""


@dataclass
class RiskModel(RiskPredictor):
    """A trained network plus its metadata; :meth:`predict` works on raw frames."""

    net: Dave2
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def cfg(self) -> Dave2Config:
        return self.net.cfg

    @torch.no_grad()
    def predict_frames(self, frames: RiskFrames, batch_size: int) -> np.ndarray:
        """The network's risk of ``frames`` (see :func:`~.dave2.prepare_channels`); ``speed`` is
        required when the model uses it."""
        self.net.eval()
        images = (frames.left_bgr, *(frames.disparity.get(k) for k in ("disp_sgm", "disp_gt")))
        if all(a is None for a in images):
            raise ValueError(f"the risk network reads {list(self.cfg.inputs)}: none was given")
        n = next(len(a) for a in images if a is not None)
        if self.cfg.use_speed and frames.speed is None:
            raise ValueError("this risk model uses the subject speed: pass speed (N,) in m/s")
        out = []
        for i in range(0, n, batch_size):
            sl = slice(i, i + batch_size)
            x = preprocess(self.cfg, *(a[sl] if a is not None else None for a in images))
            s = (
                torch.as_tensor(np.asarray(frames.speed[sl], dtype=np.float32))
                if self.cfg.use_speed
                else None
            )
            out.append(self.net(x, s).float().numpy())
        return np.concatenate(out) if out else np.zeros(0, np.float32)


def risk_checkpoint(net: Dave2, meta: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The ``model.ckpt`` content of ``net`` (:func:`traffictwin.trainer.model_checkpoint`, problem ``risk``)."""
    return model_checkpoint("risk", net.cfg.to_dict(), net.state_dict(), meta)


def risk_meta(net: Dave2, meta: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The ``model_meta.json`` content of ``net``: format, config, parameter count and ``meta``."""
    return {
        "format": MODEL_FORMAT,
        "architecture": "dave2",
        "config": net.cfg.to_dict(),
        "in_channels": net.cfg.in_channels,
        "n_parameters": count_parameters(net),
        **(dict(meta) if meta else {}),
    }


def save_risk_model(net: Dave2, out_dir: str | Path, meta: Mapping[str, Any] | None = None) -> Path:
    """Write ``model.ckpt`` and ``model_meta.json`` into ``out_dir`` as one unit
    (:func:`traffictwin.trainer.save_model_files`: old meta removed, checkpoint, then the meta
    with the checkpoint's SHA-256, each atomically); returns the folder."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    save_model_files(out / CKPT, risk_checkpoint(net, meta), out / META, risk_meta(net, meta))
    return out


def load_risk_model(path: str | Path, map_location: str | torch.device = "cpu") -> RiskModel:
    """Load a risk model from its folder (or its ``model.ckpt``); errors name the file and the problem."""
    p = Path(path)
    folder = p if p.is_dir() else p.parent
    ckpt = p if p.is_file() else folder / CKPT
    if not ckpt.exists():
        raise RiskModelError(
            f"{ckpt}: risk model checkpoint not found (run the train_risk stage first)"
        )
    blob = read_model_checkpoint(ckpt, "risk", RiskModelError, map_location)
    arch = blob["traffictwin"].get("architecture")
    if isinstance(arch, dict) and arch.get("kind") in ("hybrid", "geometric"):
        return _load_predictor(folder, ckpt, blob, arch)
    try:
        cfg = Dave2Config.from_dict(blob["traffictwin"]["architecture"])
    except (TypeError, ValueError, KeyError) as exc:
        raise RiskModelError(f"{ckpt}: invalid model config ({exc})") from None
    net = Dave2(cfg)
    try:
        net.load_state_dict(net_state_dict(blob))
    except RuntimeError as exc:
        raise RiskModelError(
            f"{ckpt}: weights do not match the configured network ({exc})"
        ) from None
    net.eval()
    meta = _read_meta(folder, ckpt, blob)
    return RiskModel(net=net, meta=meta)


def _read_meta(folder: Path, ckpt: Path, blob: Mapping[str, Any]) -> dict[str, Any]:
    """``model_meta.json`` checked against the checkpoint (:func:`check_model_pair`): the hash,
    the sealed keys, and ``config`` equal to the checkpoint's architecture."""
    mpath = folder / META
    meta = read_model_meta(mpath, RiskModelError)
    info = blob["traffictwin"]
    check_model_pair(ckpt, meta, RiskModelError, info, SEALED_META)
    if "config" in meta and json.loads(json.dumps(meta["config"])) != info.get("architecture"):
        raise RiskModelError(
            f"{mpath}: 'config' differs from the architecture in {ckpt.name} (files from different "
            "trainings, or the metadata was edited); re-run the training stage"
        )
    return meta


def _load_predictor(folder: Path, ckpt: Path, blob: Mapping[str, Any], arch: Mapping[str, Any]):
    """A corridor rule or hybrid (:mod:`traffictwin.risk.predictors`) from its checkpoint."""
    from traffictwin.risk.predictors import build_predictor

    meta = _read_meta(folder, ckpt, blob)
    try:
        return build_predictor(arch, net_state_dict(blob), meta)
    except (TypeError, ValueError, KeyError, RuntimeError) as exc:
        raise RiskModelError(f"{ckpt}: invalid {arch.get('kind')} risk predictor ({exc})") from None


def save_predictor(model: Any, out_dir: str | Path, meta: Mapping[str, Any] | None = None) -> Path:
    """Write a corridor rule or hybrid (``model.architecture()``, its weights if any) as
    ``model.ckpt`` + ``model_meta.json``, like :func:`save_risk_model`; returns the folder."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    arch = model.architecture()
    state = model.net.state_dict() if getattr(model, "net", None) is not None else {}
    info = {
        "format": MODEL_FORMAT,
        "architecture": arch["kind"],
        "config": arch,
        **dict(meta or {}),
    }
    if state:
        info["n_parameters"] = int(sum(p.numel() for p in model.net.parameters()))
    save_model_files(out / CKPT, model_checkpoint("risk", arch, state, meta), out / META, info)
    return out
