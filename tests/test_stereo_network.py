"""The learned stereo network (traffictwin.stereo.network): shapes, soft-argmin, spread, cost
volume, loss, the float32 guard, a tiny overfit, and the spread calibration."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from traffictwin.risk.stereo_training import calibrate_spread, predict
from traffictwin.stereo.network import (
    StereoNet,
    StereoNetSpec,
    local_costs,
    soft_argmin,
    stereo_loss,
    to_input,
    warp_right,
)

TINY = StereoNetSpec(
    max_disparity=16,
    stride=2,
    feature_channels=8,
    groups=4,
    aggregation_channels=4,
    aggregation_layers=1,
    refine_channels=8,
    refine_dilations=(1, 2),
    refine_stride=1,
)


def test_forward_shapes_and_dtypes() -> None:
    net = StereoNet(TINY).eval()
    x = torch.rand(2, 3, 32, 64)
    with torch.no_grad():
        out = net(x, x)
    assert set(out) == {"disparity", "coarse", "spread"}
    for v in out.values():
        assert v.shape == (2, 1, 32, 64) and v.dtype == torch.float32
    assert (out["disparity"] >= 0).all() and (out["spread"] >= 0).all()
    with pytest.raises(ValueError, match="multiple of stride 2"):
        net(torch.rand(1, 3, 31, 64), torch.rand(1, 3, 31, 64))


def test_forward_stays_float32_under_bf16_autocast() -> None:
    net = StereoNet(TINY).eval()
    x = torch.rand(1, 3, 32, 64)
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        out = net(x, x)
    assert out["disparity"].dtype == torch.float32


def test_soft_argmin_of_a_one_hot_cost_is_exact_with_zero_spread() -> None:
    logits = torch.full((1, 12, 2, 3), -1e4)
    logits[:, 7] = 0.0
    d, s = soft_argmin(logits, step=4.0)
    assert torch.allclose(d, torch.full_like(d, 28.0)) and torch.all(s == 0)
    two = torch.full((1, 4, 1, 1), -1e4)
    two[:, 1] = two[:, 3] = 0.0  # half at level 1, half at 3: mean 2, std 1 (levels)
    d, s = soft_argmin(two)
    assert d.item() == pytest.approx(2.0) and s.item() == pytest.approx(1.0)


def test_cost_volume_peaks_at_the_shift() -> None:
    net = StereoNet(StereoNetSpec(max_disparity=16, stride=1, feature_channels=4, refine_stride=1))
    fr = torch.randn(1, 4, 8, 40)
    fl = torch.roll(fr, 5, -1)  # left(x) = right(x - 5)
    cv = net.cost_volume(fl, fr).mean(1)[0, :, :, 16:]  # away from the wrapped border
    assert int(cv.mean((1, 2)).argmax()) == 5


def test_warp_right_reproduces_the_left_image_at_the_true_disparity() -> None:
    right = torch.rand(1, 3, 4, 20)
    left = torch.roll(right, 3, -1)
    w = warp_right(right, torch.full((1, 1, 4, 20), 3.0))
    assert torch.allclose(w[..., 3:], left[..., 3:], atol=1e-5)


def test_loss_hand_case() -> None:
    gt = torch.tensor([[[[2.0, 4.0, 0.0, 60.0]]]])  # the last two: no GT / beyond max_disparity
    out = {"disparity": gt + torch.tensor([0.5, 2.0, 9.0, 9.0]), "coarse": gt.clone()}
    loss, parts = stereo_loss(out, gt, max_disparity=48, rel_weight=1.0, coarse_weight=0.5)
    # smooth-L1 (beta 1): 0.5 * 0.5^2 = 0.125 and 2 - 0.5 = 1.5; relative: 0.5 / 2, 2 / 4
    assert parts["fine"].item() == pytest.approx((0.125 + 1.5 + 0.25 + 0.5) / 2)
    assert parts["coarse"].item() == 0.0 and loss.item() == pytest.approx(parts["fine"].item())


@pytest.mark.integration  # trains a network (make test runs it, test-fast does not)
def test_tiny_network_overfits_a_shifted_texture() -> None:
    torch.manual_seed(0)
    h, w, d = 8, 48, 6.0
    tex = torch.nn.functional.avg_pool2d(torch.rand(1, 3, h, w + 8), 3, 1, 1)
    left, right = tex[..., :w], tex[..., int(d) : int(d) + w]  # left(x) = right(x - d)
    gt = torch.full((1, 1, h, w), d)
    gt[..., : int(d) + 1] = 0.0  # no match at the left border
    net = StereoNet(TINY)
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    for _ in range(150):
        loss, _ = stereo_loss(net(left, right), gt, max_disparity=16)
        opt.zero_grad()
        loss.backward()
        opt.step()
    net.eval()
    with torch.no_grad():
        pred = net(left, right)["disparity"]
    epe = (pred - gt).abs()[gt > 0].mean().item()
    assert epe < 0.5


def test_predict_pads_to_the_stride_and_crops_back() -> None:
    net = StereoNet(TINY)
    img = (np.random.default_rng(0).random((3, 30, 62, 3)) * 255).astype(np.uint8)
    d, s = predict(net, img, img, batch_size=2)
    assert d.shape == s.shape == (3, 30, 62) and d.dtype == s.dtype == np.float32
    assert to_input(img).shape == (3, 3, 30, 62)


def test_calibrate_spread_threshold_keeps_the_density_and_tables_the_deciles() -> None:
    rng = np.random.default_rng(0)
    gt = rng.uniform(1, 40, (2, 20, 50)).astype(np.float32)
    spread = rng.uniform(0, 3, gt.shape).astype(np.float32)
    disp = gt + spread * rng.choice([-1, 1], gt.shape)  # error = spread
    thr, table = calibrate_spread(disp, spread, gt, 0.8, 48)
    assert thr == pytest.approx(np.quantile(spread, 0.8), rel=1e-6)
    assert table["spread_kept/density"] == pytest.approx(0.8, abs=1e-3)
    epe = [table[f"spread_decile{i}/epe"] for i in range(10)]
    assert np.all(np.diff(epe) > 0)  # the error rises with the spread
    assert table["spread_kept/epe"] < table["spread_dropped/epe"]


@pytest.mark.parametrize(
    "change, match",
    [
        ({"stride": 3}, "stride must be 1, 2 or 4"),
        ({"max_disparity": 18, "stride": 4}, "multiple of stride"),
        ({"feature_channels": 10}, "multiple of groups"),
        ({"refine_dilations": ()}, "refine_dilations"),
        ({"stride": 1, "refine_stride": 2}, "refine_stride"),
        ({"base": "sad"}, "base must be one of"),
        ({"max_residual_px": 0.0}, "max_residual_px"),
        ({"local_cost_offsets": 17}, "local_cost_offsets"),
        ({"local_cost_step_px": 0.0}, "local_cost_step_px"),
        ({"local_cost_window": 6}, "local_cost_window must be an odd integer"),
    ],
)
def test_spec_bounds(change: dict, match: str) -> None:
    base = {**TINY.as_dict(), **change}
    with pytest.raises(ValueError, match=match):
        StereoNetSpec.from_dict(base)


SGM_TINY = StereoNetSpec(
    base="sgm", refine_channels=8, refine_dilations=(1, 2), refine_stride=1, max_residual_px=1.0
)
#: the local sub-pixel search around SGM: 9 offsets in 0.25 px steps, a 7 x 7 cost window
SEARCH_TINY = StereoNetSpec(
    base="sgm",
    refine_channels=4,
    refine_dilations=(1,),
    refine_stride=1,
    max_residual_px=0.5,
    local_cost_offsets=4,
    local_cost_step_px=0.25,
    local_cost_window=7,
)


def _sgm_pair(h: int = 16, w: int = 48, d: float = 5.0, bias: float = 0.3):
    """A texture shifted by ``d`` px, its exact disparity and an "SGM" of ``d + bias`` with an
    invalid (-1) left border and a few invalid holes."""
    torch.manual_seed(0)
    tex = torch.nn.functional.avg_pool2d(torch.rand(1, 3, h, w + 8), 3, 1, 1)
    left, right = tex[..., :w], tex[..., int(d) : int(d) + w]
    gt = torch.full((1, 1, h, w), d)
    gt[..., : int(d) + 1] = 0.0
    sgm = gt + bias
    sgm[..., : int(d) + 1] = -1.0
    sgm[..., 4:6, 20:24] = -1.0
    return left, right, gt, sgm


def test_untrained_sgm_mode_returns_sgm_exactly() -> None:
    left, right, _, sgm = _sgm_pair()
    net = StereoNet(SGM_TINY).eval()
    with torch.no_grad():
        out = net(left, right, sgm)
    assert torch.equal(out["disparity"], sgm)  # valid pixels unchanged, invalid stay -1
    assert torch.all(out["spread"] == 0)
    d, s = predict(
        net,
        (left[0].permute(1, 2, 0).numpy()[None] * 255).astype(np.uint8),
        (right[0].permute(1, 2, 0).numpy()[None] * 255).astype(np.uint8),
        sgm=sgm[:, 0].numpy(),
    )
    assert np.array_equal(d, sgm[:, 0].numpy()) and np.all(s == 0)
    with pytest.raises(ValueError, match="SGM disparity"):
        net(left, right)


def test_sgm_mode_residual_is_bounded_and_invalid_pixels_stay_invalid() -> None:
    left, right, _, sgm = _sgm_pair()
    net = StereoNet(SGM_TINY).eval()
    torch.nn.init.constant_(net.refine_out.bias, 50.0)  # a saturated residual
    with torch.no_grad():
        out = net(left, right, sgm)
    valid = sgm >= 0
    res = out["disparity"][valid] - sgm[valid]
    assert res.max().item() <= 1.0 + 1e-5 and res.max().item() > 0.99
    assert torch.all(out["disparity"][~valid] == -1.0)
    assert torch.all(out["spread"] <= 1.0 + 1e-5)


@pytest.mark.integration  # trains a network (make test runs it, test-fast does not)
def test_tiny_sgm_refiner_removes_a_subpixel_bias() -> None:
    left, right, gt, sgm = _sgm_pair(bias=0.3)
    net = StereoNet(SGM_TINY)
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    m = (gt > 0) & (sgm >= 0)

    def epe() -> float:
        with torch.no_grad():
            return (net(left, right, sgm)["disparity"] - gt).abs()[m].mean().item()

    assert epe() == pytest.approx(0.3, abs=1e-5)
    for _ in range(40):
        loss, _ = stereo_loss(
            net(left, right, sgm), torch.where(sgm >= 0, gt, 0.0), max_disparity=16
        )
        opt.zero_grad()
        loss.backward()
        opt.step()
    net.eval()
    assert epe() < 0.1


def _smooth_pair(d: float, h: int = 24, w: int = 64):
    """A smooth texture (a few sinusoids per colour, values in [0, 1]) seen by two eyes at an exact
    fractional disparity ``d`` px: ``left(x) = right(x - d)``."""
    y, x = torch.meshgrid(
        torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij"
    )

    def tex(u: torch.Tensor) -> torch.Tensor:
        chans = [
            0.5
            + 0.2 * torch.sin(0.71 * u + 0.3 * y + c)
            + 0.15 * torch.cos(0.37 * u - 0.45 * y + 2 * c)
            for c in range(3)
        ]
        return torch.stack(chans)[None].float()

    return tex(x), tex(x + d)


def test_local_costs_are_smallest_at_the_true_shift() -> None:
    left, right = _smooth_pair(5.5)
    offsets = torch.arange(-4, 5, dtype=torch.float32) * 0.25  # -1 .. 1 px
    cost = local_costs(left, right, torch.full((1, 1, 24, 64), 5.0), offsets)
    assert cost.shape == (1, 9, 24, 64)
    inner = cost[..., 8:-8].mean((0, 2, 3))  # away from the repeated border
    assert int(inner.argmin()) == 6  # offset +0.5 px: 5.0 + 0.5 = the true 5.5
    assert inner[6].item() < 0.01 < inner[4].item()  # near zero at the truth, clearly above at 5.0


def test_untrained_local_search_finds_the_subpixel_disparity_sgm_missed() -> None:
    """Before any training, the local search is a classical one (box-aggregated cost, soft-argmin):
    an SGM estimate locked at 5 px for a true 5.3 px moves to within 0.1 px of it; the spread stays
    below the search's half-width (the threshold that keeps every SGM pixel)."""
    left, right = _smooth_pair(5.3)
    sgm = torch.full((1, 1, 24, 64), 5.0)
    sgm[..., :6] = -1.0
    spec = SEARCH_TINY
    net = StereoNet(spec).eval()
    with torch.no_grad():
        out = net(left, right, sgm)
    inner = out["disparity"][..., 8:-8, 12:-8]
    assert (inner - 5.3).abs().max().item() < 0.1
    assert torch.all(out["disparity"][..., :6] == -1.0)
    assert spec.sgm_spread_bound_px == 1.0
    assert torch.all(out["spread"] <= spec.sgm_spread_bound_px) and out["spread"].max() > 0


def test_local_search_gradients_stay_finite_when_its_distribution_is_one_hot() -> None:
    left, right = _smooth_pair(5.3)
    sgm = torch.full((1, 1, 24, 64), 5.0)
    net = StereoNet(dataclasses.replace(SEARCH_TINY, local_cost_offsets=2, local_cost_window=3))
    with torch.no_grad():
        net.cost_log_scale.fill_(30.0)  # exp(30) x cost: every pixel's distribution one-hot
    out = net(left, right, sgm)
    assert out["spread"].median().item() == 0.0  # one-hot: a zero spread, sqrt(0)
    loss, _ = stereo_loss(out, torch.full_like(sgm, 5.3), max_disparity=16)
    loss.backward()
    assert all(torch.isfinite(q.grad).all() for q in net.parameters() if q.grad is not None)
