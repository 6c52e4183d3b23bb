"""A training's log says what happened and nothing else.

Every training used to print, on a fresh clone too: Lightning's "Checkpoint directory ... exists
and is not empty" (the best checkpoint went into the resume folder, which already held
resume.json), torch's ``LeafSpec`` FutureWarning (from Lightning's CombinedLoader) and
"`weights_only` was not set, defaulting to `False`" (the resume checkpoint saved without saying
what it keeps). And it counted epochs two ways ("epoch 2/2" beside "best epoch 1 of 2"): stored
epochs are 0-based (Lightning's), every line a user reads counts from 1.
"""

from __future__ import annotations

import json
import logging
import re
import warnings
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
from traffictwin.trainer.fit import _quiet_fit

pytestmark = [pytest.mark.usefixtures("single_torch_thread"), pytest.mark.integration]

NOISE = (
    r"Checkpoint directory .* exists and is not empty",
    r"LeafSpec",
    r"`weights_only` was not set",
)
EPOCH_LINE = re.compile(r"epoch (\d+)/(\d+) ")


class Killed(Exception):
    """Stands for the process being killed mid-run."""


def _fit(tmp_path: Path, out: str, resume_dir: Path | None):
    """The cheapest whole training: tiny network, 2 epochs of 2 steps (test_resume's shape)."""
    root = tmp_path / "pre"
    if not root.exists():
        write_prealigned(root)
    d = tmp_path / out
    return fit_fusion(
        TrainingSet(root, "B", {"r": 1.0, "alpha": 10.0}, GRID, 3),
        model=FusionSettings(
            TINY,
            FusionHParams(lr=0.01),
            DataSettings(batch_size=4, train_samples_per_epoch=8, val_samples=4),
            LoopSettings(max_epochs=2),
        ),
        trainer_settings=common.TrainerSettings(),
        outputs=ModelOutputs(
            d / "model.ckpt", d / "model_meta.json", d / "metrics.json", d / "curves.csv"
        ),
        tracking=TrackingSettings(
            run_name="fusion-B", profile="ci", stage="train_fusion@B", enabled=False
        ),
        resume_dir=resume_dir,
    )


def _noise(caught: list[warnings.WarningMessage], text: str) -> list[str]:
    """The unwanted messages among the recorded warnings and the captured log / output ``text``."""
    found = [
        f"{w.category.__name__}: {w.message}"
        for w in caught
        if any(re.search(p, str(w.message)) for p in NOISE)
    ]
    found += [ln for ln in text.splitlines() if any(re.search(p, ln) for p in NOISE)]
    return found


def _epoch_lines(caplog: pytest.LogCaptureFixture) -> list[tuple[int, int]]:
    """``(k, N)`` of History's "epoch k/N ..." log lines."""
    out = []
    for r in caplog.records:
        m = EPOCH_LINE.match(r.getMessage()) if r.name == "traffictwin.trainer" else None
        if m:
            out.append((int(m.group(1)), int(m.group(2))))
    return out


def test_a_fresh_training_is_quiet_and_counts_epochs_from_one(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, capfd: pytest.CaptureFixture[str]
) -> None:
    caplog.set_level(logging.INFO)
    rdir = tmp_path / "resume" / "train_fusion-B"  # as the stages run it: with a resume folder
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = _fit(tmp_path, "run", rdir)
    out, err = capfd.readouterr()
    assert _noise(caught, caplog.text + out + err) == []
    assert not rdir.exists()  # removed after success, as before

    # log lines count from 1; the stored epochs (checkpoint, meta, metrics, curves) from 0
    assert _epoch_lines(caplog) == [(1, 2), (2, 2)]
    d = tmp_path / "run"
    metrics = json.loads((d / "metrics.json").read_text())
    meta = json.loads((d / "model_meta.json").read_text())
    ck = torch.load(d / "model.ckpt", weights_only=True)
    assert [r["epoch"] for r in res.history] == [0, 1]
    assert (d / "curves.csv").read_text().splitlines()[1].startswith("0,")
    assert metrics["best_epoch"] == meta["best_epoch"] == ck["epoch"] in (0, 1)
    assert metrics["epochs"] == 2


def test_a_resumed_training_is_quiet_and_goes_on_counting(
    tmp_path: Path,
    caplog: pytest.LogCaptureFixture,
    capfd: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Resuming finds the killed run's best checkpoint in its folder (by design): no warning about
    it; the resumed run logs its second epoch as "epoch 2/2"."""
    caplog.set_level(logging.INFO)
    rdir = tmp_path / "resume" / "train_fusion-B"
    step = FusionLitModule.training_step

    def dying_step(self, batch, batch_idx):
        if self.global_step == 3:  # the second step of epoch 2 (2 steps per epoch)
            raise Killed
        return step(self, batch, batch_idx)

    monkeypatch.setattr(FusionLitModule, "training_step", dying_step)
    with pytest.raises(Killed):
        _fit(tmp_path, "run", rdir)
    assert (rdir / resume.LAST).is_file() and (rdir / common.BEST_DIR / "best.ckpt").is_file()
    monkeypatch.setattr(FusionLitModule, "training_step", step)
    capfd.readouterr()
    caplog.clear()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        _fit(tmp_path, "run", rdir)
    out, err = capfd.readouterr()
    assert _noise(caught, caplog.text + out + err) == []
    assert any("resuming train_fusion@B" in r.getMessage() for r in caplog.records)
    assert _epoch_lines(caplog) == [(2, 2)]
    assert not rdir.exists()


def test_other_warnings_still_pass() -> None:
    """The training's filters are exact: a warning of ours, or another of Lightning's, is shown."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with _quiet_fit(Path("/some/run/best")):
            warnings.warn("something else is deprecated", FutureWarning, stacklevel=1)
            warnings.warn(
                "Checkpoint directory /another/folder exists and is not empty.",
                UserWarning,
                stacklevel=1,
            )
            warnings.warn(
                "Checkpoint directory /some/run/best exists and is not empty.",
                UserWarning,
                stacklevel=1,
            )
            # the LeafSpec message raised from anywhere but Lightning's _pytree module
            warnings.warn(
                "`isinstance(treespec, LeafSpec)` is deprecated, use ...",
                FutureWarning,
                stacklevel=1,
            )
    assert [str(w.message) for w in caught] == [
        "something else is deprecated",
        "Checkpoint directory /another/folder exists and is not empty.",
        "`isinstance(treespec, LeafSpec)` is deprecated, use ...",
    ]
