"""Risk predictors that are not the DAVE-2 network: the corridor rule and the corridor hybrid.

Both take what the network takes at inference (a disparity map at the camera's resolution: SGM's
unless the predictor names another in ``cfg.inputs``, and the subject speed, m/s) and return the normalised risk (``min(1/THW, 20)/20``), so the CLI, the
API, the registry and the evaluation use them through the same ``predict`` as
:class:`traffictwin.risk.model_io.RiskModel` (:func:`traffictwin.risk.model_io.load_risk_model`
dispatches on the checkpoint's ``architecture.kind``).

* :class:`GeometricRiskModel` (``kind: geometric``) — :func:`~traffictwin.risk.baselines.geometric_risk`
  with a corridor half-width chosen on the validation split. No weights.
* :class:`HybridRiskModel` (``kind: hybrid``) — a small MLP on the bird's-eye corridor profile
  of the SGM disparity (:func:`corridor_features`: the robust nearest free distance in straight
  corridors of several half-widths and in lateral strips, as inverse distance and inverse time
  headway, and the speed), trained on the training split to predict log THW. It is the learned
  model given exactly the information the rule uses. Its settings, :class:`HybridConfig`, live in
  :mod:`traffictwin.risk.hybrid_config` (no torch, so that ``check_params`` validates them without
  loading torch) and are re-exported here.
"""

from __future__ import annotations

import math
from abc import abstractmethod
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import torch
from torch import nn

from traffictwin.risk.baselines import (
    GeometricParams,
    corridor_distances,
    geometric_risk,
    lateral_bin_distances,
    thw_from_distance,
)
from traffictwin.risk.hybrid_config import (  # noqa: F401 - re-exported: the config's home is torch-free
    HYBRID_DISPARITIES,
    HybridConfig,
)
from traffictwin.risk.metric import thw_to_risk
from traffictwin.risk.predictor import RiskFrames, RiskPredictor

KINDS = ("dave2", "hybrid", "geometric")

#: the frame inputs of a predictor that sees the SGM disparity and the speed
_SGM_INPUTS = ("disp_sgm",)


@dataclass(frozen=True)
class PredictorInputs:
    """What a predictor needs per frame (the part of :class:`~traffictwin.risk.dave2.Dave2Config`
    the evaluation and the API read): input channel groups and whether it uses the speed."""

    inputs: tuple[str, ...] = _SGM_INPUTS
    use_speed: bool = True


def _camera_dict(camera: Mapping[str, Any]) -> dict[str, float]:
    keys = ("fx", "fy", "cx", "cy", "baseline", "mount_x", "mount_height", "width", "height")
    missing = [k for k in keys if k not in camera]
    if missing:
        raise ValueError(f"camera intrinsics: key(s) {missing} missing (have {sorted(camera)})")
    return {k: float(camera[k]) for k in keys}


class _DisparityPredictor(RiskPredictor):
    """A :class:`~traffictwin.risk.predictor.RiskPredictor` of one disparity map and the speed:
    it reads the disparity its ``cfg.inputs`` names (``disp_sgm`` unless built for another);
    subclasses give :meth:`risk`."""

    name = "risk predictor"
    cfg: PredictorInputs

    @property
    def disparity_key(self) -> str:
        """The disparity this predictor reads (one of :data:`HYBRID_DISPARITIES`)."""
        return self.cfg.inputs[0]

    @abstractmethod
    def risk(self, disp: np.ndarray, speed: np.ndarray) -> np.ndarray:
        """Normalised risk (N,) from its disparity (N, H, W) px and speed (N,) m/s."""

    def risk_of(self, frames: RiskFrames) -> np.ndarray:
        """:meth:`risk` of ``frames`` (its disparity and the speed, checked)."""
        if frames.speed is None:
            raise ValueError(f"the {self.name} needs the speed (m/s)")
        disp = frames.disp(self.disparity_key, self.name)
        return self.risk(disp, np.asarray(frames.speed, np.float64))

    def predict_frames(self, frames: RiskFrames, batch_size: int) -> np.ndarray:
        """Normalised risk (N,) float32 from its disparity (N, H, W) px and speed (N,) m/s."""
        return np.asarray(self.risk_of(frames), np.float32)


# --------------------------------------------------------------------------------------------
# the corridor rule


