"""DVC plots: the long-format charts of stage plot_data (hand-computed cases), the Vega-Lite
templates and the offline page template, and -- on the ci DAG's outputs -- every plot declared in
dvc.yaml names x and y fields that are columns of its file."""

from __future__ import annotations

import csv
import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from traffictwin.report.plot_data import fusion_scores_long, learning_curves
from traffictwin.risk.charts import pr_points, risk_curves, roc_points

ROOT = Path(__file__).resolve().parents[1]
PLOTS_DIR = ROOT / ".dvc" / "plots"


# --------------------------------------------------------------------------- plot_data
def test_learning_curves_long_format() -> None:
    a = pd.DataFrame({"epoch": [0, 1], "train/loss": [1.0, 0.5], "val/loss": [1.2, np.nan]})
    b = pd.DataFrame({"epoch": [0], "train/loss": [2.0], "lr": [0.1]})  # no validation column
    long = learning_curves({"A": a, "B": b})
    assert list(long.columns) == ["model", "epoch", "split", "loss"]
    rows = sorted(map(tuple, long.itertuples(index=False)))
    # the NaN validation value of A at epoch 1 is left out
    assert rows == [
        ("A", 0, "train", 1.0),
        ("A", 0, "val", 1.2),
        ("A", 1, "train", 0.5),
        ("B", 0, "train", 2.0),
    ]
    with pytest.raises(ValueError, match="'C'.*no column 'epoch'"):
        learning_curves({"C": pd.DataFrame({"step": [1], "train/loss": [1.0]})})
    with pytest.raises(ValueError, match="'D'.*none of the loss columns"):
        learning_curves({"D": pd.DataFrame({"epoch": [1], "val/mse": [1.0]})})


def test_fusion_scores_long_parses_method_names_with_underscores() -> None:
    wide = pd.DataFrame(
        {
            "config": ["A", "D"],
            "noise_r_m": [0.0, 5.0],
            "noise_alpha_deg": [0, 20],
            "dnn_dice_occ": [0.99, 0.9],
            "dnn[paper_kl]_precision_free": [np.nan, 0.97],  # only evaluated at D
            "dnn_kld_fou_mean": [0.01, 0.06],  # not a classification score
        }
    )
    long = fusion_scores_long(wide)
    assert list(long.columns) == [
        "config",
        "noise_r_m",
        "noise_alpha_deg",
        "method",
        "class",
        "metric",
        "value",
    ]
    got = sorted((r.config, r.method, r["class"], r.metric, r.value) for _, r in long.iterrows())
    assert got == [
        ("A", "dnn", "occupied", "Dice", 0.99),
        ("D", "dnn", "occupied", "Dice", 0.9),
        ("D", "dnn[paper_kl]", "free", "precision", 0.97),
    ]
    with pytest.raises(ValueError, match="missing column"):
        fusion_scores_long(wide.drop(columns="noise_r_m"))


def test_roc_and_pr_points_hand_case() -> None:
    # scores 0.9 (pos), 0.8 (neg), 0.8 (pos), 0.1 (neg): thresholds 0.9, 0.8, 0.1
    pos, score = np.array([True, False, True, False]), np.array([0.9, 0.8, 0.8, 0.1])
    fpr, tpr = roc_points(pos, score)
    assert fpr.tolist() == [0.0, 0.0, 0.5, 1.0] and tpr.tolist() == [0.0, 0.5, 1.0, 1.0]
    rec, prec = pr_points(pos, score)  # scikit-learn's start (0, 1), then each threshold
    assert rec.tolist() == [0.0, 0.5, 1.0, 1.0]
    assert prec.tolist() == [1.0, 1.0, 2 / 3, 0.5]
    # a non-finite score is left out; one class: no ROC; no positive: no PR either
    f2, t2 = roc_points(np.r_[pos, True], np.r_[score, np.nan])
    assert f2.tolist() == fpr.tolist() and t2.tolist() == tpr.tolist()
    assert roc_points(np.ones(3, bool), np.arange(3.0))[0].size == 0
    assert pr_points(np.ones(3, bool), np.arange(3.0))[0].tolist() == [0.0, 1 / 3, 2 / 3, 1.0]
    r0, p0 = pr_points(np.zeros(3, bool), np.arange(3.0))
    assert r0.size == 0 and p0.size == 0
    with pytest.raises(ValueError, match="same length"):
        roc_points(pos, score[:3])


