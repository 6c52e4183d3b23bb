"""Fusion training: augmentation, data module, Lightning (fast_dev_run, overfit), MLflow round trip, loader checks."""

from __future__ import annotations

import json
import math
import os
import shutil
from dataclasses import asdict, replace
from pathlib import Path

import mlflow
import numpy as np
import pytest
import torch
from conftest import composed

from traffictwin import trainer as common
from traffictwin.config import ConfigError
from traffictwin.fusion.deeplab import DeepLabSpec
from traffictwin.fusion.model_io import FusionModelError, load_fusion_model, predict_masses
from traffictwin.fusion.pairs import evenly_spaced
from traffictwin.fusion.resnet import ResNetSpec
from traffictwin.fusion.training import (
    DataSettings,
    FusionDataModule,
    FusionHParams,
    FusionLitModule,
    FusionSettings,
    LoopSettings,
    TrackingSettings,
    augment,
    fit_fusion,
)
from traffictwin.fusion.training_data import TrainingSet
from traffictwin.grid import GridSpec
from traffictwin.io.shards import DatasetError, DatasetWriter
from traffictwin.mlops.registry import load_registered
from traffictwin.trainer import ModelOutputs

TINY = DeepLabSpec(
    backbone=ResNetSpec(block="basic", layers=(1, 1, 1, 1), base_width=8),
    aspp_channels=16,
    low_level_channels=8,
    decoder_channels=16,
)
GRID = GridSpec(64, 48, 1.0)


pytestmark = pytest.mark.usefixtures("single_torch_thread")