@dataclass
class GeometricRiskModel(_DisparityPredictor):
    """The corridor rule as a predictor: ``params`` (corridor half-width etc., m) and the camera
    intrinsics the disparity comes with (px, m)."""

    params: GeometricParams
    camera: dict[str, float]
    meta: dict[str, Any] = field(default_factory=dict)
    cfg: PredictorInputs = field(default_factory=PredictorInputs)
    name = "corridor rule"

    def architecture(self) -> dict[str, Any]:
        arch = {"kind": "geometric", "params": asdict(self.params), "camera": self.camera}
        if self.disparity_key != _SGM_INPUTS[0]:  # SGM's rule keeps the layout it always had
            arch["disparity"] = self.disparity_key
        return arch

    def risk(self, disp: np.ndarray, speed: np.ndarray) -> np.ndarray:
        return geometric_risk(disp, speed, self.camera, self.params)[2]


# --------------------------------------------------------------------------------------------
# the corridor hybrid


def corridor_features(
    disp: np.ndarray,
    speed: np.ndarray,
    camera: Mapping[str, float],
    geometric: GeometricParams,
    cfg: HybridConfig,
) -> np.ndarray:
    """(N, F) float32 features of frames with SGM disparity ``disp`` (N, H, W) px and speed
    ``speed`` (N,) m/s: the speed / ``speed_scale``, then for every corridor and strip the
    inverse distance ``1 / (1 + d)`` (1/m; 0 = nothing within ``max_distance``) and the inverse
    THW ``min(v / d, 20) / 20`` (the normalised risk the rule would give in that corridor)."""
    speed = np.asarray(speed, np.float64).reshape(-1)
    d = np.concatenate(
        [
            corridor_distances(disp, camera, geometric, cfg.half_widths),
            lateral_bin_distances(disp, camera, geometric, cfg.bin_edges),
        ],
        axis=1,
    )
    if speed.shape[0] != d.shape[0]:
        raise ValueError(f"speed has {speed.shape[0]} frames, disparity {d.shape[0]}")
    d = np.where(d > cfg.max_distance, np.inf, d)
    inv = 1.0 / (1.0 + d)
    ithw = thw_to_risk(thw_from_distance(d, speed))
    return np.concatenate(
        [(speed / cfg.speed_scale)[:, None], inv, ithw.astype(np.float64)], axis=1
    ).astype(np.float32)


