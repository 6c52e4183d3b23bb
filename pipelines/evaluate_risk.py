"""Stage `evaluate_risk`: every risk network variant and the baselines on the same test frames.

Reads ``evaluation.risk.*``, ``risk_model.label``, ``risk_model.run_variants``,
``risk_model.variants`` (``replicate_of``, ``objective``, ``seed_offset`` of each),
``risk_model.orb_filter``, ``risk_data.metric`` (the subject footprint), the data
(``data/risk``, ``data/disparity``, ``data/orb/orb.csv``) and ``models/risk/<variant>/``.
Writes ``reports/metrics/summary_risk.json`` (the DVC metrics file, :func:`summary`: the shipped
predictor's validation and test headline figures, flat ``split/name`` keys),
``reports/metrics/risk.json`` (layout: :mod:`traffictwin.risk.evaluation` — every metric
with its sequence-bootstrap interval, the baselines speed-only / geometric SGM / geometric GT
(oracle) / train mean / median, paired differences, seed groups, collapse flags, targets, critical
shares per split and region, the situation breakdown), ``reports/plots/risk_predictions.csv``
(per-frame predictions), ``reports/plots/risk_confusion.csv`` (actual/predicted class per test
frame of the main variant, for the ``dvc plots`` confusion template; the figures
``reports/figures/risk_*.png`` are drawn from these by ``plot_data``). Test metrics are also logged into each variant's MLflow training
run when it is in the store.
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace
from typing import TYPE_CHECKING

from traffictwin.acceptance import for_problem
from traffictwin.config import ConfigError, get, typed
from traffictwin.io.atomic import write_csv_atomic, write_json_atomic
from traffictwin.risk.config import EvalRiskConfig, MetricParams
from traffictwin.risk.evaluation import (
    TARGET_NAMES,
    CIConfig,
    Holdout,
    SuiteSettings,
    confusion_table,
    evaluate_suite,
    main_series,
    tracking_metrics,
)
from traffictwin.risk.model_config import LABELS

from ._common import params, read_run_record, run_stage, setup_logging, stage_timer
from ._inference import pin_torch_threads
from ._paths import (
    DISPARITY,
    ORB_CSV,
    RISK_DATA,
    SHIPPED_RISK_MODEL,
    STEREO_LEARNED,
    hybrid_model_dir,
    metrics_file,
    plot_file,
    risk_model_dir,
)
from .train_risk_hybrid import (
    HOLDOUT,
    HYBRID,
    holdout_runs,
    hybrid_runs,
    hybrid_settings,
    learned_disparity,
    learned_runs,
)

if TYPE_CHECKING:
    import pandas as pd

METRICS = metrics_file("risk")
SELECTION = metrics_file("risk_selection")
SUMMARY = metrics_file("summary_risk")  # the DVC metrics file: what `dvc exp show` compares
SHIPPED = "shipped"


def _write_csv(df: pd.DataFrame, path) -> None:
    write_csv_atomic(path, df, float_format="%.6g", lineterminator="\n")


def _log_to_mlflow(models: dict, metrics: dict, log: logging.Logger) -> None:
    """Add test metrics to each variant's training run (its ``run_id`` in the run record of
    ``train_risk@<variant>``; skipped when the run is not in this store)."""
    try:
        from mlflow.tracking import MlflowClient

        from traffictwin.mlops import tracking

        client = MlflowClient(tracking_uri=tracking.tracking_uri())
        for v in models:
            rid = read_run_record(f"train_risk@{v}").get("run_id")
            if not rid:
                continue
            try:
                for k, val in tracking_metrics(metrics, v).items():
                    client.log_metric(rid, k, float(val))
            except Exception as exc:  # run from another store / deleted: not an error of this stage
                log.warning(
                    "evaluate_risk: could not log test metrics to MLflow run %s (%s)", rid, exc
                )
    except Exception as exc:
        log.warning("evaluate_risk: MLflow unavailable (%s); metrics only in %s", exc, METRICS)


def _fmt3(x) -> str:
    """A metric for the log: 3 decimals, or n/a (undefined: JSON null)."""
    return "n/a" if x is None else f"{float(x):.3f}"


def read_selection() -> dict:
    """``reports/metrics/risk_selection.json`` (stage ``select_risk``: the choices made on
    validation); errors name the file."""
    import json

    if not SELECTION.exists():
        raise FileNotFoundError(f"{SELECTION}: not found (run the select_risk stage first)")
    try:
        sel = json.loads(SELECTION.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{SELECTION}: not valid JSON ({exc})") from None
    missing = [k for k in ("rules", "predictors", "shipped", "split") if k not in sel]
    if missing:
        raise ValueError(f"{SELECTION}: key(s) {missing} missing (re-run select_risk)")
    return sel


def run_variants(p) -> list[str]:
    """``risk_model.run_variants``: the variants to evaluate, each defined in ``risk_model.variants``."""
    defined = get(p, "risk_model.variants", dict)
    variants = list(get(p, "risk_model.run_variants", list))
    unknown = [v for v in variants if v not in defined]
    if not variants or unknown:
        raise ConfigError(
            f"params.yaml: 'risk_model.run_variants' must name variants of 'risk_model.variants' {sorted(defined)}, got {variants}"
        )
    return variants


def variant_settings(p, variants: list[str]) -> dict[str, dict]:
    """``risk_model.variants.<v>`` of each evaluated variant as a plain dict; ``replicate_of``
    must name a defined variant."""
    defined = get(p, "risk_model.variants", dict)
    out = {v: dict(defined[v] or {}) for v in variants}
    for v, d in out.items():
        r = d.get("replicate_of")
        if r is not None and r not in defined:
            raise ConfigError(
                f"params.yaml: 'risk_model.variants.{v}.replicate_of' names no variant of "
                f"'risk_model.variants' {sorted(defined)}: {r!r}"
            )
    return out


def risk_stage_settings(p):
    """What select_risk and evaluate_risk both read, validated once: ``evaluation.risk``, the
    subject footprint, the run variants and their settings, the primary label, the ORB filter."""
    ev = typed(p.get("evaluation", {}).get("risk"), EvalRiskConfig, key="evaluation.risk")
    subject = typed(p.get("risk_data", {}).get("metric"), MetricParams, key="risk_data.metric")
    variants = run_variants(p)
    ev.check_variants(variants)
    settings = variant_settings(p, variants)
    primary = get(p, "risk_model.label", str, choices=LABELS)
    return ev, subject, variants, settings, primary, get(p, "risk_model.orb_filter", bool)


def suite_settings(ev, subject, primary: str, variants: dict, selection: dict, holdout: list):
    """The suite's settings from ``evaluation.risk`` (``ev``), the subject footprint, the primary
    label, the variants' settings, the choices made on validation and the held-out templates."""
    ci = typed(ev.ci, CIConfig, key="evaluation.risk.ci")
    length, width = subject.subject_length, subject.subject_width
    rules = {
        r: ev.geometric.params(length, width, e["half_width"])
        for r, e in selection["rules"].items()
    }
    decisions = {
        name: {float(t): d["cut"] for t, d in e["decision"].items()}
        for name, e in selection["predictors"].items()
    }
    decisions[SHIPPED] = decisions[selection["shipped"]["predictor"]]
    return SuiteSettings(
        primary_label=primary,
        thresholds_s=tuple(ev.thresholds_s),
        thw_cap=ev.thw_cap_s,
        geometric=ev.geometric.params(length, width),
        batch_size=ev.batch_size,
        main_variant=ev.main_variant,
        variants=variants,
        ci=ci,
        collapse_std=ev.collapse_std,
        rule_params=rules,
        decisions=decisions,
        shipped=SHIPPED,
        learned=selection.get("learned"),
        holdout=Holdout(tuple(holdout), HOLDOUT, HYBRID) if holdout else None,
    )