def synthetic_pairs(n: int, h: int, w: int, seed: int) -> dict[str, np.ndarray]:
    """Learnable toy pairs: label = free background with occupied boxes; map 1 sees the left part,
    map 2 the right part shifted by a couple of cells (a misaligned second vehicle)."""
    g = np.random.default_rng(seed)
    lab = np.zeros((n, 2, h, w), np.float32)
    lab[:, 0] = 0.8
    for i in range(n):
        for _ in range(3):
            r, c = g.integers(2, h - 10), g.integers(2, w - 8)
            lab[i, 0, r : r + 6, c : c + 4] = 0.0
            lab[i, 1, r : r + 6, c : c + 4] = 0.9
    m1 = lab.copy()
    m1[:, :, :, (2 * w) // 3 :] = 0.0
    shift = g.integers(-2, 3, size=(n, 2))
    m2 = np.stack([np.roll(lab[i], tuple(shift[i]), axis=(1, 2)) for i in range(n)])
    m2[:, :, :, : w // 3] = 0.0
    return {
        "inputs": np.concatenate([m1, m2], 1).astype(np.float32),
        "label": lab,
        "noise": np.zeros((n, 3), np.float32),
        "scenario": np.arange(n, dtype=np.int64),
    }


def write_prealigned(root: Path, h: int = 64, w: int = 48, n: int = 8, seed: int = 0) -> Path:
    """A small 'prealigned' dataset: two train shards and one val shard of ``n`` pairs each."""
    wr = DatasetWriter(root, "prealigned", {"synthetic": True, "h": h, "w": w}, seed)
    for i, split in enumerate(["train", "train", "val"]):
        wr.add_shard(i, synthetic_pairs(n, h, w, seed + i), split=split)
    wr.finalize()
    return root


# ---------------------------------------------------------------------------------------------
# augmentation


def test_augmentation_moves_inputs_and_label_together() -> None:
    h, w = 64, 48
    x = torch.zeros(16, 4, h, w)
    y = torch.zeros(16, 2, h, w)
    r, c = 10, 36  # a known occupied cell off-centre (front-right)
    x[:, 1, r, c] = x[:, 3, r, c] = 1.0
    y[:, 1, r, c] = 1.0
    xa, ya = augment(
        x, y, flip=True, max_rotation_deg=20.0, generator=torch.Generator().manual_seed(0)
    )
    moved = 0
    for i in range(16):
        pos_x1 = divmod(int(xa[i, 1].argmax()), w)
        pos_x2 = divmod(int(xa[i, 3].argmax()), w)
        pos_y = divmod(int(ya[i, 1].argmax()), w)
        assert pos_x1 == pos_y == pos_x2
        assert torch.allclose(xa[i, 1], ya[i, 1]) and torch.allclose(xa[i, 3], ya[i, 1])
        moved += pos_y != (r, c)
        # rotation about the map centre in metric space: the distance to the centre is kept (square cells)
        rr, cc = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
        wgt = ya[i, 1].numpy()
        cy, cx = (wgt * rr).sum() / wgt.sum(), (wgt * cc).sum() / wgt.sum()
        d0 = math.hypot(r + 0.5 - h / 2, c + 0.5 - w / 2)
        assert math.hypot(cy + 0.5 - h / 2, cx + 0.5 - w / 2) == pytest.approx(d0, abs=0.6)
    assert moved >= 12


def test_flip_only_is_an_exact_mirror() -> None:
    x = torch.rand(32, 4, 16, 12)
    y = torch.rand(32, 2, 16, 12)
    xa, ya = augment(
        x, y, flip=True, max_rotation_deg=0.0, generator=torch.Generator().manual_seed(1)
    )
    seen = set()
    for i in range(32):
        for dims in ((), (-1,), (-2,), (-2, -1)):
            cand = torch.flip(x[i], dims) if dims else x[i]
            if torch.allclose(xa[i], cand, atol=1e-5):
                assert torch.allclose(ya[i], torch.flip(y[i], dims) if dims else y[i], atol=1e-5)
                seen.add(dims)
                break
        else:
            pytest.fail(f"sample {i} is not a mirror image of its input")
    assert len(seen) == 4


def test_augmented_masses_stay_on_the_simplex() -> None:
    g = torch.Generator().manual_seed(2)
    raw = torch.rand(8, 3, 32, 24, generator=g)
    raw = raw / raw.sum(1, keepdim=True)
    x = torch.cat([raw[:, :2], raw[:, 1:]], 1)
    y = raw[:, :2].clone()
    xa, ya = augment(x, y, generator=g)
    for t in (xa[:, :2], xa[:, 2:], ya):
        assert t.min() >= 0 and (t.sum(1) <= 1 + 1e-6).all()


# ---------------------------------------------------------------------------------------------
# data module and Lightning


def test_datamodule_subsets_and_grid_check(tmp_path: Path) -> None:
    root = write_prealigned(tmp_path / "pre")
    dm = FusionDataModule(
        root,
        DataSettings(batch_size=4, train_samples_per_epoch=8, val_samples=3),
        seed=5,
        grid=GRID,
    )
    dm.setup("fit")
    assert len(dm.train_set) == 16 and len(dm.val_set) == 3
    batches = list(dm.train_dataloader())
    assert (
        len(batches) == 2
        and batches[0][0].shape == (4, 4, 64, 48)
        and batches[0][1].shape == (4, 2, 64, 48)
    )
    first = torch.cat([b[0] for b in batches])
    dm2 = FusionDataModule(root, dm.settings, seed=5, grid=GRID)
    dm2.setup("fit")
    dl2 = dm2.train_dataloader()
    assert torch.equal(first, torch.cat([b[0] for b in dl2]))  # seeded
    assert not torch.equal(first, torch.cat([b[0] for b in dl2]))  # the next epoch draws afresh
    assert evenly_spaced(10, 3).tolist() == [0, 4, 9] and evenly_spaced(5, 0).tolist() == [
        0,
        1,
        2,
        3,
        4,
    ]
    bad = FusionDataModule(root, dm.settings, seed=5, grid=GridSpec(128, 96, 0.64))
    with pytest.raises(
        DatasetError, match=r"\(64, 48\) cells but the grid parameter says \(128, 96\)"
    ):
        bad.setup("fit")


@pytest.mark.integration
def test_fast_dev_run(tmp_path: Path) -> None:
    root = write_prealigned(tmp_path / "pre")
    dm = FusionDataModule(root, DataSettings(batch_size=4), seed=0, grid=GRID)
    module = FusionLitModule(TINY.as_dict(), asdict(FusionHParams()), meta={"seed": 0})
    trainer = common.build_trainer(
        common.TrainerSettings(), max_epochs=1, fast_dev_run=True, default_root_dir=tmp_path
    )
    trainer.fit(module, datamodule=dm)
    assert trainer.state.finished
    for k in ("train/loss", "val/loss", "val/kld", "val/kld_full", "val/dice_occ", "val/dice_free"):
        assert k in trainer.callback_metrics and math.isfinite(
            float(trainer.callback_metrics[k])
        ), k
    assert not (tmp_path / "checkpoints").exists() and not Path("checkpoints").exists()


@pytest.mark.integration
def test_short_overfit_loss_falls(tmp_path: Path) -> None:
    """A few pairs, the module's own optimizer (Adam, lr 0.01) and loss: the training loss falls by > 3x."""
    from traffictwin.fusion.losses import evidential_loss

    common.seed_everything(0)
    root = write_prealigned(tmp_path / "pre", n=4)
    module = FusionLitModule(TINY.as_dict(), asdict(FusionHParams(lr=0.01)), meta={"seed": 0})
    dm = FusionDataModule(root, DataSettings(batch_size=4), seed=0, grid=GRID)
    dm.setup("fit")
    x, y = dm.train_set.tensors[0][:4], dm.train_set.tensors[1][:4]
    opt = module.configure_optimizers()["optimizer"]
    module.train()
    losses = []
    for _ in range(30):
        loss = evidential_loss(module.net(x), y, 3.0)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss))
    assert min(losses[-5:]) < losses[0] / 3, losses


