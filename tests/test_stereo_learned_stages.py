"""Stages train_stereo and stereo_learned on a tiny rendered data set: the model files, the
aligned data/stereo_learned shards, the test metrics, and bad inputs refused before anything is
written."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pipelines import disparity as disparity_stage
from pipelines import stereo_learned as stage
from pipelines import train_stereo
from traffictwin.config import ConfigError
from traffictwin.grid import GridSpec
from traffictwin.io.shards import Dataset, DatasetError, DatasetWriter
from traffictwin.risk.dataset import RiskDataSpec, assign_splits, frame_table, make_shard
from traffictwin.risk.metric import RiskConfig
from traffictwin.risk.stereo_training import (
    StereoData,
    StereoModelError,
    StereoTrainConfig,
    fit_stereo,
    load_pairs,
    load_stereo_model,
)
from traffictwin.sim.camera import StereoCamera
from traffictwin.sim.driving import DrivingConfig
from traffictwin.stereo import evaluation as E
from traffictwin.stereo.figures import fault_free_test_examples
from traffictwin.stereo.network import StereoNetSpec
from traffictwin.stereo.sgm import SgmParams
from traffictwin.trainer import ModelOutputs, TrainerSettings

SPEC = RiskDataSpec(
    DrivingConfig(frames=3, warmup=1.0, fault_delay=0.0, fault_vertical=0.0),
    StereoCamera(width=128, height=64),
    GridSpec(128, 96, 0.64),
    RiskConfig(subject_length=4.8, subject_width=1.9),
    1.5,  # critical THW (s)
)
SGM = SgmParams(16, 5, 10, 100, 2, False)
NET = StereoNetSpec(
    max_disparity=32,
    stride=4,
    feature_channels=8,
    aggregation_channels=4,
    aggregation_layers=1,
    refine_channels=8,
    refine_dilations=(1, 2),
)
TRAIN = StereoTrainConfig(
    batch_size=2,
    crop_height=32,
    crop_width=64,
    max_epochs=2,
    steps_per_epoch=2,
    max_train_frames=0,
    val_frames=2,
    early_stopping_patience=2,
    lr=1e-3,
    lr_factor=0.5,
    lr_patience=0,
    weight_decay=0.0,
    rel_weight=1.0,
    coarse_weight=0.5,
    valid_density=0.8,
)


def _risk(root: Path, seed: int = 3, n: int = 5) -> Path:
    splits = assign_splits(n, seed)
    w = DatasetWriter(root, "risk", {"seed": seed}, seed)
    rows = {}
    for i in range(n):
        arrays, rows[i] = make_shard(seed, i, SPEC)
        w.add_shard(i, arrays, split=splits[i])
    w.add_table("frames.csv", frame_table(rows, splits))
    w.finalize(extra={"camera": SPEC.camera.intrinsics()})
    return root


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("stereo_learned")
    _risk(root / "risk")
    disparity_stage.run(SGM, 1, [0.0, 10.0, 30.0, 90.0], src=root / "risk", out=root / "disparity")
    settings = TrainerSettings(accelerator="cpu", devices=1, precision="32-true")
    model = root / "model"
    fit_stereo(
        StereoData(root / "risk", 0),
        spec=NET,
        train=TRAIN,
        trainer_settings=settings,
        outputs=ModelOutputs(model / "model.ckpt", model / "model_meta.json", root / "m.json"),
    )
    return root


def test_train_writes_a_sealed_model_with_its_spread_threshold(data: Path) -> None:
    meta = json.loads((data / "model" / "model_meta.json").read_text())
    assert meta["spread_threshold_px"] > 0 and meta["valid_density"] == 0.8
    m = json.loads((data / "m.json").read_text())
    assert {"val/epe", "val/bad1", "spread_threshold_px", "calibration/spread_decile9/epe"} <= set(
        m
    )
    net = load_stereo_model(data / "model")
    assert net.meta["spread_threshold_px"] == meta["spread_threshold_px"]
    # an edited threshold in the JSON is refused (the checkpoint's sealed copy differs)
    edited = data / "edited"
    edited.mkdir()
    (edited / "model.ckpt").write_bytes((data / "model" / "model.ckpt").read_bytes())
    (edited / "model_meta.json").write_text(json.dumps({**meta, "spread_threshold_px": 99.0}))
    with pytest.raises(StereoModelError):
        load_stereo_model(edited)
    with pytest.raises(StereoModelError, match="not found"):
        load_stereo_model(data / "nowhere")


def test_stereo_learned_writes_aligned_shards_and_test_metrics(data: Path) -> None:
    m = stage.run(data / "model", data / "risk", data / "disparity", data / "out", n_boot=20)
    risk, out = Dataset(data / "risk", kind="risk"), Dataset(data / "out", kind="stereo_learned")
    assert len(out.shards) == len(risk.shards)
    thr = json.loads((data / "model" / "model_meta.json").read_text())["spread_threshold_px"]
    for a, b in zip(risk.shards, out.shards):
        assert (a["count"], a["split"]) == (b["count"], b["split"])
    sh, src = out.load_shard(0), risk.load_shard(0)
    assert set(sh) == {"disp_learned", "disp_learned_spread"}
    assert (
        sh["disp_learned"].dtype == np.float32 and sh["disp_learned"].shape == src["disp_gt"].shape
    )
    invalid = sh["disp_learned_spread"] > thr
    assert (sh["disp_learned"][invalid] == -1).all() and (sh["disp_learned"][~invalid] >= 0).all()
    for source in ("sgm", "learned"):
        for mask in ("common", "own"):
            for k in (
                "epe",
                "bad1",
                "bad2",
                "density",
                "z10-30m_relerr_median",
                "crit_obj_relerr_p90",
            ):
                assert f"{source}/{mask}/{k}" in m and f"{source}/{mask}/{k}_lo" in m
    assert m["sgm/common/density"] == pytest.approx(m["learned/common/density"])
    assert "diff_learned_minus_sgm/common/epe_hi" in m and m["test/frames"] > 0
    json.dumps(m, allow_nan=False)
    # the example figure (plot_data): evenly spaced fault-free test frames, the learned column
    # showing the stage's output for them
    fig = fault_free_test_examples(risk, Dataset(data / "disparity", kind="disparity"), out, rows=2)
    frames = risk.table("frames.csv").sort_values(["shard", "idx"])
    picks = frames[(frames.split == "test") & (frames.fault == "none")]
    first = picks.iloc[0]
    learned = out.load_shard(int(first.shard))["disp_learned"][int(first.idx)]
    rows = len(np.unique(np.linspace(0, len(picks) - 1, 2).round()))
    assert len(fig.axes) == 5 * rows + 4 * rows  # five panels and four colour bars per row
    shown = fig.axes[3].images[0].get_array()
    assert np.allclose(
        np.ma.filled(np.ma.masked_invalid(shown), -1.0), np.where(learned >= 0, learned, -1.0)
    )


def test_stereo_learned_refuses_bad_inputs_and_writes_nothing(data: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    with pytest.raises(DatasetError, match="no manifest.json"):
        stage.run(data / "model", tmp_path / "no_risk", data / "disparity", out, n_boot=20)
    other = _risk(tmp_path / "other_risk", seed=4, n=1)
    with pytest.raises(DatasetError, match="made from another data/risk"):
        stage.run(data / "model", other, data / "disparity", out, n_boot=20)
    with pytest.raises(StereoModelError):
        stage.run(tmp_path / "no_model", data / "risk", data / "disparity", out, n_boot=20)
    assert not out.exists()


def test_train_stereo_rejects_a_crop_narrower_than_the_disparity_range() -> None:
    p = {
        "stereo_model": {
            "architecture": NET.as_dict(),
            "train": {**vars(TRAIN), "crop_width": 32},
            "holdout_templates": [],
        }
    }
    with pytest.raises(ConfigError, match="crop_width.*must exceed.*max_disparity"):
        train_stereo.model_config(p)
    p["stereo_model"]["architecture"]["stride"] = 3
    with pytest.raises(ConfigError, match="stereo_model.architecture"):
        train_stereo.model_config(p)


@pytest.mark.parametrize("offsets", [0, 2])
def test_sgm_mode_trains_on_data_disparity_and_keeps_sgm_validity(
    data: Path, tmp_path: Path, offsets: int
) -> None:
    """With or without the local search: SGM's valid pixels only, a correction within its bounds
    (the residual's, plus the search's half-width), and a spread threshold that keeps them all."""
    spec = StereoNetSpec(
        base="sgm",
        refine_channels=4,
        refine_dilations=(1,),
        refine_stride=1,
        max_residual_px=1.0,
        local_cost_offsets=offsets,
        local_cost_step_px=0.25,
        local_cost_window=3,
    )
    bound = 0.25 * offsets if offsets else 1.0  # the largest spread it reports
    model = tmp_path / "model"
    outputs = ModelOutputs(model / "model.ckpt", model / "model_meta.json", tmp_path / "m.json")
    settings = TrainerSettings(accelerator="cpu", devices=1, precision="32-true")
    with pytest.raises(DatasetError, match="data/disparity"):
        fit_stereo(
            StereoData(data / "risk", 0),
            spec=spec,
            train=TRAIN,
            trainer_settings=settings,
            outputs=outputs,
        )
    assert not model.exists()
    fit_stereo(
        StereoData(data / "risk", 0, data / "disparity"),
        spec=spec,
        train=TRAIN,
        trainer_settings=settings,
        outputs=outputs,
    )
    meta = json.loads((model / "model_meta.json").read_text())
    assert meta["architecture"]["base"] == "sgm" and meta["spread_threshold_px"] == bound
    m = stage.run(model, data / "risk", data / "disparity", tmp_path / "out", n_boot=20)
    out, sgm = Dataset(tmp_path / "out", kind="stereo_learned"), Dataset(data / "disparity")
    for i in range(len(out.shards)):
        d, s = out.load_shard(i)["disp_learned"], sgm.load_shard(i)["disp_sgm"]
        assert np.array_equal(d < 0, s < 0)  # density = SGM's
        assert np.abs(d - s)[s >= 0].max() <= 1.0 + 0.25 * offsets + 1e-5  # bounded
        assert (out.load_shard(i)["disp_learned_spread"] <= bound).all()  # none masked
    assert m["learned/own/density"] == pytest.approx(m["sgm/own/density"])


def test_generalisation_model_never_sees_its_templates_and_is_scored_on_them(
    data: Path, tmp_path: Path
) -> None:
    """A model trained without the test sequences' road templates: its training and validation
    frames hold none of them, and stereo_learned scores it beside the full model and SGM on
    exactly those templates' fault-free test frames, with paired differences."""
    import pandas as pd

    frames = pd.read_csv(data / "risk" / "frames.csv")
    held = sorted(set(frames[frames.split == "test"].template.astype(str)))
    seen = frames[~frames.template.astype(str).isin(held) & (frames.fault == "none")]
    assert held and {"train", "val"} <= set(seen.split), "the tiny data set must keep both splits"
    tr = load_pairs(data / "risk", "train", exclude_templates=tuple(held))
    assert len(tr["left"]) == int((seen.split == "train").sum())
    with pytest.raises(DatasetError, match="no fault-free 'test' frames"):
        load_pairs(data / "risk", "test", exclude_templates=tuple(held))
    model = tmp_path / "holdout"
    fit_stereo(
        StereoData(data / "risk", 0, exclude_templates=tuple(held)),
        spec=NET,
        train=TRAIN,
        trainer_settings=TrainerSettings(accelerator="cpu", devices=1, precision="32-true"),
        outputs=ModelOutputs(model / "model.ckpt", model / "model_meta.json", tmp_path / "m.json"),
    )
    assert json.loads((model / "model_meta.json").read_text())["holdout_templates"] == held
    assert json.loads((tmp_path / "m.json").read_text())["train_frames"] == len(tr["left"])
    m = stage.run(
        data / "model",
        data / "risk",
        data / "disparity",
        tmp_path / "out",
        n_boot=20,
        holdout_model=model,
    )
    g = m["generalisation"]
    test = frames[(frames.split == "test") & (frames.fault == "none")]
    assert g["templates"] == held and g["test/frames"] == len(test)
    assert g["test/sequences"] == test.scenario.nunique()
    for source in ("sgm", "learned", "holdout"):
        assert f"{source}/own/crit_obj_relerr_median" in g and f"{source}/own/epe_lo" in g
    # the full model and SGM on those frames are the whole test split's figures here (every test
    # frame is of a held-out template), so they equal the main block's
    assert g["learned/own/epe"] == pytest.approx(m["learned/own/epe"])
    assert g["sgm/common/epe"] != g["holdout/common/epe"]
    d = g["diff_holdout_minus_learned/common/epe"]
    assert d == pytest.approx(g["holdout/common/epe"] - g["learned/common/epe"])
    assert g["diff_holdout_minus_sgm/own/crit_obj_relerr_median_lo"] is not None or (
        g["holdout/own/crit_obj_relerr_median"] is None
    )
    json.dumps(m, allow_nan=False)
    # a model without held-out templates is refused for this role; no frames of them: a reason
    with pytest.raises(DatasetError, match="names no held-out road templates"):
        stage.run(
            data / "model",
            data / "risk",
            data / "disparity",
            tmp_path / "out2",
            n_boot=20,
            holdout_model=data / "model",
        )
    assert not (tmp_path / "out2").exists()
    assert stage.generalisation(["nowhere"], [], [], 20) == {
        "templates": ["nowhere"],
        "why": "no fault-free test frame of the held-out road templates",
    }


