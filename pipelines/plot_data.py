"""Stage `plot_data`: the charts and figures of what the data, training and evaluation stages wrote,
drawn here so that editing a figure re-runs only this stage (and ``report``), never another stage.

Reads only the files params.yaml names and writes:

- ``reports/charts/``: long-format CSVs for the top-level DVC plots of dvc.yaml: the training
  curves (reports/plots/train_fusion_<network or variant>.csv, train_registration.csv,
  risk_training_<variant>.csv) as ``*_learning_curves.csv``, the fusion score table as
  ``fusion_scores.csv`` (traffictwin.report.plot_data), and the risk predictions on the test frames
  with reports/metrics/risk.json's label and first THW threshold as ``risk_roc.csv`` and
  ``risk_pr.csv`` (traffictwin.risk.charts.risk_curves);
- ``reports/figures/learning_curves/``: one PNG per trained fusion network, the learned
  registration and the learned stereo network, from their reports/plots CSVs
  (traffictwin.fusion.training_figures, traffictwin.stereo.figures);
- the data figures: ``reports/figures/fusion_data_samples.png`` (data/fusion),
  ``risk_metric_example.png`` (a sequence simulated from ``risk_data`` and ``seed``),
  ``stereo_example.png`` (data/risk, data/disparity) and ``orb_outlier_example.png``
  (data/orb/orb.csv) (traffictwin.fusion.data_figure, traffictwin.risk.data_figures);
- the evaluation figures: ``fusion_{kld_boxplot,scores_occupied,scores_free,qualitative}.png``
  (reports/plots/fusion_kld.csv, reports/metrics/fusion.json, data/figure_inputs/fusion.npz),
  ``twin_timeline.png`` and ``twin_map.png`` (reports/twin_eval_frames.csv,
  data/figure_inputs/twin_map.npz), ``stereo_learned_example.png`` (data/risk, data/disparity,
  data/stereo_learned) and ``risk_{training_curves,scatter,confusion,examples,roc}.png``
  (reports/metrics/risk.json, reports/plots/risk_predictions.csv and risk_training_*.csv, data/risk,
  data/disparity) (traffictwin.{fusion,twin,stereo,risk}.figures).
"""

from __future__ import annotations

import json
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from dataclasses import fields
from pathlib import Path

import pandas as pd

from traffictwin.config import get
from traffictwin.fusion.config import grid_config
from traffictwin.io.atomic import write_csv_atomic
from traffictwin.report.plot_data import fusion_scores_long, learning_curves
from traffictwin.risk.charts import risk_curves
from traffictwin.risk.metric import risk_threshold

from ._common import params, run_stage, setup_logging, stage_timer
from ._figure_inputs import figure_input
from ._paths import (
    DISPARITY,
    FIGURES,
    FUSION_DATA,
    METRICS,
    ORB_CSV,
    PLOTS,
    REPORTS,
    RISK_DATA,
    STEREO_LEARNED,
    figure_file,
    fusion_model_dir,
)

CHARTS = REPORTS / "charts"
TWIN_FRAMES = REPORTS / "twin_eval_frames.csv"  # evaluate_twin's frames table
LEARNING_CURVES = FIGURES / "learning_curves"


def curve_files(cfg) -> dict[str, dict[str, Path]]:
    """Chart file -> {model name: its training-curve CSV} of the models this run trains."""
    variants = cfg.get("fusion_variants") or {}
    fusion = [fusion_model_dir().name, *(str(k) for k in variants)]
    risk = get(cfg, "risk_model.run_variants", list)
    return {
        "fusion_learning_curves.csv": {n: PLOTS / f"train_fusion_{n}.csv" for n in fusion},
        "registration_learning_curves.csv": {"learned": PLOTS / "train_registration.csv"},
        "risk_learning_curves.csv": {v: PLOTS / f"risk_training_{v}.csv" for v in risk},
    }


def _need(path: Path) -> Path:
    if not path.is_file():
        raise RuntimeError(f"plot_data: {path} is missing (run the stage that writes it first)")
    return path


def _read_csv(path: Path) -> pd.DataFrame:
    return pd.read_csv(_need(path))


def _metrics(name: str) -> dict:
    return json.loads(_need(METRICS / f"{name}.json").read_text())