def test_trainer_settings_from_cfg() -> None:
    cfg = {
        "trainer": {
            "accelerator": "gpu",
            "devices": 4,
            "num_nodes": 2,
            "strategy": "ddp",
            "precision": "bf16-mixed",
            "num_workers": 8,
        }
    }
    s = common.TrainerSettings.from_cfg(cfg, source="params.yaml")
    assert (s.accelerator, s.devices, s.num_nodes, s.strategy, s.precision, s.num_workers) == (
        "gpu",
        4,
        2,
        "ddp",
        "bf16-mixed",
        8,
    )
    assert (
        s.resolved_deterministic() == "warn"
        and common.TrainerSettings().resolved_deterministic() is True
    )
    with pytest.raises(ConfigError, match="'trainer.precision' must be one of"):
        common.TrainerSettings.from_cfg(
            {"trainer": {**cfg["trainer"], "precision": "fp8"}}, source="params.yaml"
        )
    with pytest.raises(ConfigError, match="'trainer.num_nodes' is missing"):
        common.TrainerSettings.from_cfg(
            {"trainer": {k: v for k, v in cfg["trainer"].items() if k != "num_nodes"}},
            source="params.yaml",
        )
    with pytest.raises(ConfigError, match="'trainer.devices' must be >= 1 or -1"):
        common.TrainerSettings.from_cfg({"trainer": {**cfg["trainer"], "devices": 0}}, source="p")
    with pytest.raises(ConfigError, match="params.yaml: 'trainer.num_threads' must be >= 0"):
        common.TrainerSettings.from_cfg(
            {"trainer": {**cfg["trainer"], "num_threads": -1}}, source="params.yaml"
        )
    with pytest.raises(ConfigError, match="'trainer.gpus'"):
        common.TrainerSettings.from_cfg({"trainer": {**cfg["trainer"], "gpus": 2}}, source="p")
    s32 = common.TrainerSettings.from_cfg(
        {"trainer": {**cfg["trainer"], "precision": 32, "devices": "auto"}}, source="p"
    )
    assert (s32.precision, s32.devices, s32.num_threads) == ("32", "auto", 0)


def test_requested_hardware_must_exist(monkeypatch: pytest.MonkeyPatch) -> None:
    """trainer=gpu on a machine without CUDA, or more devices than it has: one clear line."""
    gpu = common.TrainerSettings(accelerator="gpu", devices=4, strategy="ddp")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(
        ConfigError, match=r"p: 'trainer.accelerator' is 'gpu' but .* no CUDA device"
    ):
        gpu.check_available("p")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    with pytest.raises(ConfigError, match=r"'trainer.devices' is 4 but this machine has 2 CUDA"):
        gpu.check_available("p")
    replace(gpu, devices=2).check_available("p")  # fits
    replace(gpu, devices="auto").check_available("p")  # Lightning decides
    cores = os.cpu_count() or 1
    cpu = common.TrainerSettings(accelerator="cpu", devices=cores + 1, strategy="ddp")
    with pytest.raises(ConfigError, match=rf"'trainer.devices' is {cores + 1} CPU processes"):
        cpu.check_available("p")
    common.TrainerSettings().check_available("p")  # the default CPU trainer