def load_models(variants: list[str], hybrids: list[str]) -> dict:
    """The trained variants, the hybrid runs and the shipped predictor (select_risk)."""
    from traffictwin.risk.model_io import load_risk_model

    def model_dir(v: str):
        if v in hybrids:
            return hybrid_model_dir(v)
        return SHIPPED_RISK_MODEL if v == SHIPPED else risk_model_dir(v)

    return {v: load_risk_model(model_dir(v)) for v in [*variants, *hybrids, SHIPPED]}


def loaded_settings(models: dict, variants: list[str]) -> dict[str, dict]:
    """Variant settings of the runs that are no ``risk_model`` variant, from their metadata."""
    return {
        v: {
            "replicate_of": None if v == SHIPPED else m.meta.get("replicate_of"),
            "objective": m.meta.get("objective"),
            "seed_offset": m.meta.get("seed_offset", 0),
        }
        for v, m in models.items()
        if v not in variants
    }


def write_outputs(metrics: dict, pred: pd.DataFrame, ev) -> None:
    """The confusion and prediction tables and risk.json (the figures are drawn from them by
    plot_data)."""
    _, y, yhat = main_series(metrics, pred, ev.main_variant)
    _write_csv(
        confusion_table(pred["frame_id"], y, yhat, ev.thresholds_s[0]), plot_file("risk_confusion")
    )
    _write_csv(pred, plot_file("risk_predictions"))
    write_json_atomic(METRICS, metrics)


