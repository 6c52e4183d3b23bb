"""DeepLabV3+ (Chen et al. 2018) on a plain-torch ResNet, adapted to evidential fusion (paper III-A).

Encoder: ResNet backbone at output stride 16 (last stage dilated) + ASPP (1x1 conv, three 3x3
atrous convs at rates 6/12/18 and image pooling, concatenated and projected by a 1x1 conv).
Decoder: the stride-4 low-level features projected to 48 channels, the ASPP output upsampled
x4 and concatenated, two 3x3 convs, a 1x1 classifier to ``num_outputs`` channels, bilinear
upsampling x4 to the input size. The final activation is ReLU instead of softmax: the outputs
are evidences ``e >= 0`` for (free, occupied) per cell (see :mod:`traffictwin.fusion.losses`).

Three extensions beyond the paper (all off in :class:`DeepLabSpec`'s defaults = the paper's net):

- **Full-resolution refinement head** (``refine_channels > 0``): the decoder features are
  projected to ``refine_channels`` at stride 4, upsampled x4 and concatenated with the input
  grids (and, with ``refine_dempster``, their Dempster combination ``(m_F, m_O, u)``); a 3x3
  conv + ReLU and two 1x1 convs then predict the evidence of every cell at stride 1, so the
  output can copy or draw one-cell structure (walls, poles) that a stride-4 head blurs.
- **Evidence activation** ``evidence``: ``relu`` (paper) or ``exp`` (``e = exp(min(z, 30))``):
  masses are then a softmax of ``(z_F, z_O, log 2)``, so a mass loss never meets a dead unit.
- **Residual evidential head** ``residual: dempster`` (needs ``exp`` evidence and 4 input
  channels): the network computes Dempster's combination ``(m_F, m_O, u)`` of the two input grids
  itself, converts it to logits ``z_k = log 2 + log m_k − log u`` (masses and ``u`` clamped to
  :data:`RESIDUAL_EPS`), and its last conv only adds a correction ``Δ`` to them:
  ``e = exp(z_Dempster + Δ)``. That conv starts at zero weights and bias, so before training the
  output masses are Dempster's (to ~``RESIDUAL_EPS``); training learns where the aligned pair's
  Dempster result is wrong (pose noise) and leaves it where the maps agree. ``none`` = the
  plain network (the paper's, kept as an ablation). The floor 1e-3 keeps a confidently wrong
  cell |z| <= ~7.6 from its repair: at 1e-6 (|z| ~14.5) a short training check trailed the plain
  network at every noisy configuration, at 1e-3 it matched or beat it while starting at KLD(b)
  ~0.0014 from Dempster on aligned maps.

Input: ``(N, 4, H, W)`` float = ``[m_F1, m_O1, m_F2', m_O2']``; ``H`` and ``W`` divisible by 16.
Output: ``(N, 2, H, W)`` evidences (channel 0 free, 1 occupied).

The architecture, :class:`DeepLabSpec`, lives in :mod:`traffictwin.fusion.deeplab_spec` (no torch,
so that ``check_params`` validates it without loading torch) and is re-exported here.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from traffictwin.evidential.dempster import dempster
from traffictwin.fusion.deeplab_spec import (  # noqa: F401 - re-exported: the spec's home is torch-free
    EVIDENCE_ACTIVATIONS,
    MAX_CHANNELS,
    MAX_OUTPUTS,
    MAX_RATE,
    MAX_RATES,
    RESIDUALS,
    DeepLabSpec,
)
from traffictwin.fusion.resnet import ResNet

EXP_MAX_LOGIT = 30.0  # e <= exp(30) ~ 1e13: u >= 2e-13, far below any label's resolution
RESIDUAL_EPS = 1e-3  # floor of Dempster's masses and u before their logs (|z| <= ~7.6)


def _conv_bn_relu(cin: int, cout: int, k: int, dilation: int = 1) -> nn.Sequential:
    pad = dilation * (k // 2)
    return nn.Sequential(
        nn.Conv2d(cin, cout, k, padding=pad, dilation=dilation, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
    )


class ASPPPooling(nn.Module):
    """Image-level features: global average pool, 1x1 conv + BN + ReLU, broadcast back."""

    def __init__(self, cin: int, cout: int) -> None:
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, 1, bias=False)
        self.bn = nn.BatchNorm2d(cout)
        self.relu = nn.ReLU(inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        size = x.shape[-2:]
        y = self.relu(self.bn(self.conv(F.adaptive_avg_pool2d(x, 1))))
        return y.expand(-1, -1, size[0], size[1])


class ASPP(nn.Module):
    """Atrous spatial pyramid pooling: 1x1, 3x3 at each rate, image pooling; concat; 1x1 projection."""

    def __init__(self, cin: int, cout: int, rates: tuple[int, ...], dropout: float) -> None:
        super().__init__()
        branches = (
            [_conv_bn_relu(cin, cout, 1)]
            + [_conv_bn_relu(cin, cout, 3, r) for r in rates]
            + [ASPPPooling(cin, cout)]
        )
        self.branches = nn.ModuleList(branches)
        self.project = nn.Sequential(
            nn.Conv2d(cout * len(branches), cout, 1, bias=False),
            nn.BatchNorm2d(cout),
            nn.ReLU(inplace=True),
            nn.Dropout(dropout),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.project(torch.cat([b(x) for b in self.branches], dim=1))


class DeepLabV3Plus(nn.Module):
    """Evidential DeepLabV3+: ``(N, C_in, H, W)`` masses -> ``(N, 2, H, W)`` evidences (ReLU)."""

    def __init__(self, spec: DeepLabSpec) -> None:
        super().__init__()
        self.spec = spec
        bb = spec.backbone
        self.backbone = ResNet(bb)
        self.aspp = ASPP(bb.out_channels, spec.aspp_channels, spec.aspp_rates, spec.aspp_dropout)
        self.low_proj = _conv_bn_relu(bb.low_level_channels, spec.low_level_channels, 1)
        self.decoder = nn.Sequential(
            _conv_bn_relu(spec.aspp_channels + spec.low_level_channels, spec.decoder_channels, 3),
            _conv_bn_relu(spec.decoder_channels, spec.decoder_channels, 3),
        )
        r = spec.refine_channels
        if r:
            # stride-4 features -> r channels, upsampled; + inputs (+ Dempster) -> stride-1 head
            self.classifier = _conv_bn_relu(spec.decoder_channels, r, 1)
            head_in = r + bb.in_channels + (3 if spec.refine_dempster else 0)
            self.refine = nn.Sequential(  # no BN at full resolution: ~2x cheaper on a CPU
                nn.Conv2d(head_in, r, 3, padding=1),
                nn.ReLU(inplace=True),
                nn.Conv2d(r, r, 1),
                nn.ReLU(inplace=True),
                nn.Conv2d(r, spec.num_outputs, 1),
            )
            last = self.refine[-1]
        else:
            self.classifier = nn.Conv2d(spec.decoder_channels, spec.num_outputs, 1)
            self.refine = None
            last = self.classifier
        heads = [*self.aspp.modules(), *self.low_proj.modules(), *self.decoder.modules()]
        if self.refine is not None:
            heads += [*self.classifier.modules(), *self.refine.modules()]
        for m in heads:
            if isinstance(m, nn.Conv2d) and m is not last:
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
        if spec.residual == "dempster":  # the correction starts at 0: output = Dempster's
            nn.init.zeros_(last.weight)
            nn.init.zeros_(last.bias)
        else:
            nn.init.normal_(last.weight, std=0.01)
            nn.init.constant_(last.bias, 0.1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2:]
        os_ = self.spec.output_stride
        if h % os_ or w % os_:
            raise ValueError(
                f"input height/width ({h}, {w}) must be divisible by the output stride {os_}"
            )
        if x.shape[-3] != self.spec.backbone.in_channels:
            raise ValueError(
                f"input has {x.shape[-3]} channels, the network expects {self.spec.backbone.in_channels}"
            )
        low, high = self.backbone(x)
        y = self.aspp(high)
        y = F.interpolate(y, size=low.shape[-2:], mode="bilinear", align_corners=False)
        y = self.decoder(torch.cat([y, self.low_proj(low)], dim=1))
        y = self.classifier(y)
        y = F.interpolate(y, size=(h, w), mode="bilinear", align_corners=False)
        if self.refine is not None:
            parts = [y, x]
            if self.spec.refine_dempster:
                parts.append(_dempster_features(x))
            y = self.refine(torch.cat(parts, dim=1))
        if self.spec.residual == "dempster":
            y = dempster_logits(x) + y.float()  # float32: the logits reach |z| ~ 14.5
        if self.spec.evidence == "exp":
            return torch.exp(y.clamp(max=EXP_MAX_LOGIT))
        return F.relu(y)


def dempster_logits(x: torch.Tensor, eps: float = RESIDUAL_EPS) -> torch.Tensor:
    """Logits ``(N, 2, H, W)`` whose ``exp`` evidence gives Dempster's combination of ``x[:, :2]``
    and ``x[:, 2:4]``: ``e_k = 2 m_k / u``, so ``z_k = log 2 + log m_k − log u`` (``m_k`` and ``u``
    floored at ``eps``: a cell with ``m_k = 0`` gets ``m_k ≈ eps·u``, one with ``u = 0`` gets
    ``u ≈ eps``). float32, without gradient (the inputs are data)."""
    with torch.no_grad():
        m = dempster(x[:, 0:2].float(), x[:, 2:4].float())
        u = (1.0 - m.sum(dim=1, keepdim=True)).clamp_min(eps)
        return math.log(2.0) + torch.log(m.clamp_min(eps)) - torch.log(u)


def _dempster_features(x: torch.Tensor) -> torch.Tensor:
    """``(m_F, m_O, u)`` of Dempster's combination of the input grids ``x[:, :2]`` and ``x[:, 2:4]``."""
    m = dempster(x[:, 0:2], x[:, 2:4])
    return torch.cat([m, (1.0 - m.sum(dim=1, keepdim=True)).clamp(0.0, 1.0)], dim=1)


def channels_last_supported(model: nn.Module) -> bool:
    """Whether ``model`` can train in NHWC (``channels_last``) memory format on a oneDNN CPU.

    oneDNN 3.12 (bundled with torch 2.13 CPU wheels, AVX2 kernels) corrupts the heap or fails
    with "could not create a primitive descriptor for the reorder primitive" in the
    weight-gradient of a *strided 1x1* convolution in NHWC with 2..7 input channels (fewer than
    one AVX2 vector of float32); 1 or >= 8 channels are fine. In a ResNet that is the projection
    shortcut of ``layer2`` when ``base_width < 8`` (basic blocks) — test-sized networks only;
    every real configuration has ``base_width >= 8``. Such networks train in NCHW.
    """
    for m in model.modules():
        if (
            isinstance(m, nn.Conv2d)
            and m.kernel_size == (1, 1)
            and m.stride != (1, 1)
            and 1 < m.in_channels < 8
        ):
            return False
    return True


def count_parameters(model: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)