def test_global_rank_from_env(monkeypatch: pytest.MonkeyPatch) -> None:
    for v in ("RANK", "SLURM_PROCID", "LOCAL_RANK", "NODE_RANK", "GROUP_RANK"):
        monkeypatch.delenv(v, raising=False)
    assert common.global_rank() == 0
    monkeypatch.setenv("LOCAL_RANK", "1")
    assert common.global_rank() == 1
    with common.tracked_run("x", "y", profile="ci", stage="t") as run:
        assert run is None  # non-zero ranks do not open MLflow runs


# ---------------------------------------------------------------------------------------------
# a whole (tiny) run: outputs, MLflow, reload, loader checks


def _fit(
    tmp_path: Path, cfg: str = "B", spec: DeepLabSpec = TINY, tracking: bool = True, epochs: int = 2
):
    root = tmp_path / "pre"
    if not root.exists():
        write_prealigned(root)
    out = tmp_path / "models" / cfg
    return fit_fusion(
        TrainingSet(root, cfg, {"r": 1.0, "alpha": 10.0}, GRID, 3),
        model=FusionSettings(
            spec,
            FusionHParams(),
            DataSettings(batch_size=4, train_samples_per_epoch=8, val_samples=4),
            LoopSettings(max_epochs=epochs),
        ),
        trainer_settings=common.TrainerSettings(),
        outputs=ModelOutputs(
            out / "model.ckpt",
            out / "model_meta.json",
            tmp_path / f"metrics_{cfg}.json",
            tmp_path / f"curves_{cfg}.csv",
        ),
        tracking=TrackingSettings(
            run_name=f"fusion-{cfg}",
            profile="ci",
            stage=f"train_fusion@{cfg}",
            params={"a.b": 1},
            enabled=tracking,
        ),
    )


@pytest.mark.integration
def test_fit_logs_mlflow_and_reloads_identically(tmp_path: Path, mlflow_uri: str) -> None:
    res = _fit(tmp_path)
    meta = json.loads((tmp_path / "models/B/model_meta.json").read_text())
    assert (
        meta["cfg"] == "B"
        and meta["architecture"] == TINY.as_dict()
        and meta["grid"] == {"rows": 64, "cols": 48, "cell": 1.0}
    )
    assert len(meta["data_manifest_hash"]) == 64 and res.run_id and res.model_uri
    # what differs between identical runs stays out of the published files (see the run record)
    assert not {"mlflow_run_id", "mlflow_model_uri", "data_root"} & set(meta)
    assert res.train_seconds > 0 and res.samples_per_s > 0
    metrics = json.loads((tmp_path / "metrics_B.json").read_text())
    for k in (
        "val/loss",
        "val/kld",
        "val/kld_full",
        "val/dice_occ",
        "val/dice_free",
        "train/loss",
        "val/kld_naive",
        "best_epoch",
    ):
        assert k in metrics, k
    assert metrics["samples_seen"] == 2 * 8 and "train_seconds" not in metrics
    curves = (tmp_path / "curves_B.csv").read_text().splitlines()
    assert curves[0].startswith("epoch,") and len(curves) == 1 + 2

    client = mlflow.tracking.MlflowClient(mlflow_uri)
    run = client.get_run(res.run_id)
    assert run.info.run_name == "fusion-B" and run.data.tags["dvc_stage"] == "train_fusion@B"
    assert (
        run.data.params["a.b"] == "1"
        and run.data.params["data.manifest_hash"] == meta["data_manifest_hash"]
    )
    exp = client.get_experiment(run.info.experiment_id)
    assert exp.name == "fusion"
    for name in (
        "train/loss",
        "val/loss",
        "val/kld",
        "val/kld_full",
        "val/dice_occ",
        "val/dice_free",
    ):
        # the per-epoch history (steps 0, 1), then the best epoch's value once more at the last
        # step: the run's value, equal to the DVC metrics file's
        hist = client.get_metric_history(res.run_id, name)
        assert [m.step for m in hist] == [0, 1, 1], name
        assert hist[-1].value == hist[metrics["best_epoch"]].value == metrics[name], name
    assert [m.step for m in client.get_metric_history(res.run_id, "lr")] == [0, 1]
    # MLflow's and DVC's numbers for the same run and metric are equal
    mlflow_values = run.data.metrics
    for name, value in metrics.items():
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            assert mlflow_values[name] == value, name
    assert not any(k.startswith("best/") for k in mlflow_values)
    arts = [a.path for a in client.list_artifacts(res.run_id, "checkpoints")]
    assert arts == ["checkpoints/model.ckpt"]

    net = load_fusion_model(
        tmp_path / "models/B", expected_cfg="B", expected_architecture=TINY, expected_grid=GRID
    )
    logged = load_registered(res.model_uri, load_fusion_model)
    x = np.random.default_rng(0).random((3, 4, 64, 48)).astype(np.float32)
    m_a, u_a = predict_masses(net, x)
    m_b, u_b = predict_masses(logged, x)
    assert m_a.shape == (3, 2, 64, 48) and u_a.shape == (3, 64, 48)
    np.testing.assert_array_equal(m_a, m_b)
    np.testing.assert_array_equal(u_a, u_b)
    np.testing.assert_allclose(m_a.sum(1) + u_a, 1.0, atol=1e-6)


