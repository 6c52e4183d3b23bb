"""Resuming a killed training run: same weights, curves and metrics as a run
that was never killed; a changed config starts afresh; the resume folder goes after success."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from test_fusion_training import GRID, TINY, write_prealigned

from traffictwin import resume
from traffictwin import trainer as common
from traffictwin.fusion.training import (
    DataSettings,
    FusionHParams,
    FusionLitModule,
    FusionSettings,
    LoopSettings,
    TrackingSettings,
    fit_fusion,
)
from traffictwin.fusion.training_data import TrainingSet
from traffictwin.trainer import ModelOutputs

pytestmark = pytest.mark.usefixtures("single_torch_thread")

TIMING = ("train_seconds", "train_samples_per_s")


class Killed(Exception):
    """Stands for the process being killed mid-epoch."""


def _fit(tmp_path: Path, out: str, resume_dir: Path | None, tracking: bool = False):
    root = tmp_path / "pre"
    if not root.exists():
        write_prealigned(root)
    d = tmp_path / out
    return fit_fusion(
        TrainingSet(root, "B", {"r": 1.0, "alpha": 10.0}, GRID, 3),
        model=FusionSettings(
            TINY,
            FusionHParams(lr=0.01, lr_patience=0, lr_factor=0.5),
            DataSettings(batch_size=4, train_samples_per_epoch=8, val_samples=4),
            LoopSettings(max_epochs=4),
        ),
        trainer_settings=common.TrainerSettings(),
        outputs=ModelOutputs(
            d / "model.ckpt", d / "model_meta.json", d / "metrics.json", d / "curves.csv"
        ),
        tracking=TrackingSettings(
            run_name="fusion-B", profile="ci", stage="train_fusion@B", enabled=tracking
        ),
        resume_dir=resume_dir,
    )


def _outputs(d: Path) -> tuple[dict, dict, str, dict]:
    ck = torch.load(d / "model.ckpt", weights_only=True)
    metrics = json.loads((d / "metrics.json").read_text())
    meta = json.loads((d / "model_meta.json").read_text())
    assert "mlflow_run_id" not in meta and "mlflow_model_uri" not in meta  # run record only
    return (
        ck["state_dict"],
        {k: v for k, v in metrics.items() if k not in TIMING},
        (d / "curves.csv").read_text(),
        {"epoch": ck["epoch"], "global_step": ck["global_step"], "meta": meta},
    )


def _assert_same(a: Path, b: Path) -> None:
    sa, ma, ca, ia = _outputs(a)
    sb, mb, cb, ib = _outputs(b)
    assert sa.keys() == sb.keys()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    assert ma == mb and ca == cb and ia == ib


@pytest.mark.slow
def test_killed_run_resumes_to_the_weights_of_an_uninterrupted_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, mlflow_uri: str
) -> None:
    _fit(tmp_path, "plain", None)
    # the resume machinery alone changes nothing, and cleans up after itself
    rdir = tmp_path / "resume" / "train_fusion_B"
    _fit(tmp_path, "with_resume", rdir)
    assert not rdir.exists()
    _assert_same(tmp_path / "plain", tmp_path / "with_resume")

    # killed in the second batch of epoch 2 (global step 5; 2 steps per epoch)
    step = FusionLitModule.training_step

    def dying_step(self, batch, batch_idx):
        if self.global_step == 5:
            raise Killed
        return step(self, batch, batch_idx)

    monkeypatch.setattr(FusionLitModule, "training_step", dying_step)
    with pytest.raises(Killed):
        _fit(tmp_path, "resumed", rdir, tracking=True)
    assert (rdir / resume.LAST).is_file() and not (tmp_path / "resumed").exists()
    state = json.loads((rdir / resume.STATE).read_text())
    assert torch.load(rdir / resume.LAST, weights_only=False)["epoch"] == 2
    monkeypatch.setattr(FusionLitModule, "training_step", step)
    res = _fit(tmp_path, "resumed", rdir, tracking=True)
    assert not rdir.exists()
    _assert_same(tmp_path / "plain", tmp_path / "resumed")
    # the resumed run continues the killed run's MLflow run, whose curve has every epoch once
    assert res.run_id == state["mlflow_run_id"]
    import mlflow

    hist = mlflow.MlflowClient().get_metric_history(res.run_id, "val/kld_full")
    assert sorted({m.step for m in hist}) == [0, 1, 2, 3]


def test_prepare_resumes_only_a_matching_fingerprint(tmp_path: Path) -> None:
    d = tmp_path / "r"
    ck, state = resume.prepare(d, "fp-1")
    assert ck is None and state["fingerprint"] == "fp-1"
    (d / resume.LAST).write_bytes(b"state")
    resume.record(d, mlflow_run_id="run-1")
    ck, state = resume.prepare(d, "fp-1")
    assert ck == d / resume.LAST and state["mlflow_run_id"] == "run-1"
    # another rank only reads; a changed config or dataset starts afresh
    assert resume.prepare(d, "fp-2", clear=False) == (None, {})
    assert (d / resume.LAST).exists()
    ck, state = resume.prepare(d, "fp-2")
    assert ck is None and not (d / resume.LAST).exists() and "mlflow_run_id" not in state
    resume.finish(d)
    assert not d.exists()


def test_fingerprint_covers_config_order_free() -> None:
    a = resume.fingerprint({"lr": 0.01, "data": {"hash": "x", "n": 2}})
    assert a == resume.fingerprint({"data": {"n": 2, "hash": "x"}, "lr": 0.01})
    assert a != resume.fingerprint({"lr": 0.02, "data": {"hash": "x", "n": 2}})
    assert a != resume.fingerprint({"lr": 0.01, "data": {"hash": "y", "n": 2}})


def test_progress_bar_only_on_a_terminal(monkeypatch: pytest.MonkeyPatch) -> None:
    import io
    import sys

    class Tty(io.StringIO):
        def isatty(self) -> bool:
            return True

    monkeypatch.setattr(sys, "stderr", io.StringIO())
    assert (
        common.build_trainer(common.TrainerSettings(), max_epochs=1).progress_bar_callback is None
    )
    monkeypatch.setattr(sys, "stderr", Tty())
    assert common.build_trainer(common.TrainerSettings(), max_epochs=1).progress_bar_callback
    t = common.build_trainer(common.TrainerSettings(), max_epochs=1, enable_progress_bar=False)
    assert t.progress_bar_callback is None


@pytest.mark.slow
def test_killed_risk_run_with_mid_epoch_validations_resumes_identically(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The risk trainer validates every n steps (not at epoch ends) and uses dropout: the
    resumed run has the same curves (History rows and the loss since the last validation are
    in the checkpoint) and the same best weights."""
    from test_risk_training import _source, write_synthetic_risk

    from traffictwin.risk.dave2 import Dave2Config
    from traffictwin.risk.training import RiskRegressor, TrainConfig, fit, prepare_split

    write_synthetic_risk(tmp_path, n_shards=3, per_shard=10, outlier_rate=0.0)
    src = _source(tmp_path)
    cfg = Dave2Config(inputs=("disp_sgm",), dropout=0.3)
    tr, va = prepare_split(src, cfg, "train", "risk"), prepare_split(src, cfg, "val", "risk")
    tc = TrainConfig(epochs=3, batch_size=5, lr=1e-3, val_every_n_steps=3, seed=0, min_pred_std=0.0)
    plain = fit(cfg, tr, va, tc, common.TrainerSettings())
    steps_per_epoch = len(tr) // 5
    assert steps_per_epoch % 3 != 0  # validations fall inside epochs

    rdir = tmp_path / "resume"
    step = RiskRegressor.training_step

    def dying_step(self, batch, batch_idx):
        if self.global_step == steps_per_epoch + 2:
            raise Killed
        return step(self, batch, batch_idx)

    monkeypatch.setattr(RiskRegressor, "training_step", dying_step)
    with pytest.raises(Killed):
        fit(cfg, tr, va, tc, common.TrainerSettings(), session=resume.Session(rdir, {"k": 1}))
    monkeypatch.setattr(RiskRegressor, "training_step", step)
    session = resume.Session(rdir, {"k": 1})
    assert session.resume_from == rdir / resume.LAST
    res = fit(cfg, tr, va, tc, common.TrainerSettings(), session=session)
    assert res.history.equals(plain.history) and res.best_step == plain.best_step
    sa, sb = plain.net.state_dict(), res.net.state_dict()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
