"""The `paper` profile cannot rot: it composes to the papers' sizes, and its networks, loaders and
losses take one optimisation step on CPU on a handful of synthetic samples (no full data).

The profile itself asks for a GPU (``trainer: gpu``); the step here runs on the CPU trainer, which
is the only difference from a paper run's first step.
"""

from __future__ import annotations

from dataclasses import asdict, replace
from pathlib import Path

import pytest
import torch
from conftest import composed

from tests.test_fusion_training import write_prealigned
from tests.test_risk_training import _source, write_synthetic_risk
from traffictwin import trainer as common
from traffictwin.config import typed
from traffictwin.fusion.training import FusionDataModule, FusionLitModule, FusionModelConfig
from traffictwin.grid import GridSpec
from traffictwin.risk.training import RiskModelConfig, fit, prepare_split

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def paper() -> dict:
    return composed("profile=paper")


def test_paper_profile_composes_to_the_papers_sizes(paper: dict) -> None:
    fd, rd = paper["fusion_data"], paper["risk_data"]
    assert fd["scenarios"] * fd["encounters_per_scenario"] * 2 == 10_000  # fusion pairs
    assert rd["sequences"] * rd["frames_per_sequence"] == 110_152  # the risk paper's frames
    assert paper["trainer"]["accelerator"] == "gpu" and paper["profile"]["name"] == "paper"
    model = typed(paper["fusion_model"], FusionModelConfig, key="fusion_model")
    backbone = model.deeplab_spec("paper profile").backbone
    assert (backbone.block, tuple(backbone.layers)) == ("bottleneck", (3, 4, 6, 3))  # ResNet-50
    risk = typed(paper["risk_model"], RiskModelConfig, key="risk_model")
    for v in risk.run_variants:
        risk.variant(v)  # every run variant builds


@pytest.mark.slow
def test_paper_fusion_net_takes_one_step_on_cpu(paper: dict, tmp_path: Path) -> None:
    model = typed(paper["fusion_model"], FusionModelConfig, key="fusion_model")
    spec = model.deeplab_spec("paper profile")
    g = paper["grid"]
    grid = GridSpec(int(g["rows"]), int(g["cols"]), float(g["cell"]))
    root = write_prealigned(tmp_path / "pre", h=grid.rows, w=grid.cols, n=4)
    data = model.data(num_workers=0)
    assert data.batch_size == 80  # the paper's; the smoke step uses 4 of the 8 synthetic pairs
    dm = FusionDataModule(root, replace(data, batch_size=4), seed=0, grid=grid)
    module = FusionLitModule(spec.as_dict(), asdict(model.hparams()), meta={"seed": 0})
    n_params = sum(p.numel() for p in module.net.parameters())
    assert n_params > 30_000_000  # the ResNet-50 DeepLabV3+
    before = {k: v.detach().clone() for k, v in module.net.state_dict().items()}
    trainer = common.build_trainer(
        common.TrainerSettings(), max_epochs=1, fast_dev_run=1, default_root_dir=tmp_path
    )
    trainer.fit(module, datamodule=dm)
    assert trainer.state.finished and trainer.global_step == 1
    loss = trainer.callback_metrics["train/loss"]
    assert torch.isfinite(loss)
    after = module.net.state_dict()
    changed = [
        k for k, v in before.items() if v.is_floating_point() and not torch.equal(v, after[k])
    ]
    assert len(changed) > 100  # one Adam step moved the weights


@pytest.mark.slow
def test_paper_risk_nets_take_one_step_on_cpu(paper: dict, tmp_path: Path) -> None:
    risk = typed(paper["risk_model"], RiskModelConfig, key="risk_model")
    cam = paper["risk_data"]["camera"]
    write_synthetic_risk(
        tmp_path, n_shards=3, per_shard=6, width=int(cam["width"]), height=int(cam["height"])
    )
    src = _source(tmp_path)
    for variant in ("headline", "paper"):
        cfg, label = risk.variant(variant)
        tc = risk.train_config(int(paper["seed"]), variant)
        assert (tc.epochs, tc.batch_size) == (30, 10)  # the paper's settings
        train = prepare_split(src, cfg, "train", label)
        val = prepare_split(src, cfg, "val", label)
        res = fit(cfg, train, val, tc, common.TrainerSettings(), fast_dev_run=1)
        assert res.steps == 1, variant
        out = res.net(
            torch.zeros(2, cfg.in_channels, cfg.height, cfg.width),
            torch.tensor([5.0, 20.0]) if cfg.use_speed else None,
        )
        assert out.shape == (2,) and bool(((out >= 0) & (out <= 1)).all()), variant


@pytest.mark.slow
def test_paper_learned_registration_takes_one_step_on_cpu(paper: dict, tmp_path: Path) -> None:
    from tests.test_learned_registration import write_registration_data
    from traffictwin.fusion.registration_training import (
        RegistrationModelConfig,
        RegistrationSettings,
        fit_registration,
    )
    from traffictwin.fusion.training_data import TrainingSet
    from traffictwin.trainer import ModelOutputs

    rc = typed(paper["registration_model"], RegistrationModelConfig, key="registration_model")
    assert rc.train.batch_size == 32 and rc.train.train_samples_per_epoch == 0  # whole epochs
    g = paper["grid"]
    grid = GridSpec(int(g["rows"]), int(g["cols"]), float(g["cell"]))
    root = write_registration_data(tmp_path / "pre", grid=grid, n=4)
    res = fit_registration(
        TrainingSet(root, "D", {"r": 5.0, "alpha": 20.0}, grid, 0),
        model=RegistrationSettings(
            rc.net_spec("paper profile"),
            replace(rc.train, batch_size=4, max_epochs=1, train_samples_per_epoch=4),
            rc.min_gain,
        ),
        trainer_settings=common.TrainerSettings(),
        outputs=ModelOutputs(tmp_path / "out" / "model.ckpt"),
    )
    assert res.metrics["epochs"] == 1 and torch.isfinite(torch.tensor(res.metrics["train/loss"]))