def test_risk_curves_per_predictor() -> None:
    pred = pd.DataFrame(
        {
            "risk_thw_corridor": [0.0, 0.1, 0.2, 0.01],  # critical (> 1/30): rows 1 and 2
            "pred_net": [0.0, 0.2, 0.3, 0.1],  # ranks both critical frames first: AUC 1
            "pred_flip": [0.3, 0.1, 0.0, 0.2],  # ranks them last: AUC 0
            "speed": [1.0, 2.0, 3.0, 4.0],  # not a prediction column
            "pred_gap": [np.nan, 0.2, 0.3, 0.1],  # a missing prediction: that row left out
        }
    )
    roc, pr = risk_curves(pred, "risk_thw_corridor", 1 / 30)
    assert list(roc.columns) == ["predictor", "rank", "fpr", "tpr"]
    assert list(pr.columns) == ["predictor", "rank", "recall", "precision"]
    assert sorted(roc["predictor"].unique()) == [
        "flip (AUC 0.000)",
        "gap (AUC 1.000)",
        "net (AUC 1.000)",
    ]
    net = roc[roc["predictor"] == "net (AUC 1.000)"].sort_values("rank")
    # thresholds 0.3, 0.2, 0.1, 0.0: (0, .5), (0, 1), (.5, 1), (1, 1) after (0, 0); the point
    # inside the last straight run is dropped
    assert net[["fpr", "tpr"]].to_numpy().tolist() == [[0, 0], [0, 0.5], [0, 1], [1, 1]]
    assert net["rank"].tolist() == [0, 1, 2, 3]
    pnet = pr[pr["predictor"] == "net (AUC 1.000)"].sort_values("rank")
    # (0, 1), then recall .5, 1, 1, 1 at precision 1, 1, 2/3, 1/2: the middle of the vertical run goes
    assert pnet[["recall", "precision"]].to_numpy().tolist() == [[0, 1], [0.5, 1], [1, 1], [1, 0.5]]
    gap = roc[roc["predictor"] == "gap (AUC 1.000)"]
    assert gap[["fpr", "tpr"]].to_numpy().tolist() == [[0, 0], [0, 0.5], [0, 1], [1, 1]]
    for name, df in roc.groupby("predictor"):  # the trapezoid area is the AUC in the name
        area = float(
            np.sum(np.diff(df["fpr"]) * (df["tpr"].to_numpy()[1:] + df["tpr"].to_numpy()[:-1]) / 2)
        )
        assert f"(AUC {area:.3f})" in name
    with pytest.raises(ValueError, match="no label column 'risk_x'"):
        risk_curves(pred, "risk_x", 1 / 30)
    one_class = pred.assign(risk_thw_corridor=0.0)  # no critical frame: no curve at all
    roc0, pr0 = risk_curves(one_class, "risk_thw_corridor", 1 / 30)
    assert roc0.empty and pr0.empty and list(roc0.columns) == list(roc.columns)


# --------------------------------------------------------------------------- templates
# --------------------------------------------------------------------------- plot_data figures
def test_history_rows_leave_out_a_metric_an_epoch_lacks(tmp_path: Path) -> None:
    from pipelines.plot_data import history_rows

    f = tmp_path / "curve.csv"
    f.write_text("epoch,train/loss,val/loss\n0,1.5,\n1,1.25,0.75\n")
    assert history_rows(f) == [
        {"epoch": 0, "train/loss": 1.5},
        {"epoch": 1, "train/loss": 1.25, "val/loss": 0.75},
    ]


def test_fusion_curve_titles_name_inputs_noise_and_loss() -> None:
    from omegaconf import OmegaConf

    from pipelines._common import params
    from pipelines.plot_data import fusion_curve_titles

    cfg = params()
    loss = cfg.fusion_model.loss.name
    cfg.fusion_variants = OmegaConf.create({"d_own": {"config": "D", "inputs": "prealigned"}})
    assert fusion_curve_titles(cfg) == {
        "network": f"network: prealigned inputs, the mixed pose noise, loss {loss}",
        "d_own": f"d_own: prealigned inputs, configuration D, loss {loss}",
    }


