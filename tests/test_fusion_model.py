"""Plain-torch ResNet / DeepLabV3+: shapes, output stride, evidences, parameter counts."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import composed

from traffictwin.fusion.deeplab import (
    RESIDUAL_EPS,
    DeepLabSpec,
    DeepLabV3Plus,
    channels_last_supported,
    count_parameters,
)
from traffictwin.fusion.losses import evidence_to_masses
from traffictwin.fusion.resnet import ResNet, ResNetSpec, resnet_spec
from traffictwin.fusion.training import spec_from_cfg

pytestmark = pytest.mark.usefixtures("single_torch_thread")

# the residual head floors Dempster's masses and u at RESIDUAL_EPS before their logs: its
# untrained output equals Dempster's to about twice the floor
FLOOR_TOL = 2 * RESIDUAL_EPS


def tiny_spec(**kw) -> DeepLabSpec:
    return DeepLabSpec(
        backbone=ResNetSpec(block="basic", layers=(1, 1, 1, 1), base_width=8),
        aspp_channels=16,
        low_level_channels=8,
        decoder_channels=16,
        **kw,
    )


@pytest.mark.parametrize("hw", [(256, 176), (128, 96)])
def test_output_shape_equals_input_shape_and_evidence_nonnegative(hw) -> None:
    torch.manual_seed(0)
    net = DeepLabV3Plus(tiny_spec()).eval()
    x = torch.rand(2, 4, *hw)
    with torch.no_grad():
        e = net(x)
    assert e.shape == (2, 2, *hw)
    assert torch.all(e >= 0)
    m, u = evidence_to_masses(e)
    assert torch.allclose(m.sum(1) + u, torch.ones_like(u), atol=1e-6)


def test_default_profile_network_shape_at_paper_grid() -> None:
    spec = spec_from_cfg(
        {
            "backbone": {
                "block": "basic",
                "layers": [2, 2, 2, 2],
                "base_width": 16,
                "output_stride": 16,
            },
            "aspp_channels": 64,
            "low_level_channels": 24,
            "decoder_channels": 64,
        }
    )
    net = DeepLabV3Plus(spec).eval()
    with torch.no_grad():
        e = net(torch.rand(1, 4, 256, 176))
    assert e.shape == (1, 2, 256, 176) and torch.all(e >= 0)


def test_resnet50_backbone_matches_torchvision_parameter_count() -> None:
    # torchvision resnet50 has 25,557,032 parameters, 2,049,000 of them in the 1000-way fc layer;
    # resnet18: 11,689,512 incl. 513,000 in fc. Same layout with 3 input channels here.
    assert count_parameters(ResNet(resnet_spec(50, in_channels=3))) == 25_557_032 - 2_049_000
    assert count_parameters(ResNet(resnet_spec(18, in_channels=3))) == 11_689_512 - 513_000


def test_resnet50_deeplab_parameter_count_in_expected_range() -> None:
    net = DeepLabV3Plus(DeepLabSpec(backbone=resnet_spec(50)))
    n = count_parameters(net)
    print(f"DeepLabV3+ ResNet-50 (4 in, 2 out): {n:,} parameters")
    # backbone 23.5 M + ASPP (2048->5x256, 3 atrous 3x3) ~15.4 M + decoder ~1.2 M
    assert 38_000_000 < n < 43_000_000


def test_resnet50_forward_shape_ci_grid() -> None:
    net = DeepLabV3Plus(DeepLabSpec(backbone=resnet_spec(50))).eval()
    with torch.no_grad():
        e = net(torch.rand(1, 4, 128, 96))
    assert e.shape == (1, 2, 128, 96) and torch.all(e >= 0)


def test_output_stride_16_dilates_last_stage() -> None:
    spec = resnet_spec(18, base_width=8)
    assert spec.output_stride == 16
    bb = ResNet(spec).eval()
    with torch.no_grad():
        low, high = bb(torch.rand(1, 4, 128, 96))
    assert low.shape == (1, 8, 32, 24)  # stride 4
    assert high.shape == (1, 64, 8, 6)  # stride 16, not 32
    assert bb.layer4[0].conv1.stride == (1, 1) and bb.layer4[1].conv2.dilation == (2, 2)
    assert ResNet(resnet_spec(50, base_width=8)).layer4[1].conv2.dilation == (2, 2)


def test_aspp_rates_and_low_level_projection() -> None:
    net = DeepLabV3Plus(
        DeepLabSpec(backbone=resnet_spec(18, base_width=8), aspp_channels=16, decoder_channels=16)
    )
    dil = [b[0].dilation for b in net.aspp.branches[1:4]]
    assert dil == [(6, 6), (12, 12), (18, 18)]
    assert net.low_proj[0].out_channels == 48  # DeepLabV3+ default


def test_indivisible_input_is_rejected() -> None:
    net = DeepLabV3Plus(tiny_spec()).eval()
    with pytest.raises(ValueError, match="divisible by the output stride 16"):
        net(torch.rand(1, 4, 100, 96))
    with pytest.raises(ValueError, match="channels"):
        net(torch.rand(1, 3, 128, 96))


def test_network_gradient_is_finite() -> None:
    from traffictwin.fusion.losses import evidential_loss

    torch.manual_seed(1)
    net = DeepLabV3Plus(tiny_spec())
    x = torch.rand(2, 4, 64, 48)
    y = torch.rand(2, 2, 64, 48) / 2
    loss = evidential_loss(net(x), y)
    loss.backward()
    grads = [p.grad for p in net.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)
    assert any(g.abs().sum() > 0 for g in grads)


def test_spec_round_trip_and_validation() -> None:
    s = spec_from_cfg(
        {
            "backbone": {
                "block": "bottleneck",
                "layers": [3, 4, 6, 3],
                "base_width": 64,
                "output_stride": 16,
            }
        }
    )
    assert DeepLabSpec.from_dict(s.as_dict()) == s
    with pytest.raises(ValueError, match="block"):
        spec_from_cfg({"backbone": {"block": "dense"}})
    with pytest.raises(ValueError, match="output_stride"):
        spec_from_cfg({"backbone": {"output_stride": 4}})


@pytest.mark.parametrize(
    ("block", "base_width", "ok"),
    [("basic", 4, False), ("basic", 8, True), ("bottleneck", 2, True), ("basic", 16, True)],
)
def test_channels_last_is_refused_for_strided_1x1_convs_with_few_input_channels(
    block: str, base_width: int, ok: bool
) -> None:
    # oneDNN 3.12 (torch 2.13 CPU) corrupts the heap in the weight gradient of a strided 1x1 NHWC conv
    # with 2..7 input channels: layer2's projection shortcut when a basic ResNet has base_width < 8
    spec = DeepLabSpec(
        backbone=ResNetSpec(block=block, layers=(1, 1, 1, 1), base_width=base_width),
        aspp_channels=8,
        low_level_channels=4,
        decoder_channels=8,
    )
    assert channels_last_supported(DeepLabV3Plus(spec)) is ok


def test_tiny_network_trains_with_channels_last_requested() -> None:
    from traffictwin.fusion.training import FusionLitModule

    spec = DeepLabSpec(
        backbone=ResNetSpec(block="basic", layers=(1, 1, 1, 1), base_width=4),
        aspp_channels=8,
        low_level_channels=4,
        decoder_channels=8,
    )
    module = FusionLitModule(spec.as_dict(), {"channels_last": True})
    assert not module.channels_last
    torch.manual_seed(0)
    module(torch.rand(4, 4, 64, 48)).sum().backward()
    assert all(p.grad is not None for p in module.net.parameters() if p.requires_grad)


def test_refinement_head_runs_at_full_resolution_and_sees_the_inputs() -> None:
    torch.manual_seed(0)
    net = DeepLabV3Plus(tiny_spec(refine_channels=8, refine_dempster=True, evidence="exp")).eval()
    assert net.refine is not None and net.refine[0].in_channels == 8 + 4 + 3
    x = torch.rand(1, 4, 64, 48) * 0.5
    with torch.no_grad():
        e = net(x)
        x2 = x.clone()
        x2[0, :, 30, 20] = torch.tensor([0.0, 0.9, 0.0, 0.9])  # one cell changed
        d = (net(x2) - e).abs().sum(1)[0]
    assert e.shape == (1, 2, 64, 48) and torch.all(e > 0)  # exp evidence is positive
    # the change reaches the output at its own cell (stride 1, not only through stride-4 features)
    assert d[30, 20] > 0 and d[30, 20] >= 0.5 * d.max()


def test_exp_evidence_is_bounded_and_spec_checks_the_head() -> None:
    spec = tiny_spec(evidence="exp")
    net = DeepLabV3Plus(spec).eval()
    with torch.no_grad():
        net.classifier.bias.fill_(1e4)  # a huge logit
        e = net(torch.rand(1, 4, 64, 48))
    assert torch.isfinite(e).all() and float(e.max()) <= math.exp(30.0) * 1.0001
    with pytest.raises(ValueError, match="evidence must be one of"):
        tiny_spec(evidence="softmax")
    with pytest.raises(ValueError, match="refine_dempster needs refine_channels > 0"):
        tiny_spec(refine_dempster=True)
    with pytest.raises(ValueError, match="refine_channels must be >= 0"):
        tiny_spec(refine_channels=-1)
    # the paper's network is the default: no head, ReLU evidence
    assert (DeepLabSpec().refine_channels, DeepLabSpec().evidence) == (0, "relu")
    assert DeepLabSpec.from_dict(tiny_spec(refine_channels=8).as_dict()).refine_channels == 8


# ---------------------------------------------------------------------------------------------
# the residual head on Dempster's combination


def _masses(n: int, h: int, w: int, gen: torch.Generator) -> torch.Tensor:
    """Random valid masses (m_F, m_O, u) >= 0 summing to 1, as (n, 2, h, w)."""
    p = torch.rand(n, 3, h, w, generator=gen) ** 3  # skewed: many near-certain cells
    p = p / p.sum(1, keepdim=True)
    return p[:, :2]


def test_zero_initialised_residual_head_equals_dempster_before_training() -> None:
    from traffictwin.evidential.dempster import dempster

    torch.manual_seed(0)
    gen = torch.Generator().manual_seed(3)
    x = torch.cat([_masses(2, 64, 48, gen), _masses(2, 64, 48, gen)], dim=1)
    # hand-computed cells (batch 0): agreeing maps, one side vacuous (u = 1), total conflict K = 1,
    # near-total conflict, both vacuous
    cells = {
        (10, 10): (
            [0.7, 0.1],
            [0.6, 0.2],
            [0.7 * 0.6 + 0.7 * 0.2 + 0.2 * 0.6, 0.1 * 0.2 + 0.1 * 0.2 + 0.2 * 0.2],
        ),
        (11, 10): ([0.0, 0.0], [0.3, 0.5], [0.3, 0.5]),
        (12, 10): ([1.0, 0.0], [0.0, 1.0], [0.0, 0.0]),
        (13, 10): ([0.999, 0.0], [0.0, 0.999], [0.999 * 0.001 / (2 * 0.999 * 0.001 + 1e-6)] * 2),
        (14, 10): ([0.0, 0.0], [0.0, 0.0], [0.0, 0.0]),
    }
    for (i, j), (a, b, _) in cells.items():
        x[0, :, i, j] = torch.tensor([*a, *b])
    for spec in (
        tiny_spec(evidence="exp", residual="dempster"),  # stride-4 head + x4 upsampling
        tiny_spec(refine_channels=8, refine_dempster=True, evidence="exp", residual="dempster"),
    ):
        net = DeepLabV3Plus(spec).train()  # BN in train mode: the correction is still exactly 0
        with torch.no_grad():
            m, u = evidence_to_masses(net(x))
        expected = dempster(x[:, :2], x[:, 2:])
        assert torch.allclose(m, expected, atol=FLOOR_TOL)
        assert torch.allclose(u, 1 - expected.sum(1), atol=FLOOR_TOL)
        k_agree = 0.7 * 0.2 + 0.1 * 0.6  # agreeing cell's conflict: its masses are renormalised
        for (i, j), (_, _, want) in cells.items():
            want = torch.tensor(want)
            if (i, j) == (10, 10):
                want = want / (1 - k_agree)
            assert torch.allclose(m[0, :, i, j], want, atol=FLOOR_TOL), (
                (i, j),
                m[0, :, i, j],
                want,
            )
        assert abs(float(u[0, 12, 10]) - 1.0) < FLOOR_TOL  # total conflict: vacuous, as dempster()


def test_residual_correction_receives_gradients_and_moves_the_output() -> None:
    from traffictwin.fusion.losses import fusion_loss

    torch.manual_seed(1)
    net = DeepLabV3Plus(tiny_spec(refine_channels=8, evidence="exp", residual="dempster"))
    gen = torch.Generator().manual_seed(4)
    x = torch.cat([_masses(2, 64, 48, gen), _masses(2, 64, 48, gen)], dim=1)
    y = _masses(2, 64, 48, gen)
    before = net(x).detach()
    fusion_loss("mass", net(x), y, {"occupied_weight": 1.0}).backward()
    last = net.refine[-1]
    assert float(last.weight.grad.abs().sum()) > 0 and float(last.bias.grad.abs().sum()) > 0
    assert all(torch.isfinite(p.grad).all() for p in net.parameters() if p.grad is not None)
    opt = torch.optim.SGD(net.parameters(), lr=0.1)
    opt.step()
    assert not torch.allclose(net(x).detach(), before)


def test_residual_spec_validation_round_trip_and_plain_ablation() -> None:
    with pytest.raises(ValueError, match="residual must be one of"):
        tiny_spec(evidence="exp", residual="gate")
    with pytest.raises(ValueError, match="residual 'dempster' needs evidence 'exp'"):
        tiny_spec(residual="dempster")  # ReLU evidence
    s = tiny_spec(refine_channels=8, evidence="exp", residual="dempster")
    assert s.as_dict()["residual"] == "dempster"
    assert DeepLabSpec.from_dict(s.as_dict()) == s
    # a model folder written before the option existed has no key: the plain network
    old = s.as_dict()
    del old["residual"]
    assert DeepLabSpec.from_dict(old).residual == "none"
    # the ablation flag builds the plain network: its last conv is not zero and its output is not Dempster's
    torch.manual_seed(0)
    plain = DeepLabV3Plus(tiny_spec(refine_channels=8, evidence="exp", residual="none"))
    assert float(plain.refine[-1].weight.abs().sum()) > 0
    assert DeepLabSpec().residual == "none"  # the paper's network is the spec default


@pytest.mark.parametrize("profile", ["ci", "default", "paper"])
def test_every_profile_builds_the_residual_network(profile: str) -> None:

    from traffictwin.config import typed
    from traffictwin.fusion.training import FusionModelConfig

    cfg = composed(f"profile={profile}")
    model_cfg = typed(cfg["fusion_model"], FusionModelConfig, key="fusion_model", source="conf")
    spec = model_cfg.deeplab_spec("conf")
    assert (spec.residual, spec.evidence) == ("dempster", "exp")
    if profile == "ci":  # small enough to run here: it starts as Dempster's rule
        from traffictwin.evidential.dempster import dempster

        net = DeepLabV3Plus(spec).eval()
        gen = torch.Generator().manual_seed(5)
        x = torch.cat([_masses(1, 128, 96, gen), _masses(1, 128, 96, gen)], dim=1)
        with torch.no_grad():
            m, _ = evidence_to_masses(net(x))
        assert torch.allclose(m, dempster(x[:, :2], x[:, 2:]), atol=FLOOR_TOL)
