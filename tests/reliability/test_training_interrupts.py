"""Trainers stop on NaN/inf, shards hold finite numbers, a model folder is one unit, and MLflow
runs end FAILED / KILLED when a stage fails or is interrupted."""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from traffictwin.io.npz import check_finite, read_npz, sha256_file, write_npz_deterministic
from traffictwin.io.shards import Dataset, DatasetError, DatasetWriter
from traffictwin.trainer import (
    CKPT_SHA_KEY,
    CheckpointError,
    FiniteGuard,
    TrainingDiverged,
    check_model_pair,
    save_model_files,
)

# ---------------------------------------------------------------------------------------------
# FiniteGuard


def _fake_trainer(lr: float = 0.5, epoch: int = 3, step: int = 17, metrics=None):
    opt = SimpleNamespace(param_groups=[{"lr": lr}])
    return SimpleNamespace(
        optimizers=[opt],
        current_epoch=epoch,
        global_step=step,
        sanity_checking=False,
        callback_metrics=metrics or {},
    )


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_finite_guard_names_stage_epoch_step_lr_and_setting(bad: float) -> None:
    guard = FiniteGuard("train_fusion@B", hint="fusion_model.optim.lr")
    with pytest.raises(TrainingDiverged) as info:
        guard.on_train_batch_end(_fake_trainer(), None, {"loss": torch.tensor(bad)}, None, 0)
    msg = str(info.value)
    # Lightning's current_epoch 3 is the 4th epoch: messages count epochs from 1, like the logs
    assert msg.startswith("train_fusion@B: training diverged at epoch 4, step 17: ")
    assert f"the training loss is {bad}" in msg and "lr=0.5" in msg
    assert "lower fusion_model.optim.lr" in msg
    assert isinstance(info.value, FloatingPointError)  # run_stage's one-line class


def test_finite_guard_passes_finite_values_and_checks_the_monitor() -> None:
    guard = FiniteGuard("s", monitor="val/loss")
    tr = _fake_trainer(metrics={"val/loss": torch.tensor(0.25)})
    guard.on_train_batch_end(tr, None, {"loss": torch.tensor(1e30)}, None, 0)  # large, finite
    guard.on_train_batch_end(tr, None, torch.tensor(2.0), None, 0)  # a bare tensor
    guard.on_train_batch_end(tr, None, None, None, 0)  # nothing returned: nothing to check
    guard.on_validation_end(tr, None)
    tr.callback_metrics["val/loss"] = torch.tensor(float("nan"))
    with pytest.raises(TrainingDiverged, match="val/loss is nan"):
        guard.on_validation_end(tr, None)
    tr.sanity_checking = True
    guard.on_validation_end(tr, None)  # sanity checks are not judged
    FiniteGuard("s").on_validation_end(tr, None)  # no monitor: only the training loss


