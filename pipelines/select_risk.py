"""Stage `select_risk`: every choice of the risk evaluation, made on the validation split.

Reads ``evaluation.risk.*`` (thresholds, the rule's candidate ``geometric.half_widths``, the
main variant, ``collapse_std``), ``risk_model.run_variants`` / ``variants`` / ``label`` /
``orb_filter``, ``risk_hybrid.seeds``, ``risk_data.metric``; the models ``models/risk/<variant>``
and ``models/risk_hybrid/*``; data ``data/risk``, ``data/disparity``, ``data/orb/orb.csv``.

On the validation frames only (:func:`traffictwin.risk.selection_suite.select_on_validation`),
it picks

* the corridor half-width of the SGM rule and of the GT-disparity rule (highest ROC-AUC),
* every predictor's decision threshold at each THW threshold (highest balanced accuracy),
* the predictor to ship (highest ROC-AUC at the primary threshold among the runs of the main
  network variant, the hybrid runs and the SGM rule; a tie goes to the simpler),

unless the validation frames hold fewer than 5 critical or uncritical frames: then nothing is
chosen on them (a NaN score never ships), the rules take the label's corridor half-width and the
SGM rule ships, and both records carry a ``note`` saying why,

and writes ``models/risk_shipped/`` (that predictor's ``model.ckpt`` + ``model_meta.json``, which
records what it is and why; the registry's risk model and ``traffictwin risk`` serve it) and
``reports/metrics/risk_selection.json`` (every candidate's validation figures and the choices;
``evaluate_risk`` applies them to the test split, which this stage never reads).
"""

from __future__ import annotations

import shutil
from collections.abc import Collection
from dataclasses import asdict

import numpy as np

from traffictwin.config import get
from traffictwin.io.atomic import write_bytes_atomic, write_json_atomic
from traffictwin.model_format import CKPT_SHA_KEY
from traffictwin.risk.model_io import CKPT, META, load_risk_model, save_predictor
from traffictwin.risk.predictor import PACKAGED_STEREO
from traffictwin.risk.selection_suite import (
    RULES,
    Selection,
    SelectionSetup,
    on_label,
    select_on_validation,
    shipped_rule,
)
from traffictwin.risk.source import RiskSource

from ._common import params, run_stage, setup_logging, stage_timer
from ._paths import (
    DISPARITY,
    ORB_CSV,
    RISK_DATA,
    SHIPPED_RISK_MODEL,
    STEREO_LEARNED,
    STEREO_MODEL,
    hybrid_model_dir,
    metrics_file,
    risk_model_dir,
)
from .evaluate_risk import risk_stage_settings
from .train_risk_hybrid import (
    holdout_runs,
    hybrid_runs,
    hybrid_settings,
    learned_disparity,
    learned_runs,
)

SHIPPED = "shipped"
SELECTION = metrics_file("risk_selection")


def _copy_model(src_dir, out_dir, extra_meta: dict) -> None:
    """Publish a trained model folder's pair under ``out_dir`` (old meta removed first, checkpoint,
    then the meta with ``extra_meta`` added, each atomically: :func:`save_model_files`' order)."""
    import json

    out_dir.mkdir(parents=True, exist_ok=True)
    meta = json.loads((src_dir / META).read_text())
    (out_dir / META).unlink(missing_ok=True)
    write_bytes_atomic(out_dir / CKPT, (src_dir / CKPT).read_bytes())
    if CKPT_SHA_KEY not in meta:
        raise ValueError(f"{src_dir / META}: no {CKPT_SHA_KEY} (re-run its training stage)")
    write_json_atomic(out_dir / META, {**meta, **extra_meta})


def serving_signature(folder, source: RiskSource) -> tuple[object, np.ndarray]:
    """The MLflow signature and input example of the risk model in ``folder``: what its pyfunc
    serves (:func:`~traffictwin.risk.predictors.packed_for_serving`) for the first validation
    frame of ``source``, and the served output on it."""
    import torch
    from mlflow.models import infer_signature

    from traffictwin.risk.predictor import RiskFrames
    from traffictwin.risk.predictors import packed_for_serving
    from traffictwin.risk.source import input_keys

    model = load_risk_model(folder)
    frames = source.split_frames("val").iloc[:1]
    if len(frames) == 0:
        frames = source.frames.iloc[:1]
    rows, arr = next(iter(source.iter_arrays(frames, input_keys(model.cfg))))
    module, x = packed_for_serving(
        model, RiskFrames.of_arrays(arr, rows["speed"].to_numpy(np.float32))
    )
    with torch.no_grad():
        y = module(torch.from_numpy(x)).float().numpy()
    return infer_signature(x, y), x