@pytest.mark.integration
def test_training_is_deterministic(tmp_path: Path) -> None:
    a = _fit(tmp_path / "a", tracking=False, epochs=1)
    b = _fit(tmp_path / "b", tracking=False, epochs=1)
    sa = torch.load(a.checkpoint, weights_only=True)["state_dict"]
    sb = torch.load(b.checkpoint, weights_only=True)["state_dict"]
    assert sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)
    assert a.metrics["val/loss"] == b.metrics["val/loss"]
    # every published file byte-identical (checkpoint archive, meta, metrics, curves): dvc.lock stays put
    for rel in (
        "models/B/model.ckpt",
        "models/B/model_meta.json",
        "metrics_B.json",
        "curves_B.csv",
    ):
        assert (tmp_path / "a" / rel).read_bytes() == (tmp_path / "b" / rel).read_bytes(), rel


@pytest.mark.integration
def test_loader_rejects_other_configuration_architecture_or_swapped_file(tmp_path: Path) -> None:
    _fit(tmp_path, "B", tracking=False, epochs=1)
    _fit(
        tmp_path,
        "C",
        spec=DeepLabSpec(
            backbone=ResNetSpec(block="basic", layers=(1, 1, 1, 1), base_width=4),
            aspp_channels=8,
            low_level_channels=4,
            decoder_channels=8,
        ),
        tracking=False,
        epochs=1,
    )
    with pytest.raises(
        FusionModelError,
        match=r"trained on the pose noise of 'B' \({'r': 1.0, 'alpha': 10.0}\), expected 'C'",
    ):
        load_fusion_model(tmp_path / "models/B/model.ckpt", expected_cfg="C")
    with pytest.raises(
        FusionModelError, match="architecture mismatch: checkpoint has basic ResNet .* base_width=4"
    ):
        load_fusion_model(tmp_path / "models/C/model.ckpt", expected_architecture=TINY)
    with pytest.raises(FusionModelError, match="trained on grid"):
        load_fusion_model(tmp_path / "models/B/model.ckpt", expected_grid=GridSpec(128, 96, 0.64))
    # someone copies C's checkpoint over B's: the checkpoint and model_meta.json disagree
    shutil.copyfile(tmp_path / "models/C/model.ckpt", tmp_path / "models/B/model.ckpt")
    with pytest.raises(
        FusionModelError, match=r"models/B: model.ckpt and its model_meta.json are not one pair"
    ):
        load_fusion_model(tmp_path / "models/B/model.ckpt")
    (tmp_path / "junk.ckpt").write_bytes(b"not a checkpoint")
    with pytest.raises(FusionModelError, match="junk.ckpt: not a readable torch checkpoint"):
        load_fusion_model(tmp_path / "junk.ckpt")
    with pytest.raises(FusionModelError, match="not found"):
        load_fusion_model(tmp_path / "nowhere/model.ckpt")


