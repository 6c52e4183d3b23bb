"""DAVE-2-like risk network (Feth et al., sec. 3.1; Bojarski et al. 2016) and its input preprocessing.

Architecture (docs/design.md "DAVE-2-like net"): five convolutions — 24, 36, 48 channels with 5×5
kernels and stride 2, then 64, 64 channels with 3×3 kernels and stride 1 — each followed by a
ReLU; flatten; fully connected layers 1164 → 100 → 50 → 10 → 1 with a ReLU on all but the last
(the output is linear: a regression of the normalised risk in [0, 1], or of log THW, see below). No pooling: the input is
already subsampled (66 × 200 by default, like DAVE-2). The first fully connected layer adapts to
the flattened size of whatever resolution is configured.

Input: a stack of image-like channels chosen by name (:data:`CHANNELS`): ``rgb`` (3 channels, the
left image), ``disp_sgm`` (SGM disparity of the stereo pair), ``disp_gt`` (ground-truth disparity:
the perfect-stereo upper bound). The paper's network sees ``rgb + disp_sgm`` (4 channels). Optionally
(``use_speed``, off in the paper) the subject speed is concatenated to the flattened features as
one more scalar input of the fully connected head.

Output (``objective``, docs/design.md "Risk metric"): :meth:`Dave2.forward` always returns the
normalised risk in [0, 1]; :meth:`Dave2.raw` the head's raw outputs, on which the training loss
(:func:`risk_loss`) works:

* ``mse`` (the paper): one linear output regressing the normalised risk (clamped to [0, 1] on
  output);
* ``log_thw``: one output regressing log THW (s), the label's THW clipped to
  [1/20, ``thw_cap_s``] (risk 0 = nothing ahead -> the cap); risk = ``min(1/THW, 20) / 20``, 0 at
  the cap. Errors near the critical THW (the decision threshold) weigh as much as anywhere else, while the
  MSE on the normalised risk hardly sees them (the threshold is at a small risk);
* ``mse_bce``: the paper's output plus a logit of "critical" (THW < ``critical_thw_s``) trained
  with a binary cross-entropy term (weight ``bce_weight`` in the loss): a classification head at
  the decision threshold that shapes the shared features; the risk output is the regression.

:func:`preprocess` turns raw frames (OpenCV BGR uint8 images, disparity in pixels with -1 = invalid)
into the network's channel stack; training, evaluation and the CLI all call it, so the three can
never disagree.

The configuration, :class:`Dave2Config` (with :data:`CHANNELS`, :data:`OBJECTIVES` and the
architecture's bounds), lives in :mod:`traffictwin.risk.dave2_config` (no torch, so that
``check_params`` validates it without loading torch) and is re-exported here.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch
from torch import nn

from traffictwin.risk.dave2_config import (  # noqa: F401 - re-exported: the config's home is torch-free
    CHANNELS,
    CONV_SPEC,
    FC_SPEC,
    MAX_CONV_CHANNELS,
    MAX_FC_WIDTH,
    MAX_INPUT_SIDE,
    MAX_KERNEL,
    MAX_LAYERS,
    OBJECTIVES,
    RISK_CLIP,
    Dave2Config,
    conv_output_shape,
)


class Dave2(nn.Module):
    """DAVE-2-like regression CNN. ``forward(x (N,C,H,W) float32, speed (N,) m/s or None) -> (N,) risk``."""

    def __init__(self, cfg: Dave2Config | None = None) -> None:
        super().__init__()
        self.cfg = cfg or Dave2Config()
        layers: list[nn.Module] = []
        c_in = self.cfg.in_channels
        for ch, k, s in self.cfg.conv:
            layers += [nn.Conv2d(c_in, ch, kernel_size=k, stride=s), nn.ReLU(inplace=True)]
            c_in = ch
        self.features = nn.Sequential(*layers)
        c, h, w = conv_output_shape(self.cfg.height, self.cfg.width, self.cfg.conv)
        self.flat_size = c * h * w
        head: list[nn.Module] = []
        n_in = self.flat_size + (1 if self.cfg.use_speed else 0)
        for n_out in self.cfg.fc:
            if self.cfg.dropout > 0:
                head.append(nn.Dropout(self.cfg.dropout))
            head += [nn.Linear(n_in, n_out), nn.ReLU(inplace=True)]
            n_in = n_out
        head.append(nn.Linear(n_in, OBJECTIVES[self.cfg.objective]))
        self.head = nn.Sequential(*head)

    def forward(self, x: torch.Tensor, speed: torch.Tensor | None = None) -> torch.Tensor:
        """Normalised risk (N,) in [0, 1] (see the module docstring)."""
        return raw_to_risk(self.cfg, self.raw(x, speed))

    def raw(self, x: torch.Tensor, speed: torch.Tensor | None = None) -> torch.Tensor:
        """The head's raw outputs (N, k), k = :data:`OBJECTIVES` [objective]."""
        cfg = self.cfg
        if (
            x.ndim != 4
            or x.shape[1] != cfg.in_channels
            or x.shape[2] != cfg.height
            or x.shape[3] != cfg.width
        ):
            raise ValueError(
                f"Dave2 expects input (N, {cfg.in_channels}, {cfg.height}, {cfg.width}) for inputs {list(cfg.inputs)}, "
                f"got {tuple(x.shape)}"
            )
        z = self.features(x).flatten(1)
        if cfg.use_speed:
            if speed is None:
                raise ValueError("Dave2 was built with use_speed=True: pass speed (N,) in m/s")
            z = torch.cat([z, (speed.reshape(-1, 1).to(z.dtype) / cfg.speed_scale)], dim=1)
        return self.head(z)


