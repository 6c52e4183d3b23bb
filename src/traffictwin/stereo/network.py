"""A small learned stereo network (StereoNet / AnyNet family) and its loss.

:class:`StereoNet`: a shared 2-D feature extractor at 1/``stride`` resolution, a group-wise
correlation cost volume over ``max_disparity / stride`` disparities, a few 3-D convolutions of
aggregation, softmax over disparity + soft-argmin (the coarse disparity and its spread, the standard
deviation of the disparity distribution), bilinear upsampling to full resolution and an
edge-aware residual refinement guided by the left image (dilated convolutions on [left image,
upsampled disparity, left - right warped by it]). Every disparity is in full-resolution pixels.

:func:`stereo_loss`: smooth-L1 plus a relative term ``|d - d_gt| / max(d_gt, eps)`` on the pixels
with ground truth (``0 < d_gt < max_disparity``), on the refined and the coarse output.

The architecture, :class:`StereoNetSpec`, lives in :mod:`traffictwin.stereo.network_spec` (no
torch, so that ``check_params`` validates it without loading torch) and is re-exported here.
"""

from __future__ import annotations

import math
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from traffictwin.stereo.network_spec import BASES, StereoNetSpec


def _conv(cin: int, cout: int, stride: int = 1, dilation: int = 1) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, stride, padding=dilation, dilation=dilation, bias=False),
        nn.BatchNorm2d(cout),
        nn.LeakyReLU(0.2, inplace=True),
    )


class _Res(nn.Module):
    def __init__(self, c: int, dilation: int = 1) -> None:
        super().__init__()
        self.a = _conv(c, c, dilation=dilation)
        self.b = nn.Conv2d(c, c, 3, padding=dilation, dilation=dilation, bias=False)
        self.bn = nn.BatchNorm2d(c)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.leaky_relu(x + self.bn(self.b(self.a(x))), 0.2)