@pytest.mark.integration
def test_residual_option_round_trips_and_old_models_load_as_the_plain_network(
    tmp_path: Path,
) -> None:
    from traffictwin.io.shards import sha256_file
    from traffictwin.model_format import CKPT_SHA_KEY

    residual = replace(TINY, refine_channels=4, evidence="exp", residual="dempster")
    _fit(tmp_path, "B", spec=residual, tracking=False, epochs=1)
    meta = json.loads((tmp_path / "models/B/model_meta.json").read_text())
    assert meta["architecture"]["residual"] == "dempster"
    net = load_fusion_model(tmp_path / "models/B", expected_architecture=residual)
    assert net.spec == residual
    # a model folder from before the option: no 'residual' key in the checkpoint nor its meta
    _fit(tmp_path, "C", tracking=False, epochs=1)
    ckpt, meta_path = tmp_path / "models/C/model.ckpt", tmp_path / "models/C/model_meta.json"
    blob = torch.load(ckpt, weights_only=False)
    del blob["traffictwin"]["architecture"]["residual"]
    torch.save(blob, ckpt)
    meta = json.loads(meta_path.read_text())
    del meta["architecture"]["residual"]
    meta[CKPT_SHA_KEY] = sha256_file(ckpt)
    meta_path.write_text(json.dumps(meta))
    old = load_fusion_model(tmp_path / "models/C", expected_architecture=TINY)
    assert old.spec.residual == "none" and old.spec == TINY
    with pytest.raises(FusionModelError, match="architecture mismatch: .*residual=none"):
        load_fusion_model(tmp_path / "models/C", expected_architecture=residual)


def test_missing_data_fails_and_writes_nothing(tmp_path: Path) -> None:
    out = tmp_path / "models" / "A"
    with pytest.raises(DatasetError, match="dataset folder not found"):
        fit_fusion(
            TrainingSet(tmp_path / "absent", "A", {"r": 0.0, "alpha": 0.0}, GRID, 0),
            model=FusionSettings(
                TINY, FusionHParams(), DataSettings(batch_size=4), LoopSettings(max_epochs=1)
            ),
            trainer_settings=common.TrainerSettings(),
            outputs=ModelOutputs(out / "model.ckpt", out / "model_meta.json"),
        )
    assert not out.exists()


def test_fusion_model_config_is_validated_once_with_full_keys() -> None:

    from traffictwin.config import typed
    from traffictwin.fusion.training import FusionModelConfig

    def node() -> dict:
        return composed()["fusion_model"]

    n = node()
    m = typed(n, FusionModelConfig, key="fusion_model")
    hp, data, loop = m.hparams(), m.data(num_workers=3), m.loop()
    assert (hp.lr, hp.loss, hp.loss_settings, hp.augment_rotation_deg, hp.channels_last) == (
        n["optim"]["lr"],
        n["loss"]["name"],
        n["loss"][n["loss"]["name"]],
        n["augment"]["rotation_deg"],
        n["train"]["channels_last"],
    )
    assert (data.batch_size, data.num_workers, loop.max_epochs) == (
        n["train"]["batch_size"],
        3,
        n["train"]["max_epochs"],
    )
    assert (
        m.deeplab_spec("params.yaml").backbone.base_width
        == n["architecture"]["backbone"]["base_width"]
    )
    for group, key, value, msg in [
        ("optim", "lr_factor", 1.5, "'fusion_model.optim.lr_factor' must be <= 1.0"),
        ("train", "batch_size", 1, "'fusion_model.train.batch_size' must be >= 2"),
        ("augment", "rotation_deg", 200.0, "'fusion_model.augment.rotation_deg' must be <= 180"),
        ("loss", "name", "focal", "fusion_model.loss.name"),
        ("train", "typo", 1, "fusion_model.train.typo"),
    ]:
        bad = node()
        bad[group][key] = value
        with pytest.raises(ConfigError, match=msg):
            typed(bad, FusionModelConfig, key="fusion_model")
    # every loss has its own block; a variant's loss picks that block
    kl = m.hparams("paper_kl")
    assert (kl.loss, kl.loss_settings) == ("paper_kl", n["loss"]["paper_kl"])
    assert m.hparams("paper").loss_settings == n["loss"]["paper"]
    with pytest.raises(ConfigError, match="unknown fusion loss 'focal'"):
        m.hparams("focal")
    for loss, key, value, msg in [
        ("mass", "occupied_weight", 0.5, "'fusion_model.loss.mass.occupied_weight' must be >= 1.0"),
        ("paper_kl", "kl_weight", -1.0, "'fusion_model.loss.paper_kl.kl_weight' must be >= 0.0"),
    ]:
        bad = node()
        bad["loss"][loss][key] = value
        with pytest.raises(ConfigError, match=msg):
            typed(bad, FusionModelConfig, key="fusion_model")
    bad = node()
    bad["architecture"]["backbone"]["output_stride"] = 4
    with pytest.raises(ConfigError, match="'fusion_model.architecture' is invalid"):
        typed(bad, FusionModelConfig, key="fusion_model").deeplab_spec("params.yaml")


