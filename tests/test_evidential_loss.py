"""Evidence -> masses, the loss of eqs. (6)-(7), the KL regulariser and the torch fusion metrics."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import composed

from traffictwin.fusion.losses import (
    confusion_counts,
    dice_from_counts,
    evidence_to_masses,
    evidential_loss,
    evidential_loss_map,
    kl_dirichlet_uniform,
    kld,
    kld_full,
    pignistic_occupied,
)

pytestmark = pytest.mark.usefixtures("single_torch_thread")


def cell(a: float, b: float) -> torch.Tensor:
    """A 1-cell map (1, 2, 1, 1) with channel values (a, b)."""
    return torch.tensor([a, b], dtype=torch.float64).reshape(1, 2, 1, 1)


def test_evidence_to_masses_hand_case() -> None:
    # e = (2, 1): alpha = (3, 2), S = 5, m = (0.4, 0.2), u = 2/5
    m, u = evidence_to_masses(cell(2.0, 1.0))
    assert torch.allclose(m.flatten(), torch.tensor([0.4, 0.2], dtype=torch.float64))
    assert u.shape == (1, 1, 1) and math.isclose(float(u), 0.4)
    m0, u0 = evidence_to_masses(cell(0.0, 0.0))  # no evidence: fully unknown
    assert float(m0.abs().sum()) == 0.0 and float(u0) == 1.0


def test_masses_plus_u_is_one_and_numpy_matches_torch() -> None:
    e = torch.relu(torch.randn(3, 2, 5, 4, generator=torch.Generator().manual_seed(0)) * 10)
    m, u = evidence_to_masses(e)
    assert torch.allclose(m.sum(-3) + u, torch.ones_like(u), atol=1e-6)
    assert torch.all(m >= 0) and torch.all(u > 0) and torch.all(u <= 1)
    mn, un = evidence_to_masses(e.numpy())
    assert isinstance(mn, np.ndarray) and np.allclose(mn, m.numpy()) and np.allclose(un, u.numpy())
    with pytest.raises(ValueError, match=">= 0"):
        evidence_to_masses(-e.numpy() - 1)
    with pytest.raises(ValueError, match="channels"):
        evidence_to_masses(np.zeros((3, 4, 4)))


def test_loss_hand_computed_one_cell() -> None:
    # e = (2, 1): p = alpha/S = (0.6, 0.4), S = 5, variance terms p(1-p)/(S+1) = 0.24/6 = 0.04 each
    e = cell(2.0, 1.0)
    # y = (0.7, 0.2): (0.1)^2 + 0.04 + (0.2)^2 + 0.04 = 0.13, y_O <= 0.5 -> weight 1
    assert math.isclose(
        float(evidential_loss(e, cell(0.7, 0.2), occupied_weight=3.0)), 0.13, rel_tol=1e-12
    )
    # y = (0.1, 0.8): (0.5)^2 + 0.04 + (0.4)^2 + 0.04 = 0.49, y_O > 0.5 -> x o_w = 3
    assert math.isclose(
        float(evidential_loss(e, cell(0.1, 0.8), occupied_weight=3.0)), 1.47, rel_tol=1e-12
    )


def test_occupied_weight_only_where_label_occupied() -> None:
    # three cells: y_O = 0.9 (occupied), 0.5 (boundary: not > 0.5), 0.0
    y = torch.tensor([[0.05, 0.4, 0.9], [0.9, 0.5, 0.0]], dtype=torch.float64).reshape(1, 2, 1, 3)
    e = torch.tensor([[1.0, 2.0, 3.0], [0.5, 1.0, 0.0]], dtype=torch.float64).reshape(1, 2, 1, 3)
    l1 = evidential_loss_map(e, y, occupied_weight=1.0)
    l3 = evidential_loss_map(e, y, occupied_weight=3.0)
    ratio = (l3 / l1).flatten().tolist()
    assert ratio == pytest.approx([3.0, 1.0, 1.0])
    assert float(evidential_loss(e, y, 3.0)) == pytest.approx(float(l3.mean()))


def test_loss_gradient_finite_including_zero_evidence() -> None:
    logits = torch.randn(2, 2, 8, 6, generator=torch.Generator().manual_seed(3), requires_grad=True)
    e = torch.relu(logits * 5)
    y = torch.rand(2, 2, 8, 6, generator=torch.Generator().manual_seed(4)) / 2
    loss = evidential_loss(e, y, 3.0, kl_weight=0.5)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(logits.grad).all()


def test_kl_regulariser_hand_case_and_off_by_default() -> None:
    # KL(Dir(2,1) || Dir(1,1)) = ln G(3) - ln G(2) - ln G(2) - ln G(1) + (psi(2) - psi(3)) = ln 2 - 1/2
    alpha = cell(2.0, 1.0)
    assert float(kl_dirichlet_uniform(alpha)) == pytest.approx(math.log(2) - 0.5, rel=1e-9)
    assert float(kl_dirichlet_uniform(cell(1.0, 1.0))) == pytest.approx(0.0, abs=1e-12)
    e, y = cell(2.0, 1.0), cell(0.7, 0.2)
    assert float(evidential_loss(e, y)) == pytest.approx(0.13)  # default: no KL term
    # alpha~ = y + (1 - y) alpha = (0.7 + 0.3*3, 0.2 + 0.8*2) = (1.6, 1.8)
    kl = float(kl_dirichlet_uniform(cell(1.6, 1.8)))
    assert float(evidential_loss(e, y, kl_weight=0.5)) == pytest.approx(0.13 + 0.5 * kl)


def test_shape_mismatch_is_rejected() -> None:
    with pytest.raises(ValueError, match="shape"):
        evidential_loss(torch.zeros(1, 2, 4, 4), torch.zeros(1, 2, 4, 5))


def test_kld_hand_cases() -> None:
    # (a) y = (0.7, 0.2), p = (0.4, 0.2): 0.7 ln(0.7/0.4) + 0.2 ln 1
    y, p = cell(0.7, 0.2), cell(0.4, 0.2)
    assert float(kld(p, y)) == pytest.approx(0.7 * math.log(0.7 / 0.4))
    # (b) adds u: y_u = 0.1, p_u = 0.4
    assert float(kld_full(p, y)) == pytest.approx(
        0.7 * math.log(0.7 / 0.4) + 0.1 * math.log(0.1 / 0.4)
    )
    # clipping: label 0 vs pred 0 -> eps ln(eps/eps) = 0, no NaN
    assert float(kld(cell(0.0, 0.0), cell(0.0, 0.0))) == 0.0


def test_torch_metrics_match_numpy_evaluation_metrics() -> None:
    """Same definitions as the fusion-eval numpy metrics (docs/design.md 'Fusion metrics')."""
    from traffictwin.fusion import metrics as fm

    g = np.random.default_rng(0)
    raw = g.random((3, 3, 16, 12))
    raw[:, :, :4] = 0.0  # some all-unknown cells
    raw /= raw.sum(1, keepdims=True) + 1e-12
    lab = raw[:, :2].astype(np.float64)
    e = g.exponential(2.0, (3, 2, 16, 12)) * (g.random((3, 1, 16, 12)) > 0.2)
    pred, _ = evidence_to_masses(e)
    np.testing.assert_allclose(
        kld(torch.from_numpy(pred), torch.from_numpy(lab)).numpy(), fm.kld_fo(lab, pred), rtol=1e-9
    )
    np.testing.assert_allclose(
        kld_full(torch.from_numpy(pred), torch.from_numpy(lab)).numpy(),
        fm.kld_fou(lab, pred),
        rtol=1e-9,
    )
    c = fm.confusion_counts(lab, pred)
    ours = confusion_counts(torch.from_numpy(pred), torch.from_numpy(lab)).tolist()
    keys = ["tp_occ", "fp_occ", "fn_occ", "tp_free", "fp_free", "fn_free"]
    assert ours == [float(c[k].sum()) for k in keys]


def test_pignistic_and_dice_hand_case() -> None:
    # cells: pred (m_F, m_O) -> p_O: (0.1, 0.8) -> 0.85 occ; (0.7, 0.1) -> 0.2 free; (0, 0) -> 0.5 neither;
    #        (0.2, 0.6) -> 0.7 occ
    pred = torch.tensor([[0.1, 0.7, 0.0, 0.2], [0.8, 0.1, 0.0, 0.6]]).reshape(1, 2, 1, 4)
    # labels: occ, occ, free, free  (known: y_O > 0.5 or y_F > 0.5)
    lab = torch.tensor([[0.0, 0.1, 0.9, 0.6], [0.9, 0.8, 0.0, 0.3]]).reshape(1, 2, 1, 4)
    assert pignistic_occupied(pred).flatten().tolist() == pytest.approx([0.85, 0.2, 0.5, 0.7])
    c = confusion_counts(pred, lab).tolist()
    # occ: TP cell0, FP cell3, FN cell1 ; free: TP 0, FP cell1, FN cells 2, 3
    assert c == [1, 1, 1, 0, 1, 2]
    d = dice_from_counts(torch.tensor(c, dtype=torch.float64))
    assert d["dice_occ"] == pytest.approx(2 / 4) and d["dice_free"] == 0.0
    assert d["precision_occ"] == 0.5 and d["recall_occ"] == 0.5
    assert math.isnan(dice_from_counts(torch.zeros(6, dtype=torch.float64))["dice_occ"])


def test_confusion_counts_metric_sums_batches_like_the_function() -> None:
    from traffictwin.fusion.losses import ConfusionCounts, confusion_counts

    g = torch.Generator().manual_seed(3)
    metric = ConfusionCounts()
    total = torch.zeros(6, dtype=torch.float64)
    for _ in range(3):
        raw = torch.rand(2, 3, 8, 6, generator=g)
        m = (raw / raw.sum(1, keepdim=True))[:, :2]
        lab = torch.zeros(2, 2, 8, 6)
        lab[:, 1, :4] = 0.9
        lab[:, 0, 5:] = 0.8
        metric.update(m, lab)
        total += confusion_counts(m, lab)
    assert metric.compute().dtype == torch.float64
    assert torch.equal(metric.compute(), total) and total.sum() > 0
    metric.reset()
    assert torch.equal(metric.compute(), torch.zeros(6, dtype=torch.float64))


# ---------------------------------------------------------------------------------------------
# the loss choice (fusion_model.loss.name)


def test_mass_loss_hand_computed_one_cell() -> None:
    from traffictwin.fusion.losses import mass_loss_map

    # e = (3, 1): S = 6, m = (1/2, 1/6), u = 1/3; label y = (0.5, 0.25), y_u = 0.25
    # KL = 0.5 ln(0.5/0.5) + 0.25 ln(0.25/(1/6)) + 0.25 ln(0.25/(1/3))
    expect = 0.25 * math.log(1.5) + 0.25 * math.log(0.75)
    assert float(mass_loss_map(cell(3, 1), cell(0.5, 0.25))) == pytest.approx(expect, rel=1e-9)
    # o_w multiplies cells whose label is occupied only
    assert float(mass_loss_map(cell(3, 1), cell(0.1, 0.6), occupied_weight=3.0)) == pytest.approx(
        3.0 * float(mass_loss_map(cell(3, 1), cell(0.1, 0.6)))
    )


def test_mass_loss_is_zero_at_the_label_and_equals_the_kld_full_metric() -> None:
    from traffictwin.fusion.losses import kld_full, log_masses, mass_loss_map

    # the evidence whose masses equal the label: e_k = 2 y_k / y_u
    y = torch.tensor([0.6, 0.3], dtype=torch.float64).reshape(1, 2, 1, 1)
    e = 2 * y / 0.1
    assert float(mass_loss_map(e, y)) == pytest.approx(0.0, abs=1e-12)
    g = torch.Generator().manual_seed(0)
    e = torch.rand(2, 2, 5, 4, generator=g, dtype=torch.float64) * 5
    ya = torch.rand(2, 3, 5, 4, generator=g, dtype=torch.float64)
    ya = (ya / ya.sum(1, keepdim=True))[:, :2]
    m = torch.exp(log_masses(e))[:, :2]
    assert float(mass_loss_map(e, ya).mean(dim=(-2, -1)).mean()) == pytest.approx(
        float(kld_full(m, ya).mean()), rel=1e-6
    )


def test_log_masses_finite_and_gradient_alive_at_zero_and_huge_evidence() -> None:
    from traffictwin.fusion.losses import log_masses, mass_loss_map

    leaf = torch.tensor([0.0, 1e12], dtype=torch.float64, requires_grad=True)
    e = leaf.reshape(1, 2, 1, 1)
    lm = log_masses(e)
    assert torch.isfinite(lm).all()
    assert torch.allclose(torch.exp(lm).sum(-3), torch.ones(1, 1, 1, dtype=torch.float64))
    mass_loss_map(e, cell(0.3, 0.3)).sum().backward()
    assert torch.isfinite(leaf.grad).all() and float(leaf.grad.abs().sum()) > 0


def _old_fusion_loss(name, e, y, occupied_weight, kl_weight, kl_anneal_epochs, epoch):
    """The losses as chosen by name before the registry (an if-chain; the module's annealing)."""
    from traffictwin.fusion.losses import mass_loss_map

    w = 0.0
    if name == "paper_kl" and kl_weight > 0 and epoch is not None:
        w = kl_weight * min(1.0, epoch / max(1, kl_anneal_epochs))
    if name == "mass":
        return mass_loss_map(e, y, occupied_weight).mean()
    return evidential_loss(e, y, occupied_weight, w if name == "paper_kl" else 0.0)


def test_registered_losses_hand_computed_and_bit_identical_to_the_if_chain() -> None:
    from scipy.special import digamma

    from traffictwin.fusion.loss_registry import LOSSES
    from traffictwin.fusion.losses import fusion_loss

    assert tuple(LOSSES) == ("mass", "paper", "paper_kl")
    # one cell, e = (3, 1): alpha = (4, 2), S = 6, p = (2/3, 1/3); label y = (0.1, 0.6): occupied
    e, y = cell(3, 1), cell(0.1, 0.6)
    mass = 0.1 * math.log(0.1 / 0.5) + 0.6 * math.log(0.6 / (1 / 6)) + 0.3 * math.log(0.3 / (1 / 3))
    eq7 = (0.1 - 2 / 3) ** 2 + (0.6 - 1 / 3) ** 2 + (2 / 9 + 2 / 9) / 7
    at = np.array([0.1 + 0.9 * 4, 0.6 + 0.4 * 2])  # alpha~ = y + (1 - y) alpha
    kl = (
        math.lgamma(at.sum())
        - math.lgamma(2.0)
        - sum(math.lgamma(a) for a in at)
        + float(((at - 1) * (digamma(at) - digamma(at.sum()))).sum())
    )
    s = {"occupied_weight": 3.0, "kl_weight": 0.5, "kl_anneal_epochs": 4}
    mass_s, paper_s = {"occupied_weight": 2.0}, {"occupied_weight": 3.0}
    assert float(fusion_loss("mass", e, y, mass_s)) == pytest.approx(2.0 * mass, rel=1e-12)
    assert float(fusion_loss("paper", e, y, paper_s, epoch=9)) == pytest.approx(3 * eq7, rel=1e-12)
    for epoch, w in ((None, 0.0), (0, 0.0), (2, 0.25), (9, 0.5)):  # ramp 0.5 * min(1, epoch / 4)
        got = float(fusion_loss("paper_kl", e, y, s, epoch=epoch))
        assert got == pytest.approx(3 * eq7 + w * kl, rel=1e-12), epoch
    # a float32 batch as in training: every loss, every epoch, the same bits as the if-chain
    g = torch.Generator().manual_seed(0)
    eb = torch.rand(2, 2, 5, 4, generator=g) * 5
    yb = torch.rand(2, 3, 5, 4, generator=g)
    yb = (yb / yb.sum(1, keepdim=True))[:, :2]
    for name, settings in (("mass", mass_s), ("paper", paper_s), ("paper_kl", s)):
        for epoch in (None, 0, 1, 3, 4, 7):
            old = _old_fusion_loss(name, eb, yb, **{**s, **settings}, epoch=epoch)
            new = fusion_loss(name, eb, yb, LOSSES[name].settings(**settings), epoch)
            assert torch.equal(new, old), (name, epoch)
    with pytest.raises(ValueError, match="unknown fusion loss 'focal'"):
        fusion_loss("focal", e, y, {"occupied_weight": 1.0})


def test_a_registered_toy_loss_is_selectable_by_config_alone() -> None:
    """One settings dataclass, one function and one registration: the config check, a variant's
    loss and the training module's loss accept it, no other file touched."""
    from dataclasses import dataclass

    from traffictwin.config import ConfigError, spec, typed
    from traffictwin.fusion.config import fusion_variants
    from traffictwin.fusion.loss_registry import register_loss, unregister_loss
    from traffictwin.fusion.losses import fusion_loss
    from traffictwin.fusion.model_config import FusionModelConfig

    @dataclass
    class Toy:
        scale: float = spec(min=0.0)

    def toy_loss(e, y, s: Toy, epoch=None):
        return s.scale * (e - y).abs().mean()

    cfg = composed()
    node = cfg["fusion_model"]
    node["loss"] = {**node["loss"], "name": "toy", "toy": {"scale": 2.0}}
    with pytest.raises(ConfigError, match="'fusion_model.loss.toy': Key 'toy' not in"):
        typed(node, FusionModelConfig, key="fusion_model")  # not registered: neither name nor block
    register_loss("toy", "a test loss", settings=Toy, fn=toy_loss)
    try:
        model = typed(node, FusionModelConfig, key="fusion_model")
        hp = model.hparams()
        assert (hp.loss, hp.loss_settings) == ("toy", {"scale": 2.0})
        e, y = cell(3, 1), cell(0.1, 0.6)
        assert float(fusion_loss("toy", e, y, hp.loss_settings)) == pytest.approx(
            2 * (2.9 + 0.4) / 2
        )
        bad = {**node, "loss": {**node["loss"], "toy": {"scale": -1.0}}}
        with pytest.raises(ConfigError, match="'fusion_model.loss.toy.scale' must be >= 0.0"):
            typed(bad, FusionModelConfig, key="fusion_model")
        bad = {**node, "loss": {**node["loss"], "toy": {"scale": 1.0, "typo": 1}}}
        with pytest.raises(ConfigError, match="'fusion_model.loss.toy.typo'"):
            typed(bad, FusionModelConfig, key="fusion_model")
        cfg["fusion_variants"] = {"t": {"config": "mixed", "inputs": "prealigned", "loss": "toy"}}
        assert fusion_variants(cfg)["t"].loss == "toy"
    finally:
        unregister_loss("toy")
    with pytest.raises(ConfigError, match="unknown fusion loss 'toy'"):
        model.hparams("toy")
