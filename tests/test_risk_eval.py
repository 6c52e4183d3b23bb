"""Risk evaluation: metric formulas on hand cases, baselines, the whole suite, findings text."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from _acceptance import thresholds
from test_risk_training import camera_intrinsics, render_frame, write_synthetic_risk

from traffictwin.io.shards import Dataset
from traffictwin.risk.baselines import (
    GeometricParams,
    constant_predictions,
    geometric_distance,
    geometric_risk,
)
from traffictwin.risk.charts import roc_points
from traffictwin.risk.dave2 import Dave2, Dave2Config
from traffictwin.risk.evaluation import (
    PAPER,
    SuiteSettings,
    classification_metrics,
    confusion_table,
    evaluate,
    evaluate_suite,
    example_indices,
    label_agreement,
    main_series,
    regression_metrics,
    roc_auc,
    tracking_metrics,
)
from traffictwin.risk.findings import findings
from traffictwin.risk.metric import thw_to_risk
from traffictwin.risk.model_io import load_risk_model, save_risk_model
from traffictwin.risk.training import RiskSource

RISK = thresholds("risk")  # acceptance.risk


def test_classification_hand_case() -> None:
    y = np.array([0.5, 0.5, 0.01, 0.01, 0.2])
    p = np.array([0.4, 0.02, 0.0, 0.3, 0.5])
    m = classification_metrics(y, p, 1.5)
    assert m["confusion"] == {"tp": 2, "fp": 1, "fn": 1, "tn": 1}
    assert m["accuracy"] == pytest.approx(3 / 5)
    assert m["precision"] == pytest.approx(2 / 3) and m["recall"] == pytest.approx(2 / 3)
    assert m["balanced_accuracy"] == pytest.approx((2 / 3 + 1 / 2) / 2)
    assert m["f1"] == pytest.approx(2 / 3)
    assert m["roc_auc"] == pytest.approx(5 / 6)
    from sklearn.metrics import roc_auc_score

    assert m["roc_auc"] == pytest.approx(roc_auc_score(y > 1 / 30, p))
    # at 1.0 s (risk > 0.05): 0.02 is no longer... still uncritical; 0.01 / 0.0 unchanged
    m1 = classification_metrics(y, p, 1.0)
    assert m1["confusion"] == {"tp": 2, "fp": 1, "fn": 1, "tn": 1}
    # boundary: exactly the threshold is NOT critical (THW < 1.5 s is)
    assert (
        classification_metrics(np.array([1 / 30, 0.5]), np.array([1 / 30, 0.5]), 1.5)["confusion"][
            "tn"
        ]
        == 1
    )


def test_undefined_classification_metrics_are_nan() -> None:
    """Recall needs actual critical frames, specificity actual uncritical ones (NaN -> null in
    risk.json, n/a in the report); precision without predicted critical frames is 0."""
    m = classification_metrics(np.array([0.0, 0.01]), np.array([0.5, 0.0]), 1.5)
    assert np.isnan(m["recall"]) and np.isnan(m["f1"]) and np.isnan(m["balanced_accuracy"])
    assert m["specificity"] == 0.5 and m["precision"] == 0.0
    m = classification_metrics(np.array([0.5, 0.5]), np.array([0.0, 0.5]), 1.5)
    assert np.isnan(m["specificity"]) and m["recall"] == 0.5 and m["precision"] == 1.0


def test_paper_table1_reproduces_paper_accuracy() -> None:
    c = PAPER["confusion"]
    y = np.r_[
        np.full(c["tp"], 0.5), np.full(c["fn"], 0.5), np.full(c["fp"], 0.0), np.full(c["tn"], 0.0)
    ]
    p = np.r_[
        np.full(c["tp"], 0.5), np.full(c["fn"], 0.0), np.full(c["fp"], 0.5), np.full(c["tn"], 0.0)
    ]
    m = classification_metrics(y, p, 1.5)
    assert m["confusion"] == c
    assert round(100 * m["accuracy"], 2) == 72.87
    assert round(m["confusion_pct"]["tp"], 2) == 63.16  # Table 1: 63,16 %


def test_regression_metrics_and_auc_ties() -> None:
    y = np.array([0.0, 0.1, 0.2, 0.4])
    p = np.array([0.1, 0.1, 0.0, 0.4])
    m = regression_metrics(y, p, thw_cap=10, critical_s=1.5)
    assert m["test/mse"] == pytest.approx((0.01 + 0 + 0.04 + 0) / 4)
    assert m["test/mae"] == pytest.approx(0.3 / 4)
    # THW: y -> [10, 0.5, 0.25, 0.125], p -> [0.5, 0.5, 10, 0.125]
    assert m["test/thw_mae_s"] == pytest.approx((9.5 + 0 + 9.75 + 0) / 4)
    assert roc_auc(np.array([True, False]), np.array([0.3, 0.3])) == 0.5
    assert np.isnan(roc_auc(np.array([True, True]), np.array([0.1, 0.2])))
    with pytest.raises(ValueError, match="differ in length"):
        regression_metrics(y, p[:2], critical_s=1.5)
    agree = label_agreement(np.array([0.5, 0.0, 0.04]), np.array([0.5, 0.1, 0.0]), (1.5, 1.0))
    assert agree["class_agreement_at_1.5s"] == pytest.approx(1 / 3)


def test_constant_baselines_median_is_majority_class() -> None:
    train = np.array([0.0, 0.0, 0.2, 0.3, 0.5])  # 3 of 5 critical at 1.5 s
    c = constant_predictions(train, 4)
    assert np.allclose(c["train_mean"], 0.2) and np.allclose(c["train_median"], 0.2)
    y = np.array([0.5, 0.0, 0.3, 0.0])
    m = classification_metrics(y, c["train_median"], 1.5)
    assert m["confusion"] == {"tp": 2, "fp": 2, "fn": 0, "tn": 0}


def test_geometric_baseline_one_vehicle_at_known_distance() -> None:
    cam = camera_intrinsics(192, 96)
    params = GeometricParams(subject_length=4.8, subject_width=1.9, min_pixels=10)
    depths = [4.0, 10.0, 25.0]
    disp = np.stack([render_frame(cam, z)[0] for z in depths] + [render_frame(cam, None)[0]])
    dist = geometric_distance(disp, cam, params)
    expect = np.array(depths) + cam["mount_x"] - 4.8 / 2  # free distance from the front bumper
    assert np.allclose(dist[:3], expect, atol=1e-3)
    assert np.isinf(dist[3])  # only road: nothing in the corridor above min_height
    speed = np.array([8.0, 8.0, 16.0, 8.0])
    _, thw, risk = geometric_risk(disp, speed, cam, params)
    assert np.allclose(thw[:3], expect / speed[:3], atol=1e-3)
    assert np.allclose(risk, thw_to_risk(thw)) and risk[3] == 0
    # a vehicle outside the corridor (3.5 m to the side) is ignored
    side = render_frame(cam, 10.0)[0]
    shift = int(round(cam["fx"] * 3.5 / 10.0))
    moved = np.zeros_like(side)
    moved[:, shift:] = side[:, :-shift]
    ground = render_frame(cam, None)[0]
    moved = np.where(moved > ground, moved, ground)
    assert np.isinf(geometric_distance(moved[None], cam, params))[0]
    with pytest.raises(ValueError, match="camera intrinsics"):
        geometric_distance(disp, {"fx": 1.0}, params)
    with pytest.raises(ValueError, match="intrinsics are for"):
        geometric_distance(disp[:, :50], cam, params)


def test_geometric_baseline_with_the_project_camera_and_sgm() -> None:
    """Render a car with the risk-data stereo camera; GT and SGM disparity give the true free distance."""
    from traffictwin.sim.camera import StereoCamera
    from traffictwin.sim.scene import Boxes, Cls
    from traffictwin.stereo.sgm import compute_disparity

    cam = StereoCamera(width=320, height=160, noise_std=0.0)
    L = 4.8
    car = Boxes(center=[[15.0, 0.0]], size=[[4.5, 1.8, 1.5]], yaw=[0.0], cls=[int(Cls.CAR)])
    fr = cam.render_pair((0.0, 0.0, 0.0), car)
    expect = 15.0 - 4.5 / 2 - L / 2  # rear face of the car minus the subject's front bumper
    params = GeometricParams(subject_length=L, subject_width=1.9, min_pixels=10)
    d_gt = geometric_distance(fr["disp_gt"][None], cam.intrinsics(), params)[0]
    assert d_gt == pytest.approx(expect, abs=0.05)
    sgm = compute_disparity(fr["left"], fr["right"], num_disparities=32)
    d_sgm = geometric_distance(sgm[None], cam.intrinsics(), params)[0]
    assert d_sgm == pytest.approx(expect, rel=0.1)


def _tiny_models(tmp: Path) -> dict:
    out = {}
    for i, (name, inputs, speed, label) in enumerate(
        [
            ("rgbd", ("rgb", "disp_sgm"), False, "risk_thw_paper"),
            ("gtdisp", ("rgb", "disp_gt"), False, "risk_thw_paper"),
            ("rgbd_speed", ("rgb", "disp_sgm"), True, "risk_thw_paper"),
            ("rgbd_fov", ("rgb", "disp_sgm"), False, "risk_thw_fov"),
        ]
    ):
        torch.manual_seed(i)
        net = Dave2(Dave2Config(inputs=inputs, use_speed=speed))
        save_risk_model(net, tmp / name, {"label": label, "variant": name})
        out[name] = load_risk_model(tmp / name)
    return out


def test_evaluate_suite_on_synthetic_data(tmp_path: Path) -> None:
    write_synthetic_risk(tmp_path, n_shards=4, per_shard=8)
    src = RiskSource(
        tmp_path / "data" / "risk",
        tmp_path / "data" / "disparity",
        tmp_path / "data" / "orb" / "orb.csv",
    )
    models = _tiny_models(tmp_path / "models")
    params = GeometricParams(subject_length=4.5, subject_width=1.8)
    metrics, pred = evaluate_suite(
        src,
        models,
        SuiteSettings(
            thresholds_s=(1.5, 1.0),
            primary_label="risk_thw_paper",
            geometric=params,
            acceptance=RISK,
        ),
    )
    test = src.split_frames("test")
    assert sorted(pred["frame_id"]) == sorted(test["frame_id"])
    for v, m in models.items():
        lab = m.meta["label"]
        e = metrics["models"][v]
        assert e["label"] == lab
        assert e["test/mse"] == pytest.approx(np.mean((pred[f"pred_{v}"] - pred[lab]) ** 2))
        assert e["at_1.5s"]["confusion"]["tp"] + e["at_1.5s"]["confusion"]["fn"] == int(
            (pred[lab] > 1 / 30).sum()
        )
        assert "at_1s" in e
    # the synthetic geometry is exact up to SGM noise: the geometric baseline beats a constant by far
    geo = metrics["region"]["predictors"]["geometric_sgm"]
    const = metrics["region"]["predictors"]["train_median"]
    assert geo["risk_thw_fov"]["test/mse"] < 0.5 * const["risk_thw_fov"]["test/mse"]
    assert geo["risk_thw_fov"]["test/mse"] <= geo["risk_thw_paper"]["test/mse"]
    assert metrics["baselines"]["train_median"]["value"] == pytest.approx(
        float(np.median(src.split_frames("train")["risk_thw_paper"]))
    )
    assert metrics["n_frames"]["orb_outliers_dropped"] == src.n_orb_outliers
    json.dumps(metrics, allow_nan=False)  # strict JSON (NaN -> null)
    assert metrics["main_variant"] == "rgbd"  # the first model when none is named
    assert set(metrics["baselines"]) == {
        "train_mean",
        "train_median",
        "speed_only",
        "geometric_sgm",
        "geometric_gt",
    }
    # the GT-disparity geometric baseline (oracle) sees the exact geometry: at least as good as SGM
    gt = metrics["region"]["predictors"]["geometric_gt"]
    assert gt["risk_thw_fov"]["test/mse"] <= geo["risk_thw_fov"]["test/mse"] + 1e-4
    assert {"pred_speed_only", "pred_geometric_sgm", "pred_geometric_gt"} <= set(pred.columns)
    text = findings(metrics)
    ratio = metrics["models"]["rgbd"]["test/mse"] / PAPER["test/mse"]
    assert f"**Paper comparison (rgbd, label risk_thw_paper):** test MSE {ratio:.2f}×" in text
    assert "camera_fov" in text
    reg = metrics["region"]["predictors"]
    for per in reg.values():  # skill = 1 - MSE / MSE(train mean) of the same label
        for lab, e in per.items():
            assert e["skill"] == pytest.approx(
                1 - e["test/mse"] / reg["train_mean"][lab]["test/mse"]
            )
    assert reg["train_mean"]["risk_thw_fov"]["skill"] == pytest.approx(0.0)


def test_findings_from_hand_metrics_and_missing_parts() -> None:
    at = {
        "accuracy": 0.8,
        "balanced_accuracy": 0.75,
        "f1": 0.85,
        "roc_auc": 0.9,
        "critical_fraction_true": 0.6,
    }
    metrics = {
        "thresholds_s": [1.5, 1.0],
        "main_variant": "rgbd",
        "models": {
            # findings tells variants apart by their inputs (as evaluate_suite records them)
            "rgbd": {
                "label": "risk_thw_paper",
                "inputs": ["rgb", "disp_sgm"],
                "speed": False,
                "test/mse": 0.01,
                "test/n": 100,
                "at_1.5s": at,
            },
            "rgb": {
                "label": "risk_thw_paper",
                "inputs": ["rgb"],
                "speed": False,
                "test/mse": 0.02,
                "test/n": 100,
                "at_1.5s": {**at, "accuracy": 0.7},
            },
        },
        "baselines": {
            "train_median": {"at_1.5s": {"accuracy": 0.6}},
            "train_mean": {"test/mse": 0.04},
        },
    }
    text = findings(metrics)
    # 0.01 / 0.0147 = 0.68: the test MSE against the paper's; the scores: the results table
    assert "test MSE 0.68× the paper's (below it)" in text
    assert "80.00 %" not in text and "72.87 %" not in text
    # metrics without intervals or differences (an older risk.json): no claims
    assert "beats" not in text and "Learning vs geometry" not in text
    assert findings({"models": {}}) == "- No risk network was evaluated."
    # None (undefined metric) leaves its part out, not crashing
    metrics["models"]["rgbd"]["test/mse"] = None
    assert "Paper comparison" not in findings(metrics)


def test_evaluate_reports_thresholds() -> None:
    y = np.array([0.5, 0.0, 0.04, 0.06])
    e = evaluate(y, y, (1.5, 1.0))
    assert e["at_1.5s"]["accuracy"] == 1.0 and e["at_1s"]["accuracy"] == 1.0
    assert e["at_1.5s"]["confusion"]["tp"] == 3 and e["at_1s"]["confusion"]["tp"] == 2


def test_example_indices_confusion_table_and_tracking_metrics() -> None:
    y = np.array([0.5, 0.02, 0.3, 0.0])
    p = np.array([0.45, 0.5, 0.1, 0.0])
    # best critical frame: 0 (error 0.05); worst: 1 (error 0.48)
    assert example_indices(y, p, 1.5) == (0, 1)
    # the worst frame is the best critical one -> the second worst
    assert example_indices(np.array([0.5, 0.0]), np.array([0.0, 0.0]), 1.5) == (0, 1)
    # nothing critical -> the best frame overall
    assert example_indices(np.array([0.0, 0.01]), np.array([0.0, 0.3]), 1.5) == (0, 1)
    cm = confusion_table([7, 8, 9, 10], y, p, 1.5)
    assert cm.columns.tolist() == ["frame_id", "actual", "predicted"]
    assert cm.actual.tolist() == ["critical", "uncritical", "critical", "uncritical"]
    assert cm.predicted.tolist() == ["critical", "critical", "critical", "uncritical"]
    e = {**evaluate(y, p, (1.5, 1.0)), "label": "risk_thw_paper"}
    e["at_1.5s"]["roc_auc"] = None
    metrics = {"thresholds_s": [1.5, 1.0], "models": {"v": e}}
    vals = tracking_metrics(metrics, "v")
    assert set(vals) == {
        "test/mse",
        "test/mae",
        "test/thw_mae_s",
        "test/accuracy",
        "test/balanced_accuracy",
        "test/f1",
    }
    assert vals["test/accuracy"] == e["at_1.5s"]["accuracy"]
    pred = pd.DataFrame({"risk_thw_paper": y, "pred_v": p})
    lab, yy, pp = main_series(metrics, pred, "v")
    assert lab == "risk_thw_paper" and np.array_equal(yy, y) and np.array_equal(pp, p)


def _capture(monkeypatch: pytest.MonkeyPatch, module) -> dict:
    """Keep the figures a module saves (keyed by file name) instead of writing them."""
    figs: dict = {}
    monkeypatch.setattr(
        module, "save_figure", lambda fig, path, **_: figs.__setitem__(Path(path).name, fig)
    )
    return figs


def test_evaluation_figures_plot_the_predictions(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from traffictwin.risk import figures

    write_synthetic_risk(tmp_path, n_shards=4, per_shard=8)
    src = RiskSource(tmp_path / "data" / "risk", tmp_path / "data" / "disparity", None)
    models = {k: v for k, v in _tiny_models(tmp_path / "models").items() if k == "rgbd"}
    geo = GeometricParams(subject_length=4.5, subject_width=1.8)
    metrics, pred = evaluate_suite(
        src,
        models,
        SuiteSettings(
            acceptance=RISK,
            thresholds_s=(1.5, 1.0),
            primary_label="risk_thw_paper",
            geometric=geo,
            collapse_std=0.0,
        ),
    )
    hist = pd.DataFrame(
        {"step": [1, 2, 3], "train/loss": [0.3, 0.2, 0.1], "val/mse": [0.4, 0.3, 0.2]}
    )
    figs = _capture(monkeypatch, figures)
    metrics["models"]["rgbd"]["objective"] = "log_thw"  # the curves follow the run's objective
    # a shipped predictor (here: the speed-only rule's predictions under another key)
    pred["pred_ship"] = pred["pred_speed_only"]
    metrics["models"]["ship"] = {"at_1.5s": {"roc_auc": 0.625}}
    figures.evaluation_figures(
        Dataset(tmp_path / "data" / "risk", kind="risk"),
        Dataset(tmp_path / "data" / "disparity", kind="disparity"),
        metrics,
        pred,
        {"rgbd": hist},
        "rgbd",
        figures.EvaluationFigurePaths(
            curves=tmp_path / "c.png",
            scatter=tmp_path / "s.png",
            confusion=tmp_path / "m.png",
            examples=tmp_path / "e.png",
            roc=tmp_path / "r.png",
        ),
        shipped=("ship", "shipped (speed rule)"),
    )
    assert set(figs) == {"c.png", "s.png", "m.png", "e.png", "r.png"}
    # training curves: the objective's loss (log THW: no paper MSE there), then the validation
    # MSE of the normalised risk with the paper's test MSE
    tr, va = figs["c.png"].axes
    (line,) = [ln for ln in tr.lines if ln.get_label() == "rgbd"]
    assert line.get_xdata().tolist() == [1, 2, 3] and line.get_ydata().tolist() == [0.3, 0.2, 0.1]
    assert tr.get_ylabel() == figures.OBJECTIVE_LOSS["log_thw"]
    assert not any(ln.get_label() == "paper test MSE" for ln in tr.lines)
    assert va.get_title() == "validation MSE of normalised risk (every run)"
    assert any(ln.get_label() == "paper test MSE" for ln in va.lines)
    # scatter: the shipped predictor first, then the network, speed-only and geometric SGM
    # baselines, true vs predicted on symmetric-log axes, threshold 1/30
    ship_ax, *axes = figs["s.png"].axes
    assert ship_ax.get_title() == "shipped (speed rule)"
    assert np.allclose(ship_ax.collections[0].get_offsets()[:, 1], pred["pred_speed_only"])
    assert [a.get_title() for a in axes] == ["rgbd", "speed_only", "geometric_sgm"]
    assert all(a.get_xscale() == a.get_yscale() == "symlog" for a in figs["s.png"].axes)
    xy = axes[0].collections[0].get_offsets()
    assert np.allclose(xy[:, 0], pred["risk_thw_paper"]) and np.allclose(
        xy[:, 1], pred["pred_rgbd"]
    )
    assert np.allclose(axes[1].collections[0].get_offsets()[:, 1], pred["pred_speed_only"])
    assert np.allclose(axes[2].collections[0].get_offsets()[:, 1], pred["pred_geometric_sgm"])
    # ROC: the network and the three baselines (the oracle dashed) on the same critical frames
    (roc,) = figs["r.png"].axes
    lines = {ln.get_label().split(" (AUC")[0]: ln for ln in roc.lines}
    assert set(lines) == {
        "shipped (speed rule)",
        "rgbd",
        "speed_only",
        "geometric_sgm",
        "geometric_gt",
        "chance",
    }
    assert roc.lines[0].get_label() == "shipped (speed rule) (AUC 0.625)"
    assert np.allclose(lines["shipped (speed rule)"].get_ydata(), lines["speed_only"].get_ydata())
    fpr, tpr = roc_points(pred["risk_thw_paper"] > 1 / 30, pred["pred_geometric_sgm"])
    assert np.allclose(lines["geometric_sgm"].get_xdata(), fpr)
    assert np.allclose(lines["geometric_sgm"].get_ydata(), tpr)
    assert lines["geometric_gt"].get_linestyle() == "--" and lines["rgbd"].get_linestyle() == "-"
    assert axes[0].get_xlabel().startswith("true risk (1") and axes[0].get_ylabel().startswith(
        "predicted risk (1"
    )
    assert any(np.allclose(ln.get_xdata(), 1 / 30) for ln in axes[0].lines)
    # confusion matrix: the Table-1 counts of the main variant
    c = metrics["models"]["rgbd"]["at_1.5s"]["confusion"]
    texts = [t.get_text().split("\n")[0] for t in figs["m.png"].axes[0].texts]
    assert texts == [str(c["tp"]), str(c["fp"]), str(c["fn"]), str(c["tn"])]
    # examples: the best critical and the worst frame, image + disparity each
    ex = figs["e.png"].axes
    titles = [a.get_title() for a in ex if a.get_title().startswith(("well", "worst"))]
    good, bad = example_indices(
        pred["risk_thw_paper"].to_numpy(), pred["pred_rgbd"].to_numpy(), 1.5
    )
    assert titles[0].startswith(f"well predicted (frame {pred.frame_id[good]})")
    assert titles[-1].startswith(f"worst prediction (frame {pred.frame_id[bad]})")
    assert f"true {pred['risk_thw_paper'][bad]:.2f}" in titles[-1]
    # each example shows its own frame's left image (RGB) and SGM disparity
    frames = src.frames.set_index(src.frames["frame_id"].astype(str))
    for row, i in zip((ex[0:2], ex[2:4]), (good, bad)):  # colour bars follow the panels
        (arr,) = list(src.iter_arrays(frames.loc[[str(pred.frame_id[i])]], ["left", "disp_sgm"]))
        assert np.array_equal(row[0].images[0].get_array(), arr[1]["left"][0][..., ::-1])
        disp = arr[1]["disp_sgm"][0]
        shown = np.ma.filled(np.ma.masked_invalid(row[1].images[0].get_array()), 0.0)
        assert np.allclose(shown, np.where(disp > 0, disp, 0.0))