@pytest.mark.integration
def test_history_rows_per_epoch_or_per_validation(tmp_path: Path) -> None:
    from types import SimpleNamespace

    opt = SimpleNamespace(param_groups=[{"lr": 0.5}])
    tr = SimpleNamespace(
        sanity_checking=False,
        is_global_zero=True,
        callback_metrics={"val/loss": torch.tensor(0.25), "train/loss": 1.5, "note": 3.0},
        optimizers=[opt],
        current_epoch=0,
        max_epochs=2,
        global_step=4,
        num_training_batches=2,
    )
    per_epoch = common.History()
    per_epoch.on_train_epoch_end(tr, None)
    assert per_epoch.rows == [{"epoch": 0, "val/loss": 0.25, "train/loss": 1.5, "lr": 0.5}]
    per_epoch.write_csv(tmp_path / "e.csv")
    assert (tmp_path / "e.csv").read_text() == "epoch,lr,train/loss,val/loss\n0,0.5,1.5,0.25\n"
    per_val = common.History("validation", metrics=("val/loss", "val/mae"), train_loss="train/mse")
    per_epoch_only = per_val.on_train_epoch_end(tr, None)  # no row: rows come per validation
    assert per_epoch_only is None and per_val.rows == []
    for loss in (1.0, 2.0):
        per_val.on_train_batch_end(tr, None, {"loss": torch.tensor(loss)}, None, 0)
    per_val.on_validation_end(tr, None)
    row = per_val.rows[0]
    assert (row["step"], row["epoch"], row["train/mse"], row["val/loss"]) == (4, 2.0, 1.5, 0.25)
    assert math.isnan(row["val/mae"])
    assert list(per_val.frame().columns) == ["step", "epoch", "train/mse", "val/loss", "val/mae"]
    with pytest.raises(ValueError, match="every must be"):
        common.History("step")


# ---------------------------------------------------------------------------------------------
# bad input and the fusion_variants config


@pytest.mark.parametrize(
    "key, channel, value, msg",
    [
        ("label", 1, np.nan, "1 NaN and 0 infinite"),  # refused by the shard reader
        ("inputs", 0, -0.5, "outside the simplex"),
        ("inputs", 3, 0.9, "outside the simplex"),  # m_F2 + m_O2 > 1 in map 2
    ],
)
def test_loader_names_the_file_and_array_of_bad_masses(tmp_path: Path, key, channel, value, msg):
    from traffictwin.fusion.training_data import load_prealigned

    wr = DatasetWriter(tmp_path / "bad", "prealigned", {"synthetic": True}, 0)
    arrays = synthetic_pairs(4, 64, 48, 0)
    arrays[key][1, channel, 5, 7] = value
    if key == "inputs" and channel == 3:
        arrays[key][1, 2, 5, 7] = 0.5
    wr.add_shard(0, arrays, split="train", check=False)  # a NaN shard with a valid hash
    wr.finalize()
    with pytest.raises(DatasetError, match=rf"bad(/shard-00000.npz)?: .*array '{key}'.*{msg}"):
        load_prealigned(tmp_path / "bad", "train", GRID)


