"""The learned registration's training loss (:class:`~traffictwin.fusion.learned_registration.LearnedRegistration`):
soft cross-entropy on the coarse and fine cost volumes against Gaussian targets around the true
correction, an L1 term on the final pose and, optionally, the fused map's KLD against the label."""

from __future__ import annotations

import math

import torch

from traffictwin.evidential.dempster import dempster
from traffictwin.fusion.learned_registration import (
    LearnedRegistration,
    _clean,
    _params_of,
    warp_by,
)

__all__ = ["soft_target", "registration_loss"]


def soft_target(
    angles: torch.Tensor,
    radius: int,
    stride: int,
    m_true: torch.Tensor,
    centre: torch.Tensor,
    sig_rad: float,
    sig_px: float,
) -> torch.Tensor:
    """Gaussian target distribution over a cost volume (B, K, S, S) around the true correction."""
    th, s = _params_of(m_true, centre)
    k = angles.numel()
    cos, sin = torch.cos(angles), torch.sin(angles)  # (K,)
    # ideal correlation shift for angle k: d_k = R_k⁻¹ s (pixels)
    dx = cos[None] * s[:, 0:1] + sin[None] * s[:, 1:2]
    dy = -sin[None] * s[:, 0:1] + cos[None] * s[:, 1:2]
    offs = torch.arange(-radius, radius + 1, device=m_true.device, dtype=m_true.dtype) * stride
    wa = torch.exp(-0.5 * ((angles[None] - th[:, None]) / sig_rad) ** 2)  # (B, K)
    wy = torch.exp(-0.5 * ((offs[None, None] - dy[..., None]) / sig_px) ** 2)  # (B, K, S)
    wx = torch.exp(-0.5 * ((offs[None, None] - dx[..., None]) / sig_px) ** 2)
    t = wa[:, :, None, None] * wy[..., :, None] * wx[..., None, :]
    return t / t.sum((1, 2, 3), keepdim=True).clamp_min(1e-30) if k else t


def registration_loss(
    net: LearnedRegistration,
    inputs: torch.Tensor,
    label: torch.Tensor,
    m_true: torch.Tensor,
    centre: torch.Tensor,
    *,
    success_trans_m: float = 0.5,
    success_rot_deg: float = 1.0,
    map_weight: float = 0.0,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Training loss and its parts: soft cross-entropy on both cost volumes, L1 on the final pose
    (translation / ``success_trans_m`` + rotation / ``success_rot_deg``, the coarse estimate at a
    quarter weight), and ``map_weight`` × KLD(b) of the Dempster-fused map against ``label``."""
    from traffictwin.fusion.losses import kld_full

    out = net.estimate(inputs, centre)
    sp = net.spec
    m_true = m_true.to(out.m.dtype)
    tc = soft_target(
        net.coarse_angles.to(out.m.dtype),
        net.radius,
        net.stride,
        m_true,
        centre.to(out.m.dtype),
        math.radians(sp.rot_step_deg) / 2,
        net.stride / 2.0,
    )
    ce_c = (
        -(tc * torch.log_softmax(out.coarse_logits.flatten(1), 1).view_as(tc)).sum((1, 2, 3)).mean()
    )
    m0 = out.m_before_fine
    m_res = torch.linalg.solve(m0, m_true)  # the last fine step's target
    c1 = torch.cat([centre, torch.ones_like(centre[:, :1])], 1).to(m_true.dtype).unsqueeze(-1)
    c2 = torch.linalg.solve(m0, c1).squeeze(-1)[:, :2]
    tf = soft_target(
        net.fine_angles.to(out.m.dtype),
        net.fine_radius,
        net.fine_stride,
        m_res,
        c2,
        math.radians(sp.fine_rot_step_deg) / 2,
        net.fine_stride / 2.0,
    )
    ce_f = (
        -(tf * torch.log_softmax(out.fine_logits.flatten(1), 1).view_as(tf)).sum((1, 2, 3)).mean()
    )

    def pose_l1(m: torch.Tensor) -> torch.Tensor:
        th, s = _params_of(m, centre.to(m.dtype))
        th_t, s_t = _params_of(m_true, centre.to(m.dtype))
        dt = torch.linalg.vector_norm(s - s_t, dim=1) * net.cell / success_trans_m
        dr = (
            torch.rad2deg(torch.abs(torch.atan2(torch.sin(th - th_t), torch.cos(th - th_t))))
            / success_rot_deg
        )
        return (dt + dr).mean()

    l1 = pose_l1(out.m) + 0.25 * pose_l1(out.m_coarse)
    loss = ce_c + ce_f + 0.1 * l1
    parts = {"ce_coarse": ce_c.detach(), "ce_fine": ce_f.detach(), "pose_l1": l1.detach()}
    if map_weight > 0:
        warped = _clean(warp_by(inputs[:, 2:4], out.m, net.grid_shape))
        fused = dempster(inputs[:, :2], warped)
        kl = kld_full(fused, label).mean()
        loss = loss + map_weight * kl
        parts["kld_full"] = kl.detach()
    return loss, parts
