"""Stage `plot_data`: long-format CSVs under reports/charts/ for the top-level DVC plots of dvc.yaml,
from what earlier stages of this run wrote (only the files params.yaml names): the training
curves (reports/plots/train_fusion_<network or variant>.csv, train_registration.csv,
risk_training_<variant>.csv) as ``*_learning_curves.csv``, the fusion score table as
``fusion_scores.csv`` (traffictwin.report.plot_data), and the risk predictions on the test frames
with reports/metrics/risk.json's label and first THW threshold as ``risk_roc.csv`` and
``risk_pr.csv`` (traffictwin.risk.charts.risk_curves).
"""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd

from traffictwin.io.atomic import write_csv_atomic
from traffictwin.report.plot_data import fusion_scores_long, learning_curves
from traffictwin.risk.charts import risk_curves
from traffictwin.risk.metric import risk_threshold

from ._common import params, run_stage, setup_logging, stage_timer
from ._paths import METRICS, PLOTS, REPORTS, fusion_model_dir

CHARTS = REPORTS / "charts"


def curve_files(cfg) -> dict[str, dict[str, Path]]:
    """Chart file -> {model name: its training-curve CSV} of the models this run trains."""
    from traffictwin.config import get

    variants = cfg.get("fusion_variants") or {}
    fusion = [fusion_model_dir().name, *(str(k) for k in variants)]
    risk = get(cfg, "risk_model.run_variants", list)
    return {
        "fusion_learning_curves.csv": {n: PLOTS / f"train_fusion_{n}.csv" for n in fusion},
        "registration_learning_curves.csv": {"learned": PLOTS / "train_registration.csv"},
        "risk_learning_curves.csv": {v: PLOTS / f"risk_training_{v}.csv" for v in risk},
    }


def _read_csv(path: Path) -> pd.DataFrame:
    if not path.is_file():
        raise RuntimeError(f"plot_data: {path} is missing (run the stage that writes it first)")
    return pd.read_csv(path)


def _write(df: pd.DataFrame, name: str) -> None:
    write_csv_atomic(CHARTS / name, df, float_format="%.6g")  # "\n": os.linesep on POSIX


def main() -> None:
    log = setup_logging()
    with stage_timer("plot_data"):
        CHARTS.mkdir(parents=True, exist_ok=True)
        charts = curve_files(params())
        for out, files in charts.items():
            curves = {name: _read_csv(path) for name, path in files.items()}
            _write(learning_curves(curves, x="epoch"), out)
        _write(fusion_scores_long(_read_csv(PLOTS / "fusion_scores.csv")), "fusion_scores.csv")
        risk_file = METRICS / "risk.json"
        if not risk_file.is_file():
            raise RuntimeError(f"plot_data: {risk_file} is missing (run evaluate_risk first)")
        risk = json.loads(risk_file.read_text())
        label, ts = risk.get("primary_label"), risk.get("thresholds_s")
        if not isinstance(label, str) or not isinstance(ts, list) or not ts:
            raise ValueError(
                f"plot_data: {risk_file}: expected 'primary_label' and a list 'thresholds_s'"
            )
        predictions = _read_csv(PLOTS / "risk_predictions.csv")
        curves = risk_curves(predictions, label, risk_threshold(float(ts[0])))
        for df, name in zip(curves, ("risk_roc.csv", "risk_pr.csv"), strict=True):
            _write(df, name)
    log.info("plot_data: %d charts -> %s", len(charts) + 3, CHARTS)


if __name__ == "__main__":
    run_stage(main, "plot_data")
