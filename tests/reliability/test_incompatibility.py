"""Known-incompatible models: what the problems' gate evaluators call incompatible, and only that.

A fusion model trained for another grid or number of input channels cannot run on the current
test set (its recorded ``model_meta.json`` says so before any weight is read); a risk model whose
config this version cannot build is incompatible. Anything else that goes wrong is an error that
stops the gate (tests in test_gate_reliability.py).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from traffictwin.fusion.deeplab import DeepLabSpec, DeepLabV3Plus
from traffictwin.fusion.gate_eval import fusion_evaluator, grid_incompatibility
from traffictwin.fusion.model_io import CKPT_FORMAT
from traffictwin.fusion.resnet import ResNetSpec
from traffictwin.mlops import registry as reg
from traffictwin.risk.dave2 import Dave2, Dave2Config
from traffictwin.risk.gate_eval import config_incompatibility
from traffictwin.risk.model_io import risk_meta
from traffictwin.trainer import log_model, model_checkpoint

META = {
    "grid": {"rows": 32, "cols": 48, "cell": 0.5},
    "architecture": {"backbone": {"in_channels": 4}},
}


def test_grid_incompatibility_names_the_mismatch():
    assert grid_incompatibility(META, (3, 4, 32, 48)) is None
    assert (
        grid_incompatibility(META, (3, 4, 64, 48))
        == "trained on a 32x48 grid, the test set is 64x48"
    )
    assert (
        grid_incompatibility(META, (3, 6, 32, 48)) == "takes 4 input channels, the test set has 6"
    )
    assert (
        grid_incompatibility({}, (1, 4, 32, 48))
        == "trained on a NonexNone grid, the test set is 32x48"
    )
    # registration networks record no backbone: the grid decides
    assert grid_incompatibility({"grid": META["grid"], "architecture": {}}, (1, 4, 32, 48)) is None


def test_risk_config_incompatibility():
    good = risk_meta(Dave2(Dave2Config(inputs=("disp_sgm",))))
    assert config_incompatibility(good) is None
    assert "no network 'config'" in config_incompatibility({"architecture": "dave2"})
    bad = {**good, "config": {**good["config"], "inputs": ["thermal"]}}
    assert "not valid here" in config_incompatibility(bad) and "thermal" in config_incompatibility(
        bad
    )


def _tiny_fusion(rows: int, cols: int):
    spec = DeepLabSpec(
        backbone=ResNetSpec(layers=(1, 1, 1, 1), base_width=8),
        aspp_channels=8,
        aspp_rates=(1, 2, 3),
        low_level_channels=4,
        decoder_channels=8,
    )
    torch.manual_seed(0)
    net = DeepLabV3Plus(spec).eval()
    meta = {
        "format": CKPT_FORMAT,
        "cfg": "D",
        "grid": {"rows": rows, "cols": cols, "cell": 0.5},
        "data_manifest_hash": "test",
    }
    ck = model_checkpoint("fusion", spec.as_dict(), net.state_dict(), meta)
    return net, ck, ck["traffictwin"]


def test_fusion_evaluator_calls_another_grid_incompatible(cl):
    import mlflow

    ids = {}
    for rows in (32, 64):
        net, ck, meta = _tiny_fusion(rows, 48)
        mlflow.set_experiment("fusion")
        with mlflow.start_run() as run:
            log_model(ck, meta, net, np.zeros((1, 4, rows, 48), np.float32))
        ids[rows] = reg.ensure_version(cl, "traffictwin-fusion", run.info.run_id).version
    rng = np.random.default_rng(0)
    x = rng.dirichlet([1, 1, 1, 1, 1], size=(2, 32, 48))[..., :4].transpose(0, 3, 1, 2)
    label = rng.dirichlet([1, 1, 1], size=(2, 32, 48))[..., :2].transpose(0, 3, 1, 2)
    ev = fusion_evaluator(x.astype(np.float32), label.astype(np.float32), batch_size=2)
    assert np.isfinite(ev(reg.version_uri("traffictwin-fusion", ids[32]))["val/kld_fou_mean"])
    with pytest.raises(reg.IncompatibleModelError) as exc:
        ev(reg.version_uri("traffictwin-fusion", ids[64]))
    assert str(exc.value) == (
        f"model 'traffictwin-fusion' v{ids[64]}: trained on a 64x48 grid, the test set is 32x48"
    )