def soft_argmin(cost_logits: torch.Tensor, step: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Expected disparity and its spread (standard deviation) of ``softmax(cost_logits)`` over
    dim 1 (levels ``0, step, 2 step, ...``; ``cost_logits`` (B, D, H, W), higher = more likely).
    Returns ``(disparity, spread)``, each (B, 1, H, W), in the units of ``step``."""
    p = torch.softmax(cost_logits, dim=1)
    d = torch.arange(cost_logits.shape[1], dtype=p.dtype, device=p.device).view(1, -1, 1, 1) * step
    mean = (p * d).sum(1, keepdim=True)
    var = (p * (d - mean) ** 2).sum(1, keepdim=True)
    return mean, var.clamp_min(0.0).sqrt()


def local_costs(
    left: torch.Tensor, right: torch.Tensor, disp: torch.Tensor, offsets: torch.Tensor
) -> torch.Tensor:
    """Matching cost ``mean_c |left - right(x - disp - o)|`` (B, K, H, W) at each of the K
    disparity offsets ``offsets`` (px), the right image resampled bicubically (bilinear
    resampling pulls sub-pixel minima towards whole pixels) with its border repeated; one
    resampling for all K. ``disp`` (B, 1, H, W) px."""
    b, c, h, w = right.shape
    k = offsets.numel()
    d = (disp.unsqueeze(1) + offsets.to(disp).view(1, k, 1, 1, 1)).reshape(b * k, 1, h, w)
    rr = right.unsqueeze(1).expand(b, k, c, h, w).reshape(b * k, c, h, w)
    warped = warp_right(rr, d, mode="bicubic", padding_mode="border")
    return (left.unsqueeze(1) - warped.view(b, k, c, h, w)).abs().mean(2)


def warp_right(
    right: torch.Tensor, disp: torch.Tensor, mode: str = "bilinear", padding_mode: str = "zeros"
) -> torch.Tensor:
    """The right image resampled at ``x - disp`` (B, C, H, W; ``disp`` (B, 1, H, W) px): where the
    disparity is right, it reproduces the left image (``grid_sample``'s ``mode`` and
    ``padding_mode``: zeros beyond the border by default)."""
    b, _, h, w = right.shape
    xs = torch.arange(w, dtype=disp.dtype, device=disp.device).view(1, 1, w).expand(b, h, w)
    ys = torch.arange(h, dtype=disp.dtype, device=disp.device).view(1, h, 1).expand(b, h, w)
    gx = 2.0 * (xs - disp[:, 0]) / max(w - 1, 1) - 1.0
    gy = 2.0 * ys / max(h - 1, 1) - 1.0
    grid = torch.stack([gx, gy], -1)
    return F.grid_sample(right, grid, mode=mode, padding_mode=padding_mode, align_corners=True)


class StereoNet(nn.Module):
    """Left/right images (B, 3, H, W), float in [0, 1] -> dict of ``disparity`` (B, 1, H, W) px
    (refined), ``coarse`` (B, 1, H, W) px (upsampled soft-argmin) and ``spread`` (B, 1, H, W) px
    (std of the disparity distribution, upsampled). H and W must be multiples of ``stride``."""

    def __init__(self, spec: StereoNetSpec) -> None:
        super().__init__()
        self.spec = spec
        r = spec.refine_channels
        if spec.base == "sgm":
            # the refinement alone: [left, SGM disparity, validity, left - warped, local costs]
            k = spec.local_cost_offsets
            n_off = 2 * k + 1 if k else 0
            offsets = torch.arange(-k, k + 1, dtype=torch.float32) * float(spec.local_cost_step_px)
            self.register_buffer("cost_offsets", offsets[:n_off], persistent=False)
            self.refine_in = _conv(3 + 1 + 1 + 3 + n_off, r)
            self.refine = nn.Sequential(*[_Res(r, d) for d in spec.refine_dilations])
            self.refine_out = nn.Conv2d(r, 1, 3, padding=1)
            nn.init.zeros_(self.refine_out.weight)  # untrained: SGM plus the local search
            nn.init.zeros_(self.refine_out.bias)
            if n_off:  # untrained: the soft-argmin of the box-aggregated cost (a classical search)
                win = spec.local_cost_window
                self.cost_aggregate = nn.Conv2d(1, 1, win, padding=win // 2, bias=False)
                nn.init.constant_(self.cost_aggregate.weight, 1.0 / win**2)
                self.cost_log_scale = nn.Parameter(torch.tensor(math.log(100.0)))
                self.cost_logits = nn.Conv2d(r, n_off, 3, padding=1)
                nn.init.zeros_(self.cost_logits.weight)
                nn.init.zeros_(self.cost_logits.bias)
            return
        c = spec.feature_channels
        layers: list[nn.Module] = [_conv(3, c, stride=min(spec.stride, 2))]
        if spec.stride == 4:
            layers.append(_conv(c, c, stride=2))
        layers += [_Res(c), _Res(c), nn.Conv2d(c, c, 3, padding=1)]
        self.features = nn.Sequential(*layers)
        a = spec.aggregation_channels
        agg: list[nn.Module] = [
            nn.Conv3d(spec.groups, a, 3, padding=1, bias=False),
            nn.BatchNorm3d(a),
            nn.LeakyReLU(0.2, inplace=True),
        ]
        for _ in range(spec.aggregation_layers):
            agg += [
                nn.Conv3d(a, a, 3, padding=1, bias=False),
                nn.BatchNorm3d(a),
                nn.LeakyReLU(0.2, inplace=True),
            ]
        agg.append(nn.Conv3d(a, 1, 3, padding=1))
        self.aggregate = nn.Sequential(*agg)
        r = spec.refine_channels
        self.refine_in = _conv(3 + 1 + 3, r)
        self.refine = nn.Sequential(*[_Res(r, d) for d in spec.refine_dilations])
        self.refine_out = nn.Conv2d(r, 1, 3, padding=1)
        nn.init.zeros_(self.refine_out.weight)  # starts as the identity on the coarse disparity
        nn.init.zeros_(self.refine_out.bias)

    def cost_volume(self, fl: torch.Tensor, fr: torch.Tensor) -> torch.Tensor:
        """Group-wise correlation (B, G, D, h, w): mean over each group's channels of
        ``fl(x) * fr(x - d)``, zero where ``x - d`` falls outside the image."""
        b, c, h, w = fl.shape
        g, n = self.spec.groups, self.spec.levels
        fl = fl.view(b, g, c // g, h, w)
        fr = F.pad(fr, (n - 1, 0)).view(b, g, c // g, h, w + n - 1)
        # fr_pad[..., x + n - 1 - d] = fr[..., x - d]: a strided view over the levels, no loop
        win = fr.unfold(-1, w, 1)  # (b, g, c/g, h, n, w): window k starts at k = n - 1 - d
        win = win.flip(-2).permute(0, 1, 2, 4, 3, 5)  # (b, g, c/g, n, h, w), level d
        return (fl.unsqueeze(3) * win).mean(2)

    def forward(
        self, left: torch.Tensor, right: torch.Tensor, sgm: torch.Tensor | None = None
    ) -> dict[str, torch.Tensor]:
        """``sgm`` (B, 1, H, W) px, -1 (any negative) = invalid: required in ``base: sgm`` mode."""
        # float32 throughout, whatever the trainer's autocast: bf16's 8-bit mantissa resolves a
        # 30 px disparity to 0.125 px, far coarser than the sub-pixel accuracy this net is for
        with torch.autocast(left.device.type, enabled=False):
            if self.spec.base == "sgm":
                if sgm is None:
                    raise ValueError("StereoNet (base: sgm) needs the SGM disparity input")
                return self._refine_sgm(left.float(), right.float(), sgm.float())
            return self._forward(left.float(), right.float())

    def _refine_sgm(
        self, left: torch.Tensor, right: torch.Tensor, sgm: torch.Tensor
    ) -> dict[str, torch.Tensor]:
        """SGM + ``tanh(residual) * max_residual_px`` (+ the local search's soft-argmin offset) on
        SGM's valid pixels, -1 elsewhere; ``spread`` px = the local search distribution's standard
        deviation, without one |residual| (0 where SGM is invalid); ``coarse`` = SGM (invalid -> 0)."""
        if sgm.shape[-2:] != left.shape[-2:] or sgm.shape[1] != 1:
            raise ValueError(
                f"StereoNet: SGM disparity {tuple(sgm.shape)} must be (B, 1) x the image size "
                f"{tuple(left.shape[-2:])}"
            )
        valid = sgm >= 0
        d0 = torch.where(valid, sgm, torch.zeros_like(sgm))
        rs = self.spec.refine_stride
        if rs > 1:
            lo, ro = F.avg_pool2d(left, rs), F.avg_pool2d(right, rs)
            dr = F.avg_pool2d(d0, rs) / rs
            vr = F.avg_pool2d(valid.float(), rs)
        else:
            lo, ro, dr, vr = left, right, d0, valid.float()
        err = lo - warp_right(ro, dr)
        x = [lo - 0.5, dr * (rs / self.spec.max_disparity), vr, err]
        n_off = self.cost_offsets.numel()
        if n_off:  # offsets in px of the refinement's resolution
            cost = local_costs(lo, ro, dr, self.cost_offsets / rs)
            x.append(cost)
        z = self.refine(self.refine_in(torch.cat(x, 1)))
        raw = self.refine_out(z)
        if n_off:
            b, _, h, w = cost.shape
            agg = self.cost_aggregate(cost.reshape(b * n_off, 1, h, w)).view(b, n_off, h, w)
            logits = self.cost_logits(z) - self.cost_log_scale.exp() * agg
            step = float(self.spec.local_cost_step_px)
            offset = soft_argmin(logits, step)[0]  # at offsets 0, step, ... from -k * step
            # the spread is not trained: without the detach, a one-hot distribution's sqrt(0) would
            # send 0 * inf = NaN into the gradients
            spread = soft_argmin(logits.detach(), step)[1]
            raw = torch.cat([raw, offset - self.spec.local_cost_offsets * step, spread], 1)
        if rs > 1:
            raw = F.interpolate(raw, size=left.shape[-2:], mode="bilinear", align_corners=False)
        res = torch.tanh(raw[:, :1]) * float(self.spec.max_residual_px)
        res = res + raw[:, 1:2] if n_off else res
        zero = torch.zeros_like(res)
        res = torch.where(valid, res, zero)
        spread = torch.where(valid, raw[:, 2:3], zero) if n_off else res.abs()
        out = torch.where(valid, (d0 + res).clamp_min(0.0), torch.full_like(d0, -1.0))
        return {"disparity": out, "coarse": d0, "spread": spread}

    def _forward(self, left: torch.Tensor, right: torch.Tensor) -> dict[str, torch.Tensor]:
        s = self.spec.stride
        h, w = left.shape[-2:]
        if h % s or w % s:
            raise ValueError(f"StereoNet: image size {h}x{w} px must be a multiple of stride {s}")
        x = torch.cat([left, right], 0) - 0.5
        f = self.features(x)
        fl, fr = f.chunk(2, 0)
        logits = self.aggregate(self.cost_volume(fl, fr)).squeeze(1)  # (B, D, h, w)
        d, spread = soft_argmin(logits, float(s))
        if s > 1:
            d = F.interpolate(d, size=(h, w), mode="bilinear", align_corners=False)
            spread = F.interpolate(spread, size=(h, w), mode="bilinear", align_corners=False)
        rs = self.spec.refine_stride
        if rs > 1:  # refine at 1/rs resolution: image and disparity (px of that resolution)
            lo, ro = F.avg_pool2d(left, rs), F.avg_pool2d(right, rs)
            dr = F.interpolate(d, scale_factor=1.0 / rs, mode="bilinear", align_corners=False) / rs
        else:
            lo, ro, dr = left, right, d
        err = lo - warp_right(ro, dr)
        z = self.refine(
            self.refine_in(torch.cat([lo - 0.5, dr * (rs / self.spec.max_disparity), err], 1))
        )
        res = self.refine_out(z) * rs
        if rs > 1:
            res = F.interpolate(res, size=(h, w), mode="bilinear", align_corners=False)
        refined = (d + res).clamp_min(0.0)
        return {"disparity": refined, "coarse": d, "spread": spread}


def stereo_loss(
    out: dict[str, torch.Tensor],
    gt: torch.Tensor,
    *,
    max_disparity: float,
    rel_weight: float = 1.0,
    coarse_weight: float = 0.5,
    eps: float = 1.0,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Smooth-L1 (px) + ``rel_weight`` x ``|d - d_gt| / max(d_gt, eps)`` over the pixels with
    ``0 < d_gt < max_disparity``, for the refined output plus ``coarse_weight`` x the same for the
    coarse one. ``gt`` (B, 1, H, W) px. Returns the loss and its parts (refined / coarse)."""
    valid = (gt > 0) & (gt < max_disparity)
    n = valid.sum().clamp_min(1)
    g = gt.clamp_min(eps)

    def term(d: torch.Tensor) -> torch.Tensor:
        sl1 = F.smooth_l1_loss(d, gt, reduction="none", beta=1.0)
        rel = (d - gt).abs() / g
        return ((sl1 + rel_weight * rel) * valid).sum() / n

    fine, coarse = term(out["disparity"]), term(out["coarse"])
    return fine + coarse_weight * coarse, {"fine": fine.detach(), "coarse": coarse.detach()}


def param_count(net: nn.Module) -> int:
    """Trainable parameters of ``net``."""
    return sum(p.numel() for p in net.parameters() if p.requires_grad)


def to_input(images: Any) -> torch.Tensor:
    """BGR uint8 images (N, H, W, 3) -> RGB float (N, 3, H, W) in [0, 1]."""
    t = torch.as_tensor(images)
    if t.ndim != 4 or t.shape[-1] != 3:
        raise ValueError(f"stereo images must be (N, H, W, 3) BGR, got {tuple(t.shape)}")
    return t.flip(-1).permute(0, 3, 1, 2).float().div_(255.0)


__all__ = [
    "BASES",
    "StereoNet",
    "StereoNetSpec",
    "local_costs",
    "param_count",
    "soft_argmin",
    "stereo_loss",
    "to_input",
    "warp_right",
]