def test_training_figures_draw_each_network_once_and_drop_stale_ones(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """One PNG per trained network from its curve CSV; a PNG of a network this run no longer
    trains is removed; the fusion figure plots the CSV's validation KLD(b) per epoch."""
    from matplotlib import pyplot as plt

    import pipelines.plot_data as pd_stage
    from pipelines._common import params
    from traffictwin.fusion.training_figures import learning_curves as fusion_curves

    plots, out = tmp_path / "plots", tmp_path / "figures" / "learning_curves"
    plots.mkdir()
    rows = (
        "epoch,train/loss,val/loss,val/kld_full,val/kld_full_naive,val/dice_occ,val/dice_occ_naive"
    )
    (plots / "train_fusion_network.csv").write_text(
        rows + "\n0,0.5,0.4,0.03,0.2,0.9,0.8\n1,0.3,0.2,0.01,0.2,0.95,0.8\n"
    )
    (plots / "train_registration.csv").write_text(
        "epoch,train/loss,val/loss,val/success_rate,val/trans_err_m,val/rot_err_deg\n"
        "0,2.0,1.5,0.5,0.4,1.2\n1,1.0,1.2,0.8,0.2,0.6\n"
    )
    (plots / "train_stereo.csv").write_text(
        "epoch,train/loss,val/loss,val/epe,val/bad1\n0,0.3,0.35,0.4,0.02\n1,0.2,0.25,0.3,0.01\n"
    )
    out.mkdir(parents=True)
    (out / "train_fusion_gone.png").write_bytes(b"\x89PNG")
    monkeypatch.setattr(pd_stage, "PLOTS", plots)
    monkeypatch.setattr(pd_stage, "LEARNING_CURVES", out)
    assert pd_stage.training_figures(params()) == 3
    assert sorted(p.name for p in out.iterdir()) == [
        "train_fusion_network.png",
        "train_registration.png",
        "train_stereo.png",
    ]
    fig = fusion_curves(pd_stage.history_rows(plots / "train_fusion_network.csv"), "t")
    line = fig.axes[0].lines[0]
    assert list(line.get_xdata()) == [0, 1] and list(line.get_ydata()) == [0.03, 0.01]
    plt.close(fig)


def test_page_template_is_offline_and_declares_its_charset() -> None:
    cfg = (ROOT / ".dvc" / "config").read_text()
    m = re.search(r"^\s*html_template\s*=\s*(\S+)\s*$", cfg, re.M)
    assert m, ".dvc/config sets no plots.html_template"
    page = (ROOT / ".dvc" / m.group(1)).read_text(encoding="utf-8")
    assert re.search(r'<meta charset="utf-8"\s*/?>', page, re.I)
    assert "{plot_divs}" in page
    # DVC fills {scripts} with CDN links: the template must not ask for them
    assert "{scripts}" not in page
    assert not re.search(r"<script[^>]*\bsrc\s*=\s*[\"']?https?:", page, re.I)
    for name in ("vega 5", "vega-lite 5", "vega-embed 6"):
        assert f"/* {name}" in page, name
    licences = (PLOTS_DIR / "VENDOR-LICENSES.txt").read_text()
    assert licences.count("BSD-3-Clause") >= 1 and "Redistribution and use" in licences


def _templates() -> dict[str, dict]:
    return {p.stem: json.loads(p.read_text()) for p in PLOTS_DIR.glob("*.json")}


def test_templates_title_both_axes_from_the_plot_labels() -> None:
    for name, t in _templates().items():
        enc = t.get("encoding") or t["spec"]["encoding"]
        assert enc["x"]["title"] == "<DVC_METRIC_X_LABEL>", name
        assert enc["y"]["title"] == "<DVC_METRIC_Y_LABEL>", name
        assert t["data"]["values"] == "<DVC_METRIC_DATA>", name


def _declared_plots(dvc: dict) -> list[tuple[str, str, list[str], str | None]]:
    """``(plot id, file, y fields, x field)`` of every plot with data in dvc.yaml (stage-level CSV
    plots and top-level plots; images have no fields)."""
    out = []
    for name, st in dvc["stages"].items():
        body = st.get("do", st)
        for entry in body.get("plots", []):
            path, props = (entry, {}) if isinstance(entry, str) else next(iter(entry.items()))
            if path.endswith(".png") or path.startswith("reports/figures/"):  # images
                continue
            props = props or {}
            out.append((f"{name}:{path}", path, [props.get("y")], props.get("x")))
    for entry in dvc.get("plots", []):
        pid, props = next(iter(entry.items())) if isinstance(entry, dict) else (entry, {})
        props = props or {}
        y = props.get("y")
        if isinstance(y, dict):
            for f, fields in y.items():
                out.append(
                    (pid, f, fields if isinstance(fields, list) else [fields], props.get("x"))
                )
        else:
            out.append((pid, pid, [y], props.get("x")))
    return out


def test_every_template_named_in_dvc_yaml_exists() -> None:
    dvc = yaml.safe_load((ROOT / "dvc.yaml").read_text())
    builtin = {
        "linear",
        "simple",
        "scatter",
        "smooth",
        "confusion",
        "confusion_normalized",
        "bar_horizontal",
        "bar_horizontal_sorted",
    }
    names = set()
    for st in dvc["stages"].values():
        for entry in st.get("do", st).get("plots", []):
            if isinstance(entry, dict):
                names.add((next(iter(entry.values())) or {}).get("template"))
    for entry in dvc.get("plots", []):
        names.add((next(iter(entry.values())) or {}).get("template"))
    names.discard(None)
    missing = names - builtin - set(_templates())
    assert not missing, missing


def test_every_declared_plot_has_x_and_y_columns_in_its_file(ci_dag: Path) -> None:
    dvc = yaml.safe_load((ci_dag / "dvc.yaml").read_text())
    plots = _declared_plots(dvc)
    assert len(plots) >= 9
    for pid, f, ys, x in plots:
        paths = sorted(ci_dag.glob(f.replace("${key}", "*").replace("${item}", "*")))
        assert paths, (pid, f, "no such file after the ci DAG")
        for path in paths:
            with path.open() as fh:
                header = next(csv.reader(fh))
            assert x and x in header, (pid, path.name, x, header)
            for y in ys:
                assert y and y in header, (pid, path.name, y, header)
            rows = sum(1 for _ in path.open()) - 1
            if path.name in ("risk_roc.csv", "risk_pr.csv"):
                # a curve needs critical and uncritical test frames (the ci profile may have one class)
                pred = pd.read_csv(ci_dag / "reports" / "plots" / "risk_predictions.csv")
                critical = pred["risk_thw_corridor"] > 1 / 30
                assert (rows > 0) == (0 < critical.sum() < len(critical)), (pid, rows)
            else:
                assert rows > 0, (pid, path.name, "no rows")


def test_plot_data_draws_the_learning_curves_of_the_networks_the_run_trained(ci_dag: Path) -> None:
    curves = ci_dag / "reports" / "figures" / "learning_curves"
    assert sorted(p.stem for p in curves.glob("*.png")) == [
        "train_fusion_network",
        "train_registration",
        "train_stereo",
    ]


#: the figures of the evaluations, drawn by plot_data from their outputs
EVALUATION_FIGURES = (
    "fusion_kld_boxplot",
    "fusion_scores_occupied",
    "fusion_scores_free",
    "fusion_qualitative",
    "twin_map",
    "twin_timeline",
    "stereo_learned_example",
    "risk_training_curves",
    "risk_scatter",
    "risk_examples",
    "risk_confusion",
    "risk_roc",
)


def test_plot_data_draws_the_evaluation_figures_from_their_outputs(ci_dag: Path) -> None:
    from test_evaluate_fusion import png_ok

    from traffictwin.io.figure_inputs import read_arrays_with_meta

    stages = yaml.safe_load((ci_dag / "dvc.yaml").read_text())["stages"]

    def declared(stage: str) -> set[str]:
        items = [*stages[stage].get("outs", []), *stages[stage].get("plots", [])]
        return {next(iter(i)) if isinstance(i, dict) else i for i in items}

    drawn = declared("plot_data")
    for name in EVALUATION_FIGURES:
        path = f"reports/figures/{name}.png"
        assert path in drawn, path
        png_ok(ci_dag / path)
    for stage in ("evaluate_fusion", "evaluate_twin", "evaluate_risk", "stereo_learned"):
        assert not [p for p in declared(stage) if p.endswith(".png")], stage
    # the twin's timeline figure and DVC plot show the same sequence: the one the snapshot keeps
    _, meta = read_arrays_with_meta(ci_dag / "data" / "figure_inputs" / "twin_map.npz")
    frames = pd.read_csv(ci_dag / "reports" / "twin_eval_frames.csv")
    timeline = pd.read_csv(ci_dag / "reports" / "plots" / "twin_timeline.csv")
    ego = frames[
        (frames.noise == "frame")
        & (frames.configuration == meta["configuration"])
        & (frames.sequence == meta["sequence"])
        & (frames.method == "ego")
    ]
    truth = timeline[timeline.series == "truth"]
    np.testing.assert_allclose(truth["time"], ego["time"])
    np.testing.assert_allclose(truth["thw"], np.minimum(ego["thw_true"], 5.0), rtol=1e-5)


def test_plot_data_fails_naming_a_missing_evaluation_input(ci_dag: Path, tmp_path: Path) -> None:
    """The evaluation figures are drawn in a forked second process: an input missing there still
    fails the stage (non-zero exit) with an error naming the file, and no figure is left
    half-written."""
    import subprocess
    import sys

    from conftest import copy_dag, stage_env

    repo = copy_dag(ci_dag, tmp_path / "repo", mlflow=False)
    (repo / "data" / "figure_inputs" / "twin_map.npz").unlink()
    before = {p.name: p.read_bytes() for p in (repo / "reports" / "figures").glob("*.png")}
    p = subprocess.run(
        [sys.executable, "-m", "pipelines.plot_data"],
        cwd=repo,
        env=stage_env(repo),
        capture_output=True,
        text=True,
    )
    assert p.returncode != 0
    assert "data/figure_inputs/twin_map.npz is missing" in p.stderr, p.stderr[-2000:]
    after = {p.name: p.read_bytes() for p in (repo / "reports" / "figures").glob("*.png")}
    assert after == before  # every figure drawn again byte for byte or not at all