def test_fusion_variants_are_checked_against_configurations_and_registered_data() -> None:
    from omegaconf import OmegaConf

    from traffictwin.config import ConfigError
    from traffictwin.fusion.config import fusion_variants, variant_row

    base = {
        "configurations": {"A": {"r": 0.0, "alpha": 0.0}, "D": {"r": 5.0, "alpha": 20.0}},
        "fusion_data": {
            "register": {"configurations": ["D"], "max_train_pairs": 8, "max_val_pairs": None}
        },
    }

    def with_variants(v):
        return OmegaConf.create({**base, "fusion_variants": v})

    got = fusion_variants(
        with_variants(
            {
                "paper": {"config": "mixed", "inputs": "prealigned", "loss": "paper"},
                "D-reg": {"config": "D", "inputs": "registered", "loss": None},
                "A": {"config": "A", "inputs": "prealigned", "loss": None},
            }
        )
    )
    assert [(v.method, v.loss, v.config) for v in got.values()] == [
        ("dnn", "paper", "mixed"),
        ("registered+network", None, "D"),
        ("dnn", None, "A"),
    ]
    assert variant_row("dnn", "paper", "mass") == "dnn[paper]"
    # a registered-pairs network of its own (the default hybrid is the one network: row registered+network)
    assert (
        variant_row("registered+network", None, "mass") == "registered+network[registered-trained]"
    )
    assert variant_row("dnn", None, "mass", per_config=True) == "dnn[per-config]"
    assert variant_row("dnn", "paper", "mass", per_config=True) == "dnn[per-config,paper]"
    assert fusion_variants(with_variants({})) == {}
    for bad, msg in [
        ({"x": {"config": "Z", "inputs": "prealigned"}}, "'fusion_variants.x.config' = 'Z'"),
        ({"x": {"config": "A", "inputs": "registered"}}, "registered pairs of 'A'"),
        ({"x": {"config": "D", "inputs": "lidar"}}, "fusion_variants.x.inputs"),
        ({"network": {"config": "D", "inputs": "prealigned"}}, "clashes with the one network"),
    ]:
        with pytest.raises(ConfigError, match=msg):
            fusion_variants(with_variants(bad))


def test_register_prealigned_rewarps_map2_by_the_registration_pose() -> None:
    from traffictwin.evidential.warp import warp_masses
    from traffictwin.fusion.registration_batches import register_prealigned, registered_fusion

    grid = GridSpec(64, 48, 0.5)
    g = np.random.default_rng(0)
    m1 = np.zeros((2, 2, 64, 48), np.float32)
    m1[:, 0] = 0.6
    m1[:, 0, 20:24, 10:30] = 0.0
    m1[:, 1, 20:24, 10:30] = 0.9  # a wall
    map2 = m1.copy()
    noisy = np.array([[1.0, -0.5, 0.05], [0.0, 0.0, 0.0]])
    arrays = {
        "inputs": np.concatenate([m1, g.random(m1.shape).astype(np.float32) * 0.1], 1),
        "label": m1.copy(),
        "rel_pose_noisy": noisy,
        "pair_id": np.array([1000, 1001]),
    }
    out = register_prealigned(arrays, map2, grid)
    ref = registered_fusion(m1, map2, noisy, grid)
    np.testing.assert_array_equal(out["inputs"][:, :2], m1)  # map 1 unchanged
    np.testing.assert_allclose(out["rel_pose_registered"], ref.poses)
    for i in range(2):
        np.testing.assert_allclose(
            out["inputs"][i, 2:], warp_masses(map2[i], ref.poses[i], grid), atol=1e-6
        )
    np.testing.assert_array_equal(out["pair_id"], arrays["pair_id"])
    assert out["reg_accepted"].dtype == bool
    with pytest.raises(ValueError, match="must match map 1"):
        register_prealigned(arrays, map2[:1], grid)


@pytest.mark.parametrize("profile", ["default", "paper"])
def test_early_stopping_cannot_stop_with_the_best_epoch_in_the_last_fifth(profile: str) -> None:
    # with min_delta 0 early stopping counts the same improvements as the checkpoint selection, so
    # a run it ends has run best + 1 + patience epochs; patience >= max_epochs / 5 then keeps the
    # best epoch out of the last fifth of any run that stops early

    cfg = composed(f"profile={profile}")
    t = cfg["fusion_model"]["train"]
    assert t["early_stopping_min_delta"] == 0.0
    assert 5 * t["early_stopping_patience"] >= t["max_epochs"]