def summary(metrics: dict, selection: dict, threshold_s: float) -> dict[str, float]:
    """The handful of numbers a person compares between experiments, flat ``split/name`` keys:
    the shipped predictor's validation ROC-AUC and balanced accuracy (where select_risk chose it:
    ``val/roc_auc``, ``val/balanced_accuracy``) and its test ROC-AUC, balanced accuracy and
    accuracy of critical frames (THW < ``threshold_s``, the first threshold). A number that is
    missing or not finite (ROC-AUC of one-class frames) is left out."""
    t = f"{threshold_s:g}"
    shipped = selection.get("shipped") or {}
    val_cut = (shipped.get("decision") or {}).get(t) or {}
    test = ((metrics.get("models") or {}).get(SHIPPED) or {}).get(f"at_{t}s") or {}
    out = {
        "val/roc_auc": shipped.get("roc_auc"),
        "val/balanced_accuracy": val_cut.get("balanced_accuracy"),
        "test/roc_auc": test.get("roc_auc"),
        "test/balanced_accuracy": test.get("balanced_accuracy"),
        "test/accuracy": test.get("accuracy"),
    }
    return {
        k: float(v)
        for k, v in out.items()
        if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
    }


def _log_summary(log: logging.Logger, metrics: dict, ev) -> None:
    """The shipped predictor's headline numbers, and the collapsed models (if any)."""
    t0 = ev.thresholds_s[0]
    sh = metrics["models"][SHIPPED][f"at_{t0:g}s"]
    log.info(
        "evaluate_risk: shipped %s: balanced accuracy %s, ROC-AUC %s at THW %g s on %d test frames",
        metrics["selection"]["shipped_from"],
        _fmt3(sh.get("balanced_accuracy")),
        _fmt3(sh.get("roc_auc")),
        t0,
        metrics["models"][ev.main_variant]["test/n"],
    )
    failed = [v for v, e in metrics["models"].items() if e.get("collapsed")]
    if failed:
        log.warning(
            "evaluate_risk: collapsed model(s) %s (test prediction std < %g): reported as failed runs",
            failed,
            ev.collapse_std,
        )


def main() -> None:
    # the evaluation's own imports (torch, matplotlib): the settings above are read without them
    from traffictwin.risk.predictors import predictor_kind
    from traffictwin.risk.source import RiskSource

    log = setup_logging()
    p = params()
    ev, subject, variants, settings, primary, orb_filter = risk_stage_settings(p)
    selection = read_selection()
    _, seeds, holdout = hybrid_settings(p)
    suite = suite_settings(ev, subject, primary, settings, selection, holdout)
    suite = replace(suite, acceptance=for_problem(p, "risk", TARGET_NAMES))
    with stage_timer("evaluate_risk") as record:
        record["torch_threads"] = pin_torch_threads(p)
        source = RiskSource(
            RISK_DATA, DISPARITY, ORB_CSV if orb_filter else None, learned_root=STEREO_LEARNED
        )
        hybrids = [
            *hybrid_runs(seeds),
            *holdout_runs(seeds, holdout),
            *learned_runs(seeds, learned_disparity(p)),
        ]
        models = load_models(variants, hybrids)
        suite = replace(suite, variants={**settings, **loaded_settings(models, variants)})
        metrics, pred = evaluate_suite(source, models, suite)
        metrics["selection"] = {
            "file": SELECTION.name,
            "split": selection["split"],
            "shipped_from": selection["shipped"]["predictor"],
            "shipped_kind": predictor_kind(models[SHIPPED]),
            "rules": {r: e["half_width"] for r, e in selection["rules"].items()},
        }
        write_outputs(metrics, pred, ev)
        write_json_atomic(SUMMARY, summary(metrics, selection, ev.thresholds_s[0]))
        _log_to_mlflow(models, metrics, log)
        _log_summary(log, metrics, ev)


if __name__ == "__main__":
    run_stage(main, "evaluate_risk")