class _Tiny(torch.nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.lin = torch.nn.Linear(3, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.lin(x).squeeze(-1)


@pytest.mark.integration
def test_build_trainer_adds_a_guard_and_an_infinite_lr_stops_the_run() -> None:
    import lightning as L

    from traffictwin.trainer import NetModule, TrainerSettings, build_trainer

    class Mod(NetModule):
        def training_step(self, batch, batch_idx):
            x, y = batch
            return self.loss_fn(self.net(x), y)

    g = torch.Generator().manual_seed(0)
    ds = torch.utils.data.TensorDataset(
        torch.randn(32, 3, generator=g), torch.randn(32, generator=g)
    )
    dl = torch.utils.data.DataLoader(ds, batch_size=8)
    trainer = build_trainer(TrainerSettings(), max_epochs=2)
    assert sum(isinstance(cb, FiniteGuard) for cb in trainer.callbacks) == 1
    L.seed_everything(0, verbose=False)
    module = Mod(_Tiny(), torch.nn.functional.mse_loss, lr=float("inf"))
    with pytest.raises(TrainingDiverged, match=r"epoch 1, step [12]: .* lr=inf"):
        trainer.fit(module, train_dataloaders=dl)
    # a guard given by the caller is not doubled
    own = FiniteGuard("mine")
    assert build_trainer(TrainerSettings(), max_epochs=1, callbacks=[own]).callbacks.count(own) == 1


# ---------------------------------------------------------------------------------------------
# finite data: writers refuse, readers refuse (a NaN shard with a valid hash)


def test_check_finite_hand_cases() -> None:
    ok = {"i": np.array([1, 2]), "b": np.array([True]), "f": np.zeros((2, 2), np.float32)}
    check_finite(ok, "x")
    bad = {"f": np.array([[0.0, 1.0], [np.nan, np.nan]]), "g": np.array([np.inf])}
    with pytest.raises(
        DatasetError,
        match=r"^x: array 'f' holds 2 NaN and 0 infinite value\(s\) \(first at index \(1, 0\)\)",
    ):
        check_finite(bad, "x")
    with pytest.raises(DatasetError, match=r"array 'g' holds 0 NaN and 1 infinite"):
        check_finite({"g": bad["g"]}, "x")
    check_finite({"g": np.array([np.inf, -np.inf, 1.0])}, "x", allow_inf=("g",))
    with pytest.raises(DatasetError, match="array 'g' holds 1 NaN"):  # NaN is never data
        check_finite({"g": np.array([np.inf, np.nan])}, "x", allow_inf=("g",))


def test_writer_refuses_non_finite_arrays_and_writes_nothing(tmp_path: Path) -> None:
    target = tmp_path / "s.npz"
    with pytest.raises(DatasetError, match=r"s.npz \(refusing to write\): array 'x' holds 1 NaN"):
        write_npz_deterministic(target, {"x": np.array([1.0, np.nan])})
    assert not target.exists() and list(tmp_path.iterdir()) == []
    w = DatasetWriter(tmp_path / "ds", "unit", {}, 0)
    with pytest.raises(DatasetError, match="array 'x' holds 0 NaN and 1 infinite"):
        w.add_shard(0, {"x": np.array([np.inf, 1.0])})
    assert not (tmp_path / "ds" / "shard-00000.npz").exists()
    w.add_shard(0, {"x": np.array([np.inf, 1.0])}, allow_inf=("x",))  # a declared +inf


def test_reader_refuses_a_nan_shard_with_a_valid_hash_naming_the_file(tmp_path: Path) -> None:
    w = DatasetWriter(tmp_path / "ds", "unit", {}, 0)
    w.add_shard(0, {"x": np.ones(3, np.float32)}, split="train")
    w.add_shard(1, {"x": np.array([1.0, np.nan, 2.0], np.float32)}, split="train", check=False)
    w.finalize()
    ds = Dataset(tmp_path / "ds", kind="unit")  # every hash is valid
    assert ds.load_shard(0)["x"].tolist() == [1.0, 1.0, 1.0]
    with pytest.raises(
        DatasetError, match=r"ds/shard-00001.npz: array 'x' holds 1 NaN .*index \(1,\)"
    ):
        ds.load_shard(1)
    with pytest.raises(DatasetError, match="shard-00001.npz"):
        ds.load_all("train")
    with pytest.raises(DatasetError, match="shard-00001.npz"):
        read_npz(tmp_path / "ds" / "shard-00001.npz")


def test_reader_accepts_declared_infinities_only(tmp_path: Path) -> None:
    w = DatasetWriter(tmp_path / "ds", "twin", {}, 0)
    w.add_shard(0, {"thw_true": np.array([np.inf, 2.0])}, allow_inf=("thw_true",))
    w.finalize()
    with pytest.raises(DatasetError, match="array 'thw_true' holds 0 NaN and 1 infinite"):
        Dataset(tmp_path / "ds", kind="twin").load_shard(0)
    got = Dataset(tmp_path / "ds", kind="twin", allow_inf=("thw_true",)).load_shard(0)
    assert got["thw_true"][0] == np.inf


# ---------------------------------------------------------------------------------------------
# model.ckpt + model_meta.json as one unit


def _ckpt(value: float) -> dict:
    return {"state_dict": {"net.w": torch.full((2,), value)}, "traffictwin": {"format": "x"}}


def test_save_model_files_records_the_checkpoint_hash_last(tmp_path: Path) -> None:
    ck, meta = tmp_path / "m" / "model.ckpt", tmp_path / "m" / "model_meta.json"
    digest = save_model_files(ck, _ckpt(1.0), meta, {"cfg": "B"})
    written = json.loads(meta.read_text())
    assert digest == sha256_file(ck) == written[CKPT_SHA_KEY] and written["cfg"] == "B"
    check_model_pair(ck, written)
    # a checkpoint of another training beside this meta: refused, naming the folder
    torch.save(_ckpt(2.0), ck)
    with pytest.raises(
        CheckpointError,
        match=rf"^{tmp_path / 'm'}: model.ckpt and its model_meta.json are not one pair",
    ):
        check_model_pair(ck, written)
    # a meta without the key, or no meta: refused too (the seal cannot be peeled off)
    with pytest.raises(CheckpointError, match="no 'ckpt_sha256'"):
        check_model_pair(ck, {"cfg": "B"})
    with pytest.raises(CheckpointError, match="no model_meta.json beside model.ckpt"):
        check_model_pair(ck, None)
    save_model_files(tmp_path / "only.ckpt", _ckpt(1.0))  # no meta: the checkpoint alone


def test_a_kill_between_checkpoint_and_meta_leaves_no_mismatched_pair(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import traffictwin.io.atomic as atomic

    ck, meta = tmp_path / "model.ckpt", tmp_path / "model_meta.json"
    save_model_files(ck, _ckpt(1.0), meta, {"run": 1})

    def killed(*a, **k):
        raise KeyboardInterrupt  # stands for the process dying before the meta is written

    monkeypatch.setattr(atomic, "write_json_atomic", killed)
    with pytest.raises(KeyboardInterrupt):
        save_model_files(ck, _ckpt(2.0), meta, {"run": 2})
    assert not meta.exists()  # the old meta was removed before the new checkpoint was written
    assert torch.equal(
        torch.load(ck, weights_only=True)["state_dict"]["net.w"], torch.full((2,), 2.0)
    )


def test_risk_loader_refuses_a_mismatched_pair_naming_the_folder(tmp_path: Path) -> None:
    from traffictwin.risk.dave2 import Dave2, Dave2Config
    from traffictwin.risk.model_io import RiskModelError, load_risk_model, save_risk_model

    torch.manual_seed(0)
    a, b = Dave2(Dave2Config()), Dave2(Dave2Config())
    save_risk_model(a, tmp_path / "a", {"variant": "a"})
    save_risk_model(b, tmp_path / "b", {"variant": "b"})
    assert load_risk_model(tmp_path / "a").meta["variant"] == "a"
    (tmp_path / "a" / "model.ckpt").write_bytes((tmp_path / "b" / "model.ckpt").read_bytes())
    with pytest.raises(
        RiskModelError,
        match=rf"^{tmp_path / 'a'}: model.ckpt and its model_meta.json are not one pair",
    ):
        load_risk_model(tmp_path / "a")


# ---------------------------------------------------------------------------------------------
# MLflow runs end FINISHED / FAILED / KILLED


def _status(uri: str, run_id: str) -> str:
    from mlflow.tracking import MlflowClient

    return MlflowClient(uri).get_run(run_id).info.status


def test_run_status_on_success_exception_and_sigterm(
    mlflow_uri: str, tmp_path: Path, monkeypatch
) -> None:
    from traffictwin.mlops.tracking import RunInterrupted, start_run

    monkeypatch.chdir(tmp_path)
    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    with start_run("unit", "ok", profile="ci", stage="unit") as run:
        ok = run.info.run_id
        assert signal.getsignal(signal.SIGTERM) is not before[0]  # handlers installed
    assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)) == before
    with pytest.raises(ValueError, match="boom"):
        with start_run("unit", "fails", profile="ci", stage="unit") as run:
            failed = run.info.run_id
            raise ValueError("boom")
    with pytest.raises(RunInterrupted) as info:
        with start_run("unit", "killed", profile="ci", stage="unit") as run:
            killed = run.info.run_id
            os.kill(os.getpid(), signal.SIGTERM)
            pytest.fail("SIGTERM did not interrupt the run")
    assert info.value.signum == signal.SIGTERM and str(info.value) == "received SIGTERM"
    with pytest.raises(RunInterrupted):
        with start_run("unit", "ctrl-c", profile="ci", stage="unit") as run:
            interrupted = run.info.run_id
            os.kill(os.getpid(), signal.SIGINT)
    assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)) == before
    assert [_status(mlflow_uri, r) for r in (ok, failed, killed, interrupted)] == [
        "FINISHED",
        "FAILED",
        "KILLED",
        "KILLED",
    ]


def test_end_status_rules() -> None:
    from traffictwin.mlops.tracking import RunInterrupted, end_status

    assert end_status(None) == "FINISHED"
    assert end_status(ValueError("x")) == "FAILED"
    assert end_status(RunInterrupted(signal.SIGTERM)) == "KILLED"
    assert end_status(KeyboardInterrupt()) == "KILLED"
    # Lightning turns a Ctrl-C into sys.exit(1): a signal was received, so the run was killed
    assert end_status(SystemExit(1), [signal.SIGINT]) == "KILLED"