def track_shipped(p, sel: dict, folder, source: RiskSource | None = None) -> dict:
    """An MLflow run ``risk-shipped`` (experiment ``risk``) with the validation figures and the
    shipped predictor logged as a model (the registry's ``traffictwin-risk`` registers it) with
    its signature and a validation frame as input example (:func:`serving_signature`, given
    ``source``); the run-record fields ``run_id``, ``model_uri``, ``model_sha256``."""
    from traffictwin.io.shards import sha256_file
    from traffictwin.mlops import model_artifact as art
    from traffictwin.mlops import tracking

    signature, example = serving_signature(folder, source) if source is not None else (None, None)

    sh = sel["shipped"]
    metrics = {
        f"val/{name}/roc_auc": e["roc_auc"]
        for name, e in sel["predictors"].items()
        if e["roc_auc"] is not None and np.isfinite(e["roc_auc"])
    }
    for r, e in sel["rules"].items():
        metrics[f"val/{r}/half_width_m"] = e["half_width"]
    with tracking.start_run(
        "risk",
        "risk-shipped",
        profile=get(p, "profile.name", str),
        stage="select_risk",
        params={
            "shipped.predictor": sh["predictor"],
            "shipped.kind": sh["kind"],
            "criterion": sel["criterion"],
            **({"shipped.note": sh["note"]} if sh.get("note") else {}),
            **{f"rules.{r}.half_width": e["half_width"] for r, e in sel["rules"].items()},
        },
    ) as run:
        import mlflow

        mlflow.log_metrics(metrics)
        uri, _ = art.log_model(
            {art.CKPT: folder / CKPT, art.META: folder / META},
            problem="risk",
            signature=signature,
            input_example=example,
            metadata={"variant": SHIPPED, "predictor": sh["predictor"], "kind": sh["kind"]},
        )
        return {
            "run_id": run.info.run_id,
            "model_uri": uri,
            "model_sha256": sha256_file(folder / CKPT),
        }


def _publish_shipped(
    sel: Selection, setup: SelectionSetup, models, source, seeds, learned: Collection[str] = ()
) -> None:
    """``models/risk_shipped/``: the shipped predictor's ``model.ckpt`` + ``model_meta.json``
    (what it is and why): the rule saved at its half-width, else the trained run's folder copied;
    a run of ``learned`` (the hybrid on the learned stereo network's disparity) with that
    network in ``stereo/``."""
    shipped = sel.shipped.predictor
    extra = {"shipped": asdict(sel.shipped), "variant": SHIPPED, "label": setup.primary}
    if shipped in RULES:
        any_model = next(iter(on_label(models, setup.primary).values()))
        save_predictor(
            shipped_rule(sel, setup, source.camera),
            SHIPPED_RISK_MODEL,
            {**extra, "objective": "rule", "domain": any_model.meta.get("domain", {})},
        )
    else:
        hybrids = [*hybrid_runs(seeds), *learned]
        _copy_model(
            hybrid_model_dir(shipped) if shipped in hybrids else risk_model_dir(shipped),
            SHIPPED_RISK_MODEL,
            extra,
        )
    # a shipped predictor that reads the learned stereo network's disparity carries that network
    # (api.load_risk finds it in the folder's PACKAGED_STEREO); any other ships without one
    packaged = SHIPPED_RISK_MODEL / PACKAGED_STEREO
    shutil.rmtree(packaged, ignore_errors=True)
    if shipped in learned:
        _copy_model(STEREO_MODEL, packaged, {})


def main() -> None:
    log = setup_logging()
    p = params()
    ev, subject, variants, settings, primary, orb_filter = risk_stage_settings(p)
    _, seeds, holdout = hybrid_settings(p)
    held_runs = holdout_runs(seeds, holdout)
    on_learned = learned_runs(seeds, learned_disparity(p))
    setup = SelectionSetup(ev, subject, primary, settings, held_runs, holdout)

    with stage_timer("select_risk") as record:
        source = RiskSource(
            RISK_DATA, DISPARITY, ORB_CSV if orb_filter else None, learned_root=STEREO_LEARNED
        )
        models = {v: load_risk_model(risk_model_dir(v)) for v in variants}
        models.update(
            {
                h: load_risk_model(hybrid_model_dir(h))
                for h in [*hybrid_runs(seeds), *held_runs, *on_learned]
            }
        )
        selection = select_on_validation(source, models, setup)
        _publish_shipped(selection, setup, models, source, seeds, on_learned)
        sel = selection.to_json()
        write_json_atomic(SELECTION, sel)
        record["shipped"] = selection.shipped.predictor
        record.update(track_shipped(p, sel, SHIPPED_RISK_MODEL, source))
        sh = selection.shipped
        log.info(
            "select_risk: rules SGM %.2f m, GT %.2f m; shipped %s (%s, %s) -> %s",
            selection.rules["geometric_sgm"].half_width,
            selection.rules["geometric_gt"].half_width,
            sh.predictor,
            sh.kind,
            sh.note or f"validation ROC-AUC {sh.roc_auc:.3f}",
            SHIPPED_RISK_MODEL,
        )


if __name__ == "__main__":
    run_stage(main, "select_risk")