def test_train_stereo_holdout_needs_a_template(monkeypatch: pytest.MonkeyPatch) -> None:
    p = {
        "seed": 0,
        "stereo_model": {
            "architecture": NET.as_dict(),
            "train": vars(TRAIN),
            "holdout_templates": [],
        },
    }
    monkeypatch.setattr(train_stereo, "params", lambda: p)
    with pytest.raises(ConfigError, match="'stereo_model.holdout_templates' is empty"):
        train_stereo.main(["--holdout"])


def test_evaluate_reads_every_metric_from_the_same_resamples_as_statistic_ci() -> None:
    """One pass of resamples for all metrics gives exactly the intervals that one
    statistic_ci call per metric gives (same seed, same clusters)."""
    from traffictwin.stats import statistic_ci
    from traffictwin.stereo.metrics import ERROR_EDGES

    rng = np.random.default_rng(5)
    n, e = 30, len(ERROR_EDGES)
    sequences = rng.integers(0, 7, size=n)

    def sums(scale: float) -> dict[str, np.ndarray]:
        n_gt = rng.integers(50, 100, size=n)
        cnt = rng.integers(10, 50, size=n)
        return {
            "n_gt": n_gt,
            "n": cnt,
            "abs": rng.random(n) * cnt * scale,
            "bad1": rng.integers(0, 10, size=n),
            "bad2": rng.integers(0, 5, size=n),
            "bands": rng.integers(0, 3, size=(n, 3, e)),
            "crit": rng.integers(0, 3, size=(n, e)),
            "crit_n_gt": rng.integers(20, 40, size=n),
            "crit_n": rng.integers(0, 20, size=n),
        }

    s = {f"{src}/{m}": sums(k) for k, src in ((1.0, "sgm"), (0.5, "learned")) for m in E.MASKS}
    got = E.evaluate(s, sequences, n_boot=50, seed=3)
    codes, inv = np.unique(sequences, return_inverse=True)
    g = len(codes)
    per = {
        k: {f: np.stack([v[f][inv == j].sum(0) for j in range(g)]) for f in v} for k, v in s.items()
    }

    def w(idx: np.ndarray) -> np.ndarray:
        return np.bincount(idx, minlength=g).astype(np.float64)

    for key, metric in (("learned/own", "epe"), ("sgm/common", "crit_obj_relerr_p90")):
        ci = statistic_ci(
            lambda i, k=key, m=metric: E.statistics(per[k], w(i))[m], g, n_boot=50, seed=3
        )
        assert (got[f"{key}/{metric}"], got[f"{key}/{metric}_lo"], got[f"{key}/{metric}_hi"]) == (
            ci.estimate,
            ci.lo,
            ci.hi,
        )
    ci = statistic_ci(
        lambda i: (
            E.statistics(per["learned/own"], w(i))["epe"]
            - E.statistics(per["sgm/own"], w(i))["epe"]
        ),
        g,
        n_boot=50,
        seed=3,
    )
    k = "diff_learned_minus_sgm/own/epe"
    assert (got[k], got[k + "_lo"], got[k + "_hi"]) == (ci.estimate, ci.lo, ci.hi)