class HybridNet(nn.Module):
    """Standardised features → MLP (two ReLU layers of ``hidden``) → log THW (log s)."""

    def __init__(self, n_features: int, hidden: int) -> None:
        super().__init__()
        self.register_buffer("mean", torch.zeros(n_features))
        self.register_buffer("std", torch.ones(n_features))
        self.mlp = nn.Sequential(
            nn.Linear(n_features, hidden),
            nn.ReLU(),
            nn.Linear(hidden, hidden),
            nn.ReLU(),
            nn.Linear(hidden, 1),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.mlp((x - self.mean) / self.std).squeeze(-1)


def log_thw_target(thw: np.ndarray, cap: float) -> np.ndarray:
    """log of the THW (s) clipped to [0.05, ``cap``] (inf / NaN = nothing ahead = ``cap``)."""
    t = np.asarray(thw, np.float64)
    t = np.where(np.isfinite(t), t, cap)
    return np.log(np.clip(t, 0.05, cap)).astype(np.float32)


def fit_hybrid(
    x: np.ndarray,
    thw: np.ndarray,
    cfg: HybridConfig,
    seed: int,
    x_val: np.ndarray | None = None,
    thw_val: np.ndarray | None = None,
) -> tuple[HybridNet, list[dict[str, float]]]:
    """Train a :class:`HybridNet` on features ``x`` (N, F) and true THW ``thw`` (N,) s, seeded
    (weights, batch order). Returns the net and its history: per epoch the mean training Huber
    loss and, with ``x_val``/``thw_val``, the validation loss (log s)."""
    x = np.asarray(x, np.float32)
    if x.ndim != 2 or x.shape[1] != cfg.n_features or len(x) == 0:
        raise ValueError(f"hybrid features: expected (N>0, {cfg.n_features}), got {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError("hybrid features must be finite")
    y = torch.from_numpy(log_thw_target(thw, cfg.thw_cap_s))
    gen = torch.Generator().manual_seed(int(seed))
    torch.manual_seed(int(seed))
    net = HybridNet(x.shape[1], cfg.hidden)
    xt = torch.from_numpy(x.copy())
    net.mean.copy_(xt.mean(0))
    net.std.copy_(xt.std(0).clamp_min(1e-6))
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    xv = torch.from_numpy(np.asarray(x_val, np.float32).copy()) if x_val is not None else None
    yv = torch.from_numpy(log_thw_target(thw_val, cfg.thw_cap_s)) if thw_val is not None else None
    history: list[dict[str, float]] = []
    for epoch in range(cfg.epochs):
        net.train()
        perm = torch.randperm(len(xt), generator=gen)
        total = 0.0
        for i in range(0, len(xt), cfg.batch_size):
            b = perm[i : i + cfg.batch_size]
            loss = nn.functional.huber_loss(net(xt[b]), y[b], delta=cfg.huber_delta)
            opt.zero_grad()
            loss.backward()
            opt.step()
            total += loss.item() * len(b)
        row = {"epoch": epoch + 1, "train_loss": total / len(xt)}
        if xv is not None and yv is not None:
            net.eval()
            with torch.no_grad():
                row["val_loss"] = float(
                    nn.functional.huber_loss(net(xv), yv, delta=cfg.huber_delta)
                )
        history.append(row)
    if not math.isfinite(history[-1]["train_loss"]):
        raise FloatingPointError("hybrid training diverged (non-finite loss)")
    net.eval()
    return net, history


@dataclass
class HybridRiskModel(_DisparityPredictor):
    """A trained :class:`HybridNet` with its feature settings, the corridor point filter
    (``geometric``; its half-width is unused) and the camera intrinsics."""

    net: HybridNet
    config: HybridConfig
    geometric: GeometricParams
    camera: dict[str, float]
    meta: dict[str, Any] = field(default_factory=dict)
    cfg: PredictorInputs = field(default_factory=PredictorInputs)
    name = "corridor hybrid"

    def architecture(self) -> dict[str, Any]:
        return {
            "kind": "hybrid",
            "features": self.config.to_dict(),
            "geometric": asdict(self.geometric),
            "camera": self.camera,
        }

    def features(self, disp: np.ndarray, speed: np.ndarray) -> np.ndarray:
        """(N, F) :func:`corridor_features` of its disparity (N, H, W) px and speed (N,) m/s."""
        return corridor_features(disp, speed, self.camera, self.geometric, self.config)

    @torch.no_grad()
    def predict_features(self, x: np.ndarray) -> np.ndarray:
        """Normalised risk (N,) float32 from features (N, F)."""
        log_thw = self.net(torch.from_numpy(np.asarray(x, np.float32).copy())).numpy()
        return thw_to_risk(np.exp(log_thw.astype(np.float64)))

    def risk(self, disp: np.ndarray, speed: np.ndarray) -> np.ndarray:
        return self.predict_features(self.features(disp, speed))

    def predict_frames(self, frames: RiskFrames, batch_size: int) -> np.ndarray:
        """Normalised risk (N,) float32; the corridor profile is computed once per feature
        setting for ``frames`` (hybrids of several seeds share it)."""
        if frames.speed is None:
            raise ValueError(f"the {self.name} needs the speed (m/s)")
        disp = frames.disp(self.disparity_key, self.name)
        key = ("corridor_features", self.config, self.geometric, tuple(sorted(self.camera.items())))
        x = frames.memo(key, lambda: self.features(disp, np.asarray(frames.speed, np.float64)))
        return np.asarray(self.predict_features(x), np.float32)


class PackedPredictor(nn.Module):
    """The rule / hybrid as a single-input module for the MLflow pyfunc flavour: input (N, 1 + H·W)
    float32 = the speed (m/s) then the disparity the predictor reads (px, row-major, the camera's
    H×W; SGM's unless its ``disparity_key`` says otherwise); output (N,) normalised risk."""

    def __init__(self, model: Any) -> None:
        super().__init__()
        self.model = model
        self.h, self.w = int(model.camera["height"]), int(model.camera["width"])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        a = x.detach().cpu().numpy()
        if a.ndim != 2 or a.shape[1] != 1 + self.h * self.w:
            raise ValueError(
                f"packed risk input must be (N, 1 + {self.h}×{self.w}) = speed + disparity, got {a.shape}"
            )
        disp = a[:, 1:].reshape(-1, self.h, self.w)
        frames = RiskFrames(disparity={self.model.disparity_key: disp}, speed=a[:, 0])
        return torch.from_numpy(self.model.predict_frames(frames, len(a)))


def _rule_disparity(architecture: Mapping[str, Any]) -> str:
    """The disparity a corridor rule's ``architecture`` reads (``disp_sgm`` when it names none);
    ``ValueError`` unless one of :data:`HYBRID_DISPARITIES`."""
    key = architecture.get("disparity", _SGM_INPUTS[0])
    if key not in HYBRID_DISPARITIES:
        raise ValueError(f"'disparity' must be one of {list(HYBRID_DISPARITIES)}, got {key!r}")
    return str(key)


def packed_for_serving(model: Any, frames: RiskFrames) -> tuple[nn.Module, np.ndarray]:
    """The single-input module the MLflow pyfunc flavour serves for a risk ``model`` (the rule /
    hybrid: :class:`PackedPredictor`; the network: :class:`~traffictwin.risk.dave2.PackedDave2`)
    and its input (float32) for ``frames``: the input example a signature is inferred from."""
    if isinstance(model, _DisparityPredictor):
        if frames.speed is None:
            raise ValueError(f"the {model.name}'s served input starts with the speed (m/s)")
        disp = frames.disp(model.disparity_key, model.name)
        speed = np.asarray(frames.speed, np.float32).reshape(-1, 1)
        x = np.concatenate([speed, disp.reshape(len(disp), -1).astype(np.float32)], axis=1)
        return PackedPredictor(model), np.ascontiguousarray(x)
    from traffictwin.risk.dave2 import PackedDave2, pack_input, preprocess

    cfg = model.cfg
    d = frames.disparity
    x = preprocess(cfg, frames.left_bgr, d.get("disp_sgm"), d.get("disp_gt"))
    sp = torch.as_tensor(np.asarray(frames.speed, np.float32)) if cfg.use_speed else None
    return PackedDave2(model.net).eval(), pack_input(cfg, x, sp).numpy()


def architecture_problem(architecture: Mapping[str, Any]) -> str | None:
    """Why a rule / hybrid ``architecture`` (a checkpoint's or ``model_meta.json``'s ``config``)
    cannot be built by this version; ``None`` if it can (no weights needed)."""
    try:
        kind = architecture.get("kind")
        if kind == "geometric":
            GeometricParams(**architecture["params"])
            PredictorInputs(inputs=(_rule_disparity(architecture),))
        elif kind == "hybrid":
            HybridConfig.from_dict(architecture["features"])
            GeometricParams(**architecture["geometric"])
        else:
            return f"unknown risk predictor kind {kind!r} (expected one of {KINDS})"
        _camera_dict(architecture["camera"])
    except (TypeError, ValueError, KeyError) as exc:
        return f"its {architecture.get('kind')} predictor config is not valid here ({exc})"
    return None


def build_predictor(architecture: Mapping[str, Any], state: Mapping[str, torch.Tensor], meta: dict):
    """A :class:`GeometricRiskModel` or :class:`HybridRiskModel` from a checkpoint's
    ``architecture`` and weights (``ValueError`` / ``RuntimeError`` on a bad one)."""
    kind = architecture.get("kind")
    if kind == "geometric":
        return GeometricRiskModel(
            GeometricParams(**architecture["params"]),
            _camera_dict(architecture["camera"]),
            meta,
            PredictorInputs(inputs=(_rule_disparity(architecture),)),
        )
    if kind == "hybrid":
        cfg = HybridConfig.from_dict(architecture["features"])
        net = HybridNet(cfg.n_features, cfg.hidden)
        net.load_state_dict(dict(state))
        net.eval()
        return HybridRiskModel(
            net,
            cfg,
            GeometricParams(**architecture["geometric"]),
            _camera_dict(architecture["camera"]),
            meta,
            PredictorInputs(inputs=(cfg.disparity,)),
        )
    raise ValueError(f"unknown risk predictor kind {kind!r} (expected one of {KINDS})")


def predictor_kind(model: Any) -> str:
    """``dave2``, ``hybrid`` or ``geometric``."""
    if isinstance(model, GeometricRiskModel):
        return "geometric"
    if isinstance(model, HybridRiskModel):
        return "hybrid"
    return "dave2"


def geometric_params_with(params: GeometricParams, half_width: float) -> GeometricParams:
    """``params`` with another corridor half-width (m)."""
    from dataclasses import replace

    return replace(params, corridor_half_width=float(half_width))


def source_features(
    source: Any,
    frames: Any,
    camera: Mapping[str, float],
    geometric: GeometricParams,
    cfg: HybridConfig,
) -> tuple[np.ndarray, Any]:
    """Hybrid features of ``frames`` (rows of a :class:`~traffictwin.risk.training.RiskSource`)
    from the disparity ``cfg.disparity`` names, and the frames in the order of the features
    (shard by shard)."""
    import pandas as pd

    feats, order = [], []
    for rows, arr in source.iter_arrays(frames, [cfg.disparity]):
        feats.append(
            corridor_features(
                arr[cfg.disparity], rows["speed"].to_numpy(np.float64), camera, geometric, cfg
            )
        )
        order.append(rows)
    if not feats:
        return np.zeros((0, cfg.n_features), np.float32), frames.iloc[:0]
    return np.concatenate(feats), pd.concat(order)
