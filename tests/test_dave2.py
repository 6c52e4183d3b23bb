"""DAVE-2-like risk network: shapes, parameter count, preprocessing, save/load."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from traffictwin.risk.dave2 import (
    Dave2,
    Dave2Config,
    PackedDave2,
    conv_output_shape,
    count_parameters,
    pack_input,
    prepare_channels,
    preprocess,
)
from traffictwin.risk.model_io import RiskModelError, load_risk_model, save_risk_model


def _expected_params(c_in: int, flat: int, speed: bool = False) -> int:
    conv = [(c_in, 24, 5), (24, 36, 5), (36, 48, 5), (48, 64, 3), (64, 64, 3)]
    n = sum(ci * co * k * k + co for ci, co, k in conv)
    fc = [(flat + int(speed), 1164), (1164, 100), (100, 50), (50, 10), (10, 1)]
    return n + sum(a * b + b for a, b in fc)


def test_shapes_and_parameter_count_66x200() -> None:
    m = Dave2(Dave2Config())
    # 66x200 -> 31x98 -> 14x47 -> 5x22 -> 3x20 -> 1x18 (x 64 channels)
    assert conv_output_shape(66, 200) == (64, 1, 18)
    assert m.flat_size == 64 * 18
    n = count_parameters(m)
    print(f"DAVE-2 risk net (rgb+disp, 66x200): {n:,} parameters")
    assert n == _expected_params(4, 1152)
    out = m(torch.randn(3, 4, 66, 200))
    assert out.shape == (3,) and torch.isfinite(out).all()


def test_other_resolution_and_channels_adapt_first_fc() -> None:
    cfg = Dave2Config(inputs=("rgb",), height=120, width=320)
    m = Dave2(cfg)
    c, h, w = conv_output_shape(120, 320)
    assert (c, h, w) == (
        64,
        8,
        33,
    )  # 120 -> 58 -> 27 -> 12 -> 10 -> 8; 320 -> 158 -> 77 -> 37 -> 35 -> 33
    assert m.head[0].in_features == 64 * 8 * 33
    assert count_parameters(m) == _expected_params(3, 64 * 8 * 33)
    out = m(torch.rand(2, 3, 120, 320))
    assert out.shape == (2,) and torch.isfinite(out).all()
    d = Dave2(Dave2Config(inputs=("disp_sgm",)))
    assert d.features[0].in_channels == 1


def test_speed_input_changes_output_and_is_required() -> None:
    torch.manual_seed(0)
    m = Dave2(Dave2Config(use_speed=True)).eval()
    assert m.head[0].in_features == 1152 + 1
    assert count_parameters(m) == _expected_params(4, 1152, speed=True)
    x = torch.randn(2, 4, 66, 200)
    a, b = m.raw(x, torch.tensor([5.0, 5.0])), m.raw(x, torch.tensor([25.0, 25.0]))
    assert not torch.allclose(a, b)
    with pytest.raises(ValueError, match="use_speed=True"):
        m(x)
    packed = PackedDave2(m)
    risk = m(x, torch.tensor([5.0, 5.0]))
    assert torch.equal(packed(pack_input(m.cfg, x, torch.tensor([5.0, 5.0]))), risk)
    assert torch.equal(risk, torch.clamp(a[:, 0], 0.0, 1.0))  # mse: the clamped regression


def test_bad_configs_and_inputs() -> None:
    with pytest.raises(ValueError, match="too small"):
        Dave2Config(height=40, width=200)
    with pytest.raises(ValueError, match="unknown channel group"):
        Dave2Config(inputs=("rgb", "depth"))
    m = Dave2(Dave2Config())
    with pytest.raises(ValueError, match=r"expects input \(N, 4, 66, 200\)"):
        m(torch.randn(1, 3, 66, 200))


def test_preprocess_channels_normalisation_and_invalid_disparity() -> None:
    cfg = Dave2Config(height=66, width=200, disp_scale=32.0)
    left = np.zeros((2, 132, 400, 3), np.uint8)
    left[..., 2] = 255  # red in BGR
    disp = np.full((2, 132, 400), 16.0, np.float32)
    disp[:, :, :200] = -1.0  # invalid left half
    x = preprocess(cfg, left, disp)
    assert x.shape == (2, 4, 66, 200) and x.dtype == torch.float32
    assert torch.allclose(x[:, 0], torch.ones(1))  # R channel first (BGR -> RGB), 255 -> +1
    assert torch.allclose(x[:, 1:3], -torch.ones(1))
    assert torch.allclose(x[:, 3, :, :100], torch.zeros(1))  # invalid -> 0
    assert torch.allclose(x[:, 3, :, 100:], torch.full((1,), 0.5))  # 16 px / 32


def test_disparity_of_another_size_than_the_image_is_an_error() -> None:
    cfg = Dave2Config()
    left = np.zeros((2, 100, 300, 3), np.uint8)
    with pytest.raises(ValueError, match=r"input sizes disagree.*rgb 100×300.*disp_sgm 50×150"):
        prepare_channels(cfg, left, np.zeros((2, 50, 150), np.float32))
    with pytest.raises(ValueError, match="'disp_sgm' is required"):
        prepare_channels(cfg, left, None)


def test_save_load_roundtrip_identical(tmp_path: Path) -> None:
    torch.manual_seed(1)
    net = Dave2(Dave2Config(inputs=("rgb", "disp_gt"), use_speed=True))
    save_risk_model(net, tmp_path / "m", {"label": "risk_thw_paper", "variant": "x"})
    loaded = load_risk_model(tmp_path / "m")
    assert loaded.meta["label"] == "risk_thw_paper" and loaded.meta[
        "n_parameters"
    ] == count_parameters(net)
    rng = np.random.default_rng(0)
    left = rng.integers(0, 255, (3, 80, 240, 3), dtype=np.uint8)
    gt = rng.uniform(0, 30, (3, 80, 240)).astype(np.float32)
    sp = np.array([3.0, 10.0, 20.0], np.float32)
    x = preprocess(net.cfg, left, disp_gt=gt)
    with torch.no_grad():
        ref = net.eval()(x, torch.from_numpy(sp)).numpy()
    assert np.array_equal(loaded.predict(left, disp_gt=gt, speed=sp), ref)
    with pytest.raises(ValueError, match="uses the subject speed"):
        loaded.predict(left, disp_gt=gt)


def test_load_errors_name_the_file(tmp_path: Path) -> None:
    with pytest.raises(RiskModelError, match="model.ckpt: risk model checkpoint not found"):
        load_risk_model(tmp_path)
    (tmp_path / "model.ckpt").write_bytes(b"not a checkpoint")
    with pytest.raises(RiskModelError, match="not a readable torch checkpoint"):
        load_risk_model(tmp_path)
    net = Dave2(Dave2Config())
    save_risk_model(net, tmp_path / "ok")
    meta = json.loads((tmp_path / "ok" / "model_meta.json").read_text())
    meta["config"]["height"] = 99
    (tmp_path / "ok" / "model_meta.json").write_text(json.dumps(meta))
    with pytest.raises(RiskModelError, match="'config' differs"):
        load_risk_model(tmp_path / "ok")


def test_risk_and_fusion_models_share_one_checkpoint_format(tmp_path: Path) -> None:
    from traffictwin.fusion.deeplab import DeepLabSpec, DeepLabV3Plus
    from traffictwin.fusion.model_io import CKPT_FORMAT, FusionModelError, load_fusion_model
    from traffictwin.fusion.resnet import ResNetSpec
    from traffictwin.trainer import (
        MODEL_FORMAT,
        model_checkpoint,
        net_state_dict,
        save_model_files,
    )

    assert CKPT_FORMAT == MODEL_FORMAT
    net = Dave2(Dave2Config())
    save_risk_model(net, tmp_path / "risk", {"label": "risk"})
    ck = torch.load(tmp_path / "risk" / "model.ckpt", weights_only=True)
    info = ck["traffictwin"]
    assert (info["format"], info["problem"], info["architecture"]) == (
        MODEL_FORMAT,
        "risk",
        net.cfg.to_dict(),
    )
    assert info["label"] == "risk"
    own = net.state_dict()
    assert all(torch.equal(v, own[k]) for k, v in net_state_dict(ck).items())
    assert set(net_state_dict(ck)) == set(own)
    # a fusion network in the same format is refused by the risk loader, and the other way round
    spec = DeepLabSpec(
        backbone=ResNetSpec(block="basic", layers=(1, 1, 1, 1), base_width=8),
        aspp_channels=8,
        low_level_channels=8,
        decoder_channels=8,
    )
    fus = tmp_path / "fusion" / "model.ckpt"
    fus.parent.mkdir()
    ck = model_checkpoint("fusion", spec.as_dict(), DeepLabV3Plus(spec).state_dict())
    save_model_files(fus, ck, fus.parent / "model_meta.json", ck["traffictwin"])
    assert load_fusion_model(fus).spec == spec
    with pytest.raises(RiskModelError, match="a fusion model checkpoint, expected a risk model"):
        load_risk_model(fus)
    with pytest.raises(FusionModelError, match="a risk model checkpoint, expected a fusion model"):
        load_fusion_model(tmp_path / "risk" / "model.ckpt")
    # the old risk format ({"format": 1, "config", "state_dict"}) is not a model checkpoint
    torch.save({"format": 1, "config": net.cfg.to_dict(), "state_dict": own}, fus)
    with pytest.raises(RiskModelError, match=f"expected format '{MODEL_FORMAT}'"):
        load_risk_model(fus)