def _write(df: pd.DataFrame, name: str) -> None:
    write_csv_atomic(CHARTS / name, df, float_format="%.6g")  # "\n": os.linesep on POSIX


def charts(cfg) -> int:
    """The long-format CSVs of ``reports/charts``; returns how many."""
    CHARTS.mkdir(parents=True, exist_ok=True)
    files = curve_files(cfg)
    for out, by_model in files.items():
        curves = {name: _read_csv(path) for name, path in by_model.items()}
        _write(learning_curves(curves, x="epoch"), out)
    _write(fusion_scores_long(_read_csv(PLOTS / "fusion_scores.csv")), "fusion_scores.csv")
    risk = _metrics("risk")
    label, ts = risk.get("primary_label"), risk.get("thresholds_s")
    if not isinstance(label, str) or not isinstance(ts, list) or not ts:
        raise ValueError(
            f"plot_data: {METRICS / 'risk.json'}: expected 'primary_label' and a list 'thresholds_s'"
        )
    predictions = _read_csv(PLOTS / "risk_predictions.csv")
    curves = risk_curves(predictions, label, risk_threshold(float(ts[0])))
    for df, name in zip(curves, ("risk_roc.csv", "risk_pr.csv"), strict=True):
        _write(df, name)
    return len(files) + 3


def history_rows(path: Path) -> list[dict[str, float]]:
    """A training-curve CSV (reports/plots) as the History rows the learning-curve figures take
    (one dict per epoch; a metric missing in an epoch is left out of its row)."""
    return [
        {k: v for k, v in row.items() if pd.notna(v)} for row in _read_csv(path).to_dict("records")
    ]


def fusion_curve_titles(cfg) -> dict[str, str]:
    """Model name -> learning-curve title of each fusion network this run trains (inputs, the
    training noise, the loss)."""
    from traffictwin.fusion.config import MIXED, NETWORK_MODEL, fusion_variants

    default_loss = get(cfg, "fusion_model.loss.name", str)
    targets = {NETWORK_MODEL: ("prealigned", MIXED, default_loss)}
    for name, v in fusion_variants(cfg).items():
        targets[name] = (v.inputs, v.config, v.loss or default_loss)
    return {
        name: f"{name}: {inputs} inputs, "
        + ("the mixed pose noise" if config == MIXED else f"configuration {config}")
        + f", loss {loss}"
        for name, (inputs, config, loss) in targets.items()
    }


def training_figures(cfg) -> int:
    """One learning-curve PNG per trained network under ``reports/figures/learning_curves``
    (only those of this run: stale ones are removed); returns how many."""
    from traffictwin.fusion.training_figures import learning_curves as fusion_curves
    from traffictwin.fusion.training_figures import registration_learning_curves
    from traffictwin.io.atomic import save_figure
    from traffictwin.stereo.figures import learning_curves as stereo_curves

    figures = {
        f"train_fusion_{name}": (fusion_curves, title)
        for name, title in fusion_curve_titles(cfg).items()
    }
    figures["train_registration"] = (
        registration_learning_curves,
        "learned registration, mixed pose noise",
    )
    figures["train_stereo"] = (stereo_curves, "learned stereo network")
    LEARNING_CURVES.mkdir(parents=True, exist_ok=True)
    for old in LEARNING_CURVES.glob("*.png"):
        if old.stem not in figures:
            old.unlink()
    for stem, (draw, title) in figures.items():
        save_figure(
            draw(history_rows(PLOTS / f"{stem}.csv"), title), LEARNING_CURVES / f"{stem}.png"
        )
    return len(figures)


def data_figures(cfg) -> int:
    """The figures of the fusion and risk data (see the module docstring); returns how many."""
    from traffictwin.fusion.config import fusion_data_config
    from traffictwin.fusion.data_figure import pick_samples, plot_fusion_samples
    from traffictwin.io.shards import Dataset
    from traffictwin.risk.data_figures import (
        orb_example_figure,
        risk_metric_figure,
        stereo_example_figure,
    )

    from .generate_risk import read_config

    samples = pick_samples(
        Dataset(FUSION_DATA, kind="fusion"), fusion_data_config(cfg).figure.samples
    )
    plot_fusion_samples(
        figure_file("fusion_data_samples"),
        samples,
        grid_config(cfg),
        title="Fusion data: two input maps with poses and the Dempster label",
    )
    rd, spec, seed = read_config(cfg)
    risk_metric_figure(seed, spec, figure_file("risk_metric_example"))
    risk = Dataset(RISK_DATA, kind="risk", verify=False)
    stereo_example_figure(
        risk, Dataset(DISPARITY, kind="disparity", verify=False), figure_file("stereo_example")
    )
    orb = _read_csv(ORB_CSV)
    orb_example_figure(  # a pair the ORB check flags (the figure shows ORB matches)
        risk,
        orb.assign(outlier=orb.flag_orb),
        rd.orb,
        figure_file("orb_outlier_example"),
    )
    return 4


