"""Stage `select_risk`: every choice of the risk evaluation, made on the validation split.

Reads ``evaluation.risk.*`` (thresholds, the rule's candidate ``geometric.half_widths``, the
main variant, ``collapse_std``), ``risk_model.run_variants`` / ``variants`` / ``label`` /
``orb_filter``, ``risk_hybrid.seeds``, ``risk_data.metric``; the models ``models/risk/<variant>``
and ``models/risk_hybrid/*``; data ``data/risk``, ``data/disparity``, ``data/orb/orb.csv``.

On the validation frames only, it picks

* the corridor half-width of the SGM rule and of the GT-disparity rule (highest ROC-AUC),
* every predictor's decision threshold at each THW threshold (highest balanced accuracy),
* the predictor to ship (highest ROC-AUC at the primary threshold among the runs of the main
  network variant, the hybrid runs and the SGM rule; a tie goes to the simpler),

and writes ``models/risk_shipped/`` (that predictor's ``model.ckpt`` + ``model_meta.json``, which
records what it is and why; the registry's risk model and ``traffictwin risk`` serve it) and
``reports/metrics/risk_selection.json`` (every candidate's validation figures and the choices;
``evaluate_risk`` applies them to the test split, which this stage never reads).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from traffictwin.config import get
from traffictwin.io.atomic import write_bytes_atomic, write_json_atomic
from traffictwin.io.jsonio import json_clean
from traffictwin.model_format import CKPT_SHA_KEY
from traffictwin.risk.baselines import corridor_distances, fit_speed_only, thw_from_distance
from traffictwin.risk.metric import risk_threshold, thw_to_risk
from traffictwin.risk.model_io import CKPT, META, load_risk_model, save_predictor
from traffictwin.risk.predictors import GeometricRiskModel, predictor_kind
from traffictwin.risk.selection import best_cut, choose, roc_auc, tune_half_width
from traffictwin.risk.training import RiskSource, check_label, input_keys

from ._common import params, run_stage, setup_logging, stage_timer
from ._paths import (
    DISPARITY,
    ORB_CSV,
    RISK_DATA,
    SHIPPED_RISK_MODEL,
    hybrid_model_dir,
    metrics_file,
    risk_model_dir,
)
from .evaluate_risk import risk_stage_settings
from .train_risk_hybrid import holdout_runs, hybrid_runs, hybrid_settings

SHIPPED = "shipped"
SELECTION = metrics_file("risk_selection")
RULES = {"geometric_sgm": "disp_sgm", "geometric_gt": "disp_gt"}
_CAMERA_KEYS = ("fx", "fy", "cx", "cy", "baseline", "mount_x", "mount_height", "width", "height")


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


def track_shipped(p, sel: dict, folder) -> dict:
    """An MLflow run ``risk-shipped`` (experiment ``risk``) with the validation figures and the
    shipped predictor logged as a model (the registry's ``traffictwin-risk`` registers it); the
    run-record fields ``run_id``, ``model_uri``, ``model_sha256``."""
    from traffictwin.io.shards import sha256_file
    from traffictwin.mlops import model_artifact as art
    from traffictwin.mlops import tracking

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
            **{f"rules.{r}.half_width": e["half_width"] for r, e in sel["rules"].items()},
        },
    ) as run:
        import mlflow

        mlflow.log_metrics(metrics)
        uri, _ = art.log_model(
            {art.CKPT: folder / CKPT, art.META: folder / META},
            problem="risk",
            metadata={"variant": SHIPPED, "predictor": sh["predictor"], "kind": sh["kind"]},
        )
        return {
            "run_id": run.info.run_id,
            "model_uri": uri,
            "model_sha256": sha256_file(folder / CKPT),
        }


def main() -> None:
    log = setup_logging()
    p = params()
    ev, subject, variants, settings, primary, orb_filter = risk_stage_settings(p)
    _, seeds, holdout = hybrid_settings(p)
    held_runs = holdout_runs(seeds, holdout)
    t0 = ev.thresholds_s[0]
    half_widths = [float(w) for w in ev.geometric.half_widths]

    with stage_timer("select_risk") as record:
        source = RiskSource(RISK_DATA, DISPARITY, ORB_CSV if orb_filter else None)
        camera = source.camera
        models = {v: load_risk_model(risk_model_dir(v)) for v in variants}
        models.update(
            {h: load_risk_model(hybrid_model_dir(h)) for h in [*hybrid_runs(seeds), *held_runs]}
        )
        label_of = {v: str(m.meta.get("label") or primary) for v, m in models.items()}
        on_primary = {v: m for v, m in models.items() if label_of[v] == primary}
        frames = source.split_frames("val")
        fpath = str(source.risk.root / "frames.csv")
        if len(frames) == 0:
            raise ValueError(f"{fpath}: the validation split has no frames (after the ORB check)")
        keys = sorted(
            {k for m in on_primary.values() for k in input_keys(m.cfg)} | set(RULES.values())
        )
        geo = ev.geometric.params(subject.subject_length, subject.subject_width)
        preds: dict[str, list[np.ndarray]] = {v: [] for v in on_primary}
        dists: dict[str, list[np.ndarray]] = {r: [] for r in RULES}
        order = []
        for rows, arr in source.iter_arrays(frames, keys):
            sp = rows["speed"].to_numpy(np.float64)
            for v, m in on_primary.items():
                preds[v].append(
                    m.predict(
                        arr.get("left"),
                        arr.get("disp_sgm"),
                        arr.get("disp_gt"),
                        speed=sp.astype(np.float32),
                        batch_size=ev.batch_size,
                    )
                )
            for r, k in RULES.items():
                dists[r].append(corridor_distances(arr[k], camera, geo, half_widths))
            order.append(rows)
        rows = pd.concat(order)
        y = check_label(rows, primary, fpath).astype(np.float64)
        speed = rows["speed"].to_numpy(np.float64)
        score = {v: np.concatenate(ps).astype(np.float64) for v, ps in preds.items()}

        sel: dict = {
            "split": "val",
            "n_frames": int(len(rows)),
            "n_sequences": int(rows["scenario"].nunique()),
            "label": primary,
            "thresholds_s": [float(t) for t in ev.thresholds_s],
            "criterion": f"ROC-AUC of critical (THW < {t0:g} s) on the validation split",
            "holdout_templates": list(holdout),
            "rules": {},
            "predictors": {},
        }
        for r in RULES:
            d = np.concatenate(dists[r])
            w, table = tune_half_width(d, speed, y > risk_threshold(t0), half_widths, t0)
            k = half_widths.index(w)
            score[r] = thw_to_risk(thw_from_distance(d[:, k], speed)).astype(np.float64)
            sel["rules"][r] = {  # keyed by width, "1p25" for 1.25 m (dotted report keys)
                "half_width": w,
                "candidates": {f"{c['half_width']:g}".replace(".", "p"): c for c in table},
            }

        def kind_of(name: str) -> str:
            if name in RULES:
                return "geometric"
            return "speed_only" if name == "speed_only" else predictor_kind(models[name])

        def group_of(name: str) -> str:
            """A run's variant group: its ``replicate_of`` (settings or model meta), else itself."""
            if name not in models:
                return name
            rep = (settings.get(name) or {}).get("replicate_of") or models[name].meta.get(
                "replicate_of"
            )
            return str(rep or name)

        train = source.split_frames("train")
        if len(train):  # the speed-only baseline (fitted on train) gets its cut on validation too
            so = fit_speed_only(
                train["speed"].to_numpy(np.float64),
                check_label(train, primary, fpath).astype(np.float64),
            )
            score["speed_only"] = so.predict(speed)
        seen = ~rows["template"].isin(holdout).to_numpy() if holdout else np.ones(len(y), bool)
        for name, s in score.items():
            # a run trained without the held-out templates is tuned on the validation frames of
            # the templates it saw (so its held-out test frames stay unseen)
            m = seen if name in held_runs else np.ones(len(y), bool)
            spread = float(np.std(s[m]))
            entry = {
                "kind": kind_of(name),
                "group": group_of(name),
                "pred_std": spread,
                "collapsed": bool(spread < ev.collapse_std),
                "roc_auc": roc_auc(y[m] > risk_threshold(t0), s[m]),
                "n_frames": int(m.sum()),
                "decision": {},
            }
            for t in ev.thresholds_s:
                cut, ba = best_cut(y[m] > risk_threshold(t), s[m], risk_threshold(t))
                entry["decision"][f"{t:g}"] = {"cut": cut, "balanced_accuracy": ba}
            sel["predictors"][name] = entry
        # the groups: seed-averaged validation AUC of every learned variant on the primary label
        groups: dict[str, list[str]] = {}
        for name, e in sel["predictors"].items():
            if name in models:
                groups.setdefault(e["group"], []).append(name)
        sel["groups"] = {
            g: {
                "runs": runs,
                "kind": sel["predictors"][runs[0]]["kind"],
                "roc_auc_mean": float(np.mean([sel["predictors"][r]["roc_auc"] for r in runs])),
            }
            for g, runs in groups.items()
        }
        main_group = (settings.get(ev.main_variant) or {}).get("replicate_of") or ev.main_variant
        learned = [g for g in (main_group, "hybrid") if g in sel["groups"]]
        sel["learned"] = (
            max(learned, key=lambda g: sel["groups"][g]["roc_auc_mean"]) if learned else None
        )
        candidates = {
            n: sel["predictors"][n]
            for n in [*(r for g in learned for r in sel["groups"][g]["runs"]), "geometric_sgm"]
            # a collapsed learned run is a failed run; the rule is no trained model (a constant
            # output only says the validation frames had nothing in its corridor)
            if n in RULES or not sel["predictors"][n]["collapsed"]
        }
        shipped = choose(candidates)
        c = sel["predictors"][shipped]
        sel["shipped"] = {
            "predictor": shipped,
            "kind": c["kind"],
            "roc_auc": c["roc_auc"],
            "candidates": sorted(candidates),
            "decision": c["decision"],
        }
        out = SHIPPED_RISK_MODEL
        extra = {"shipped": sel["shipped"], "variant": SHIPPED, "label": primary}
        if shipped in RULES:
            rule = GeometricRiskModel(
                ev.geometric.params(
                    subject.subject_length,
                    subject.subject_width,
                    sel["rules"][shipped]["half_width"],
                ),
                {k: float(camera[k]) for k in _CAMERA_KEYS},
            )
            any_model = next(iter(on_primary.values()))
            save_predictor(
                rule,
                out,
                {**extra, "objective": "rule", "domain": any_model.meta.get("domain", {})},
            )
        else:
            _copy_model(
                hybrid_model_dir(shipped)
                if shipped in hybrid_runs(seeds)
                else risk_model_dir(shipped),
                out,
                extra,
            )
        sel = json_clean(sel)  # undefined figures (one class on validation) as null
        write_json_atomic(SELECTION, sel)
        record["shipped"] = shipped
        record.update(track_shipped(p, sel, out))
        log.info(
            "select_risk: rules SGM %.2f m, GT %.2f m; shipped %s (%s, validation ROC-AUC %.3f) -> %s",
            sel["rules"]["geometric_sgm"]["half_width"],
            sel["rules"]["geometric_gt"]["half_width"],
            shipped,
            c["kind"],
            c["roc_auc"],
            out,
        )


if __name__ == "__main__":
    run_stage(main, "select_risk")
