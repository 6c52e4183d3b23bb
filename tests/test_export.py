"""`traffictwin export`: TorchScript files whose outputs match the eager networks."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from _cli_models import CELL, H, W, save_fusion_model, save_risk

from traffictwin import cli, export
from traffictwin.evidential.masses import evidence_to_masses
from traffictwin.fusion.model_io import load_fusion_model
from traffictwin.risk.dave2 import pack_input
from traffictwin.risk.model_io import load_risk_model


def test_fusion_export_matches_the_eager_network(tmp_path, capsys):
    d = save_fusion_model(tmp_path / "m")
    out = tmp_path / "fusion.pt"
    assert cli.main(["export", "fusion", "--model", str(d), "-o", str(out)]) == 0
    assert json.loads(capsys.readouterr().out)["output"] == str(out)
    module, meta = export.load(out)
    assert meta["problem"] == "fusion" and meta["grid"] == {"rows": H, "cols": W, "cell": CELL}
    assert meta["source"] == str(d)
    net = load_fusion_model(d)
    x = torch.from_numpy(np.random.default_rng(0).dirichlet([1, 1, 1], size=(3, 2, H, W))[..., :2])
    x = x.permute(0, 1, 4, 2, 3).reshape(3, 4, H, W).float()  # (m_F1, m_O1, m_F2', m_O2')
    with torch.no_grad():
        m, u = evidence_to_masses(net(x))
        got = module(x)
    assert got.shape == (3, 3, H, W)
    torch.testing.assert_close(got[:, :2], m, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(got[:, 2], u, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(got.sum(1), torch.ones(3, H, W), rtol=0, atol=1e-5)


@pytest.mark.parametrize("use_speed", [False, True])
def test_risk_export_matches_the_eager_network(tmp_path, use_speed, capsys):
    d = save_risk(tmp_path / "m", use_speed=use_speed)
    out = tmp_path / "risk.pt"
    assert cli.main(["export", "risk", "--model", str(d), "-o", str(out)]) == 0
    capsys.readouterr()
    module, meta = export.load(out)
    net = load_risk_model(d).net
    cfg = net.cfg
    assert meta["problem"] == "risk" and meta["config"] == cfg.to_dict()
    g = torch.Generator().manual_seed(1)
    x = torch.rand(4, cfg.in_channels, cfg.height, cfg.width, generator=g) * 2 - 1
    speed = torch.tensor([0.0, 5.0, 12.5, 25.0]) if use_speed else None
    with torch.no_grad():
        want = net(x, speed)
        got = module(pack_input(cfg, x, speed))
    assert got.shape == (4,)
    assert ((want > 0) & (want < 1)).any(), "all outputs clamped: the comparison would be vacuous"
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)


def test_export_refuses_an_existing_file(tmp_path, capsys):
    d = save_risk(tmp_path / "m")
    out = tmp_path / "risk.pt"
    out.write_bytes(b"old")
    assert cli.main(["export", "risk", "--model", str(d), "-o", str(out)]) == 1
    err = capsys.readouterr().err  # no previous export: --force would not replace it either
    assert "not a previous .pt output" in err and "--force" not in err
    assert out.read_bytes() == b"old"