def _figure_input(name: str) -> tuple[dict, dict]:
    from traffictwin.io.figure_inputs import read_arrays_with_meta

    return read_arrays_with_meta(_need(figure_input(name)))


def evaluation_figures(cfg) -> int:
    """The figures of the evaluation stages' outputs (see the module docstring); returns how many."""
    from traffictwin.fusion.evaluation_figures import evaluation_figures as fusion_figures
    from traffictwin.io.atomic import save_figure
    from traffictwin.io.shards import Dataset
    from traffictwin.risk import figures as risk_figures
    from traffictwin.stereo.figures import fault_free_test_examples
    from traffictwin.twin.figure_inputs import TwinSnapshot
    from traffictwin.twin.figures import timeline_figure, twin_map_figure

    panels, meta = _figure_input("fusion")
    scores = fusion_scores_long(_read_csv(PLOTS / "fusion_scores.csv"))
    figures = fusion_figures(
        _read_csv(PLOTS / "fusion_kld.csv"), scores, _metrics("fusion"), panels, meta
    )
    arrays, tw = _figure_input("twin_map")
    frames = _read_csv(TWIN_FRAMES)
    frames = frames[frames["noise"] == "frame"]
    c, method, seq = tw["configuration"], tw["method"], tw["sequence"]
    figures["twin_timeline"] = timeline_figure(
        frames, c, method, seq, tw["critical_thw_s"], tw["warn_thw_s"]
    )
    figures["twin_map"] = twin_map_figure(
        TwinSnapshot.from_arrays(arrays), grid_config(cfg), tw["radius_m"], method, c
    )
    risk, disparity = (
        Dataset(RISK_DATA, kind="risk", verify=False),
        Dataset(DISPARITY, kind="disparity", verify=False),
    )
    learned = Dataset(STEREO_LEARNED, kind="stereo_learned", verify=False)
    figures["stereo_learned_example"] = fault_free_test_examples(risk, disparity, learned)
    for name, fig in figures.items():
        save_figure(fig, figure_file(name))
    m = _metrics("risk")
    shipped_from = (m.get("selection") or {}).get("shipped_from")
    variants = get(cfg, "risk_model.run_variants", list)
    risk_paths = risk_figures.EvaluationFigurePaths(
        **{k: figure_file(f"risk_{k}") for k in ("scatter", "confusion", "examples", "roc")},
        curves=figure_file("risk_training_curves"),
    )
    risk_figures.evaluation_figures(
        risk,
        disparity,
        m,
        _read_csv(PLOTS / "risk_predictions.csv"),
        {v: _read_csv(PLOTS / f"risk_training_{v}.csv") for v in variants},
        m["main_variant"],
        risk_paths,
        shipped=(m["shipped"], f"shipped ({shipped_from})" if shipped_from else m["shipped"]),
    )
    return len(figures) + len(fields(risk_paths))


def main() -> None:
    log = setup_logging()
    cfg = params()
    with stage_timer("plot_data"):
        # the evaluation figures (about half the stage) in a second process, forked before this
        # one draws anything: the two halves write disjoint files, each figure as drawn alone
        fork = multiprocessing.get_context("fork")
        with ProcessPoolExecutor(max_workers=1, mp_context=fork) as pool:
            evaluation = pool.submit(evaluation_figures, cfg)
            n_charts, n_curves, n_data = charts(cfg), training_figures(cfg), data_figures(cfg)
            n_eval = evaluation.result()
    log.info(
        "plot_data: %d charts -> %s, %d learning curves, %d data figures, %d evaluation figures",
        n_charts,
        CHARTS,
        n_curves,
        n_data,
        n_eval,
    )


if __name__ == "__main__":
    run_stage(main, "plot_data")