def raw_to_risk(cfg: Dave2Config, raw: torch.Tensor) -> torch.Tensor:
    """Normalised risk (N,) in [0, 1] from the raw head outputs (N, k) of objective ``cfg.objective``."""
    out = raw[:, 0].float()
    if cfg.objective == "log_thw":
        thw = torch.exp(out)
        risk = torch.clamp(1.0 / (RISK_CLIP * thw), max=1.0)
        return torch.where(thw >= cfg.thw_cap_s, torch.zeros_like(risk), risk)
    return torch.clamp(out, 0.0, 1.0)


def risk_to_log_thw(cfg: Dave2Config, y: torch.Tensor) -> torch.Tensor:
    """The ``log_thw`` target: log of THW (s) = 1 / (20 y), clipped to [1/20, thw_cap_s] (y = 0 -> cap)."""
    y = y.float()
    thw = torch.where(y > 0, 1.0 / (RISK_CLIP * torch.clamp(y, min=1e-12)), cfg.thw_cap_s)
    return torch.log(torch.clamp(thw, 1.0 / RISK_CLIP, cfg.thw_cap_s))


def risk_loss(
    cfg: Dave2Config, raw: torch.Tensor, y: torch.Tensor, bce_weight: float = 0.05
) -> torch.Tensor:
    """Training loss of objective ``cfg.objective`` on raw outputs (N, k) and normalised risk
    labels y (N,): MSE on the risk (``mse``), MSE on log THW (``log_thw``), or MSE + ``bce_weight``
    x binary cross-entropy of the critical logit against y > risk threshold (``mse_bce``)."""
    y = y.float()
    out = raw.float()
    if cfg.objective == "log_thw":
        return torch.mean((out[:, 0] - risk_to_log_thw(cfg, y)) ** 2)
    mse = torch.mean((out[:, 0] - y) ** 2)
    if cfg.objective == "mse_bce":
        critical = (y > min(1.0 / cfg.critical_thw_s, RISK_CLIP) / RISK_CLIP).float()
        bce = nn.functional.binary_cross_entropy_with_logits(out[:, 1], critical)
        return mse + bce_weight * bce
    return mse


def count_parameters(model: nn.Module) -> int:
    """Number of trainable parameters."""
    return int(sum(p.numel() for p in model.parameters() if p.requires_grad))


# --------------------------------------------------------------------------------------------
# preprocessing
# --------------------------------------------------------------------------------------------


def _resize_stack(arr: np.ndarray, height: int, width: int) -> np.ndarray:
    """Resize (N, H, W[, C]) to (N, height, width[, C]) with area interpolation (OpenCV)."""
    if arr.shape[1] == height and arr.shape[2] == width:
        return arr
    out = np.empty((arr.shape[0], height, width, *arr.shape[3:]), dtype=arr.dtype)
    for i in range(arr.shape[0]):  # per image, not per pixel: OpenCV does the pixels
        out[i] = cv2.resize(arr[i], (width, height), interpolation=cv2.INTER_AREA).reshape(
            out.shape[1:]
        )
    return out


def prepare_channels(
    cfg: Dave2Config,
    left_bgr: np.ndarray | None = None,
    disp_sgm: np.ndarray | None = None,
    disp_gt: np.ndarray | None = None,
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Resize the raw inputs the network needs to the model resolution, compactly.

    ``left_bgr``: (N, H, W, 3) uint8 BGR; ``disp_sgm``/``disp_gt``: (N, H, W) float disparity in px
    (≤ 0 or non-finite = invalid, mapped to 0). Returns ``(rgb (N,3,h,w) uint8 or None,
    disp (N,k,h,w) float16 or None)`` with the disparity channels in ``cfg.inputs`` order, already
    divided by ``cfg.disp_scale``. Call :func:`normalise` on a batch of these to get the network input.
    Raises ``ValueError`` naming the array when a needed input is missing or sizes disagree.
    """
    raw = {"rgb": left_bgr, "disp_sgm": disp_sgm, "disp_gt": disp_gt}
    shapes: dict[str, tuple[int, ...]] = {}
    for name in cfg.inputs:
        a = raw[name]
        if a is None:
            raise ValueError(
                f"input '{name}' is required by the model (inputs {list(cfg.inputs)}) but was not given"
            )
        if name == "rgb":
            if a.ndim != 4 or a.shape[-1] != 3:
                raise ValueError(f"left image: expected (N, H, W, 3) BGR, got shape {a.shape}")
            if a.dtype != np.uint8:
                raise ValueError(f"left image: expected uint8, got {a.dtype}")
            shapes[name] = a.shape[:3]
        else:
            if a.ndim != 3:
                raise ValueError(f"{name}: expected (N, H, W) disparity in px, got shape {a.shape}")
            shapes[name] = a.shape
    if len(set(shapes.values())) > 1:
        detail = ", ".join(f"{k} {v[1]}×{v[2]} (N={v[0]})" for k, v in shapes.items())
        raise ValueError(
            f"input sizes disagree: {detail}; disparity must have the image's size and frame count"
        )
    rgb = None
    if "rgb" in cfg.inputs:
        small = _resize_stack(np.ascontiguousarray(left_bgr), cfg.height, cfg.width)
        rgb = np.ascontiguousarray(small[..., ::-1].transpose(0, 3, 1, 2))  # BGR → RGB, NCHW
    disp_names = [c for c in cfg.inputs if c != "rgb"]
    disp = None
    if disp_names:
        chans = []
        for name in disp_names:
            d = np.asarray(raw[name], dtype=np.float32)
            d = np.where(np.isfinite(d) & (d > 0), d, 0.0).astype(np.float32)
            d = _resize_stack(d, cfg.height, cfg.width) / np.float32(cfg.disp_scale)
            chans.append(d)
        disp = np.stack(chans, axis=1).astype(np.float16)
    return rgb, disp


def normalise(
    cfg: Dave2Config, rgb: torch.Tensor | None, disp: torch.Tensor | None
) -> torch.Tensor:
    """Network input (N, C, h, w) float32 from :func:`prepare_channels` output (as tensors).

    RGB: ``x / 127.5 − 1`` (DAVE-2's normalisation layer), disparity: already scaled, cast to float32.
    Channels are stacked in ``cfg.inputs`` order.
    """
    parts: list[torch.Tensor] = []
    di = 0
    for name in cfg.inputs:
        if name == "rgb":
            assert rgb is not None
            parts.append(rgb.float() / 127.5 - 1.0)
        else:
            assert disp is not None
            parts.append(disp[:, di : di + 1].float())
            di += 1
    return torch.cat(parts, dim=1)


def preprocess(
    cfg: Dave2Config,
    left_bgr: np.ndarray | None = None,
    disp_sgm: np.ndarray | None = None,
    disp_gt: np.ndarray | None = None,
) -> torch.Tensor:
    """Raw frames → network input (N, C, h, w) float32 (:func:`prepare_channels` + :func:`normalise`)."""
    rgb, disp = prepare_channels(cfg, left_bgr, disp_sgm, disp_gt)
    return normalise(
        cfg,
        torch.from_numpy(rgb) if rgb is not None else None,
        torch.from_numpy(disp) if disp is not None else None,
    )


class PackedDave2(nn.Module):
    """Single-tensor wrapper of :class:`Dave2` for export (MLflow models take one input array).

    Input ``(N, C, h, w)`` normalised channels; for a speed model ``(N, C + 1, h, w)`` where the
    last plane holds the subject speed in m/s (constant over the plane; :func:`pack_input`).
    """

    def __init__(self, net: Dave2) -> None:
        super().__init__()
        self.net = net

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.net.cfg.use_speed:
            return self.net(x[:, :-1], x[:, -1, 0, 0])
        return self.net(x)


def pack_input(
    cfg: Dave2Config, x: torch.Tensor, speed: torch.Tensor | None = None
) -> torch.Tensor:
    """The :class:`PackedDave2` input: ``x`` plus, for speed models, a constant speed plane (m/s)."""
    if not cfg.use_speed:
        return x
    if speed is None:
        raise ValueError("pack_input: this model uses the subject speed; pass speed (N,) in m/s")
    plane = speed.reshape(-1, 1, 1, 1).to(x.dtype).expand(x.shape[0], 1, x.shape[2], x.shape[3])
    return torch.cat([x, plane], dim=1)
