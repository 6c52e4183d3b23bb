"""Promotion gate: register the freshly trained models, compare each with its champion, move aliases.

Not a DVC stage (it changes the MLflow registry, which DVC cannot cache); run after `dvc repro`:

    python -m pipelines.promote [--only traffictwin-fusion traffictwin-risk] [--dry-run] [--force]

One gate per task: the one fusion network (``registry.fusion.name``, ``traffictwin-fusion``), the
one learned registration (``registry.registration.name``, ``traffictwin-registration``), the
learned stereo network (``registry.stereo.name``, ``traffictwin-stereo``, when params.yaml has a
``stereo_model`` group) and the risk variant ``registry.risk.variant`` (``traffictwin-risk``); settings from the ``registry``
group (validated once), folders from ``pipelines/_paths.py``. The work is
:func:`traffictwin.mlops.promotion.promote`: every candidate (its MLflow run id from the training
stage's run record, ``reports/timings/<stage>.json``) is registered (once) as a version of its
name, and it and the current ``champion`` are evaluated on the same fixed gate set (validation
pairs of every configuration; validation frames for risk) with the evaluation stages' metric code; all decisions are taken first, then applied, so an evaluation failure moves
no alias. The whole run holds the registry lock (``<mlflow.db>.gate.lock``): a second gate waits
and then decides against the champion this one left. A champion that cannot be evaluated stops
the run with every champion kept, unless it is known-incompatible (another grid, a pickled model
of an older version), which is recorded and skipped. Exit status 0 on success (whatever the
decisions), 1 on an error (one line naming the file/model/key). It prints one row per model:
name, version, decision (champion / challenger / rejected), the gate metric with both figures,
and why (:func:`traffictwin.mlops.promotion.format_table`); ``--json`` prints the decisions.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable
from pathlib import Path

from omegaconf import DictConfig

from pipelines._common import params, setup_logging
from pipelines._paths import (
    DISPARITY,
    ORB_CSV,
    RISK_DATA,
    ROOT,
    SHIPPED_RISK_MODEL,
    STEREO_MODEL,
    fusion_model_dir,
    metrics_file,
    prealigned,
    registration_model_dir,
    risk_model_dir,
    run_record_file,
)
from traffictwin.config import ConfigError, get, typed
from traffictwin.fusion.config import pose_configurations, training_noise
from traffictwin.mlops import promotion
from traffictwin.mlops.config import RegistryConfig
from traffictwin.mlops.gate import Decision
from traffictwin.mlops.uris import mask_secrets
from traffictwin.risk.config import EvalRiskConfig

SHIPPED = "shipped"  # registry.risk.variant: the predictor select_risk chose on validation


def registry_config(cfg: DictConfig) -> RegistryConfig:
    """The validated ``registry`` group; its risk variant must be ``shipped`` (the predictor
    select_risk chose on validation) or one of ``risk_model.run_variants``."""
    rc = typed(get(cfg, "registry", dict), RegistryConfig, key="registry")
    variants = get(cfg, "risk_model.run_variants", list)
    if rc.risk.variant != SHIPPED and rc.risk.variant not in variants:
        raise ConfigError(
            f"params.yaml: 'registry.risk.variant' is '{rc.risk.variant}', "
            f"not '{SHIPPED}' or one of risk_model.run_variants {variants}"
        )
    return rc


def configurations(cfg: DictConfig) -> list[str]:
    """The pose-noise configurations (keys of ``configurations``): the fusion gates' data."""
    return list(pose_configurations(cfg))


def model_names(cfg: DictConfig, rc: RegistryConfig) -> list[str]:
    """Registered-model names of every gate: the fusion network, the learned registration (when
    params.yaml has a ``registration_model`` group), the learned stereo network (a
    ``stereo_model`` group), risk."""
    names = [rc.fusion.name]
    if "registration_model" in cfg:
        names.append(rc.registration.name)
    if "stereo_model" in cfg:
        names.append(rc.stereo.name)
    return [*names, rc.risk.name]


def _rel(path: Path) -> str:
    return str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path)


FUSION_CARD_KEYS = ("kld_fou_mean", "kld_fo_mean", "dice_occ", "dice_free", "u_auroc", "u_mean")
RISK_CARD_KEYS = (
    "test/mse",
    "test/rmse",
    "test/mae",
    "test/thw_mae_s",
    "test/thw_mae_critical_s",
    "test/thw_median_error_critical_s",
)
SIM_LIMIT = "Trained and tested on the project's own simulator, not on real sensor data."


def _card_metrics(name: str, path: list[str], keys: tuple[str, ...]) -> tuple[dict, str]:
    """``keys`` (and their intervals as ``<key>_ci`` {lo, hi}: a ``<key>_ci`` mapping, or the flat
    ``<key>_lo`` / ``<key>_hi`` of stereo.json) at ``path`` of ``reports/metrics/<name>.json``
    (the evaluation stage's output for the model folders the candidates come from); ``{}`` if
    absent."""
    f = metrics_file(name)
    try:
        node = json.loads(f.read_text())
        for k in path:
            node = node[k]
    except (OSError, json.JSONDecodeError, KeyError, TypeError):
        return {}, ""
    out = {k: node[k] for k in keys if k in node}
    out.update({f"{k}_ci": node[f"{k}_ci"] for k in keys if f"{k}_ci" in node})
    out.update(
        {
            f"{k}_ci": {"lo": node[f"{k}_lo"], "hi": node[f"{k}_hi"]}
            for k in keys
            if f"{k}_lo" in node and f"{k}_hi" in node
        }
    )
    return out, f"{_rel(f)} (test split)"


def fusion_card(row: str, cfg: DictConfig) -> Callable[[promotion.Candidate], promotion.ModelCard]:
    """The model card facts of the one fusion network (``row`` ``dnn``) or the learned
    registration (``learned``): its test numbers at every configuration."""

    def card(cand: promotion.Candidate) -> promotion.ModelCard:
        g = cfg["grid"]
        metrics: dict = {}
        source = ""
        for c in configurations(cfg):
            m, source = _card_metrics("fusion", ["test", c, row], FUSION_CARD_KEYS)
            metrics.update({f"{c}/{k}": v for k, v in m.items()})
        configs = pose_configurations(cfg)
        noise = ", ".join(
            f"{c}: r = {configs[c].r} m, alpha = {configs[c].alpha} deg"
            for c in training_noise(cfg).names(configs)
        )
        return promotion.ModelCard(
            data=f"{_rel(prealigned('mixed'))}: simulated cooperative pairs of lidar grids, pose "
            f"noise drawn across the configurations ({noise}; 98 % intervals).",
            metrics=metrics,
            metrics_source=source,
            limits=(
                SIM_LIMIT,
                f"Only for {g['rows']} x {g['cols']} grids of {g['cell']} m cells and pose errors "
                "within the training noise; larger errors are outside its training data.",
                "KLD(b) (kld_fou_mean) is the headline; kld_fo_mean is the paper group's "
                "formula, not a divergence.",
            ),
        )

    return card


def risk_card(variant: str) -> Callable[[promotion.Candidate], promotion.ModelCard]:
    """The model card facts of risk variant ``variant``."""

    def card(cand: promotion.Candidate) -> promotion.ModelCard:
        metrics, source = _card_metrics("risk", ["models", variant], RISK_CARD_KEYS)
        label = cand.meta.get("label", "?")
        return promotion.ModelCard(
            data=f"{_rel(RISK_DATA)}: simulated stereo frames that passed the ORB pair check; "
            f"label {label}.",
            metrics=metrics,
            metrics_source=source,
            limits=(
                SIM_LIMIT,
                "Risk is min(1/THW, 20)/20 for one region definition; frames the ORB check "
                "rejects are outside its domain.",
            ),
        )

    return card


STEREO_CARD_KEYS = ("epe", "bad1", "bad2", "crit_obj_relerr_median", "crit_obj_relerr_p90")


def stereo_card(cand: promotion.Candidate) -> promotion.ModelCard:
    """The model card facts of the learned stereo network: its test numbers on its own valid
    pixels (reports/metrics/stereo.json)."""
    metrics, source = _card_metrics(
        "stereo", [], tuple(f"learned/own/{k}" for k in STEREO_CARD_KEYS)
    )
    size = cand.meta.get("image_size") or ["?", "?"]
    return promotion.ModelCard(
        data=f"{_rel(RISK_DATA)}: fault-free simulated stereo pairs with their exact disparity"
        + (
            f", refining {_rel(DISPARITY)}'s SGM"
            if cand.meta.get("architecture", {}).get("base") == "sgm"
            else ""
        )
        + ".",
        metrics=metrics,
        metrics_source=source,
        limits=(
            SIM_LIMIT,
            f"Only for rectified pairs of {size[1]} x {size[0]} px from the training camera "
            "(disparity in that camera's pixel scale); pairs the ORB check rejects are outside "
            "its domain.",
        ),
    )


def _fusion_jobs(cfg: DictConfig, rc: RegistryConfig) -> list[promotion.GateJob]:
    """The fusion network's gate job, and the learned registration's where it is configured."""
    from traffictwin.fusion.gate_eval import fusion_evaluator, fusion_test_set

    f, g = rc.fusion, rc.registration
    roots = [prealigned(c) for c in configurations(cfg)]

    def make_fusion_eval(cand):
        x, y, fp = fusion_test_set(roots, f.split, f.max_pairs)
        return fusion_evaluator(x, y, f.batch_size, f.split), fp

    jobs = [
        promotion.GateJob(
            name=f.name,
            gate=f.gate(),
            model_dir=fusion_model_dir(),
            make_evaluator=make_fusion_eval,
            record_path=run_record_file("train_fusion"),
            tags={"model_dir": _rel(fusion_model_dir())},
            card=fusion_card("dnn", cfg),
        )
    ]
    # the learned registration: scored by the KLD(b) of its Dempster-fused map, on the same kind
    # of pairs with their noisy poses
    from traffictwin.fusion.gate_eval import registration_evaluator, registration_test_set

    if "registration_model" in cfg:

        def make_registration_eval(cand):
            x, y, poses, fp = registration_test_set(roots, g.split, g.max_pairs)
            return registration_evaluator(x, y, poses, g.batch_size, g.split), fp

        jobs.append(
            promotion.GateJob(
                name=g.name,
                gate=g.gate(),
                model_dir=registration_model_dir(),
                make_evaluator=make_registration_eval,
                record_path=run_record_file("train_registration"),
                tags={"model_dir": _rel(registration_model_dir())},
                card=fusion_card("learned", cfg),
            )
        )
    return jobs


def _stereo_job(cfg: DictConfig, rc: RegistryConfig) -> promotion.GateJob:
    """The learned stereo network's gate job: end-point error on the gate split's fault-free pairs."""
    from traffictwin.risk.stereo_gate import stereo_evaluator, stereo_test_set

    s = rc.stereo
    base = get(cfg, "stereo_model.architecture.base", str)

    def make_stereo_eval(cand):
        data, fp = stereo_test_set(
            RISK_DATA, DISPARITY if base == "sgm" else None, s.split, s.max_frames
        )
        return stereo_evaluator(data, s.batch_size, s.split), fp

    return promotion.GateJob(
        name=s.name,
        gate=s.gate(),
        model_dir=STEREO_MODEL,
        make_evaluator=make_stereo_eval,
        record_path=run_record_file("train_stereo"),
        tags={"model_dir": _rel(STEREO_MODEL)},
        card=stereo_card,
    )


def _risk_job(cfg: DictConfig, rc: RegistryConfig) -> promotion.GateJob:
    """The risk variant's gate job (the shipped model's, or ``rc.risk.variant``'s)."""
    from traffictwin.risk.gate_eval import risk_evaluator, risk_test_set

    r = rc.risk
    # keys of other groups the risk gate shares with the evaluate_risk stage
    default_label = get(cfg, "risk_model.label", str)
    ev = typed(cfg["evaluation"]["risk"], EvalRiskConfig, key="evaluation.risk")
    thresholds, thw_cap = list(ev.thresholds_s), ev.thw_cap_s

    def make_risk_eval(cand):
        label = cand.meta.get("label") or default_label
        data, fp = risk_test_set(RISK_DATA, DISPARITY, ORB_CSV, r.split, r.max_frames)
        evaluator = risk_evaluator(data, label, thresholds, thw_cap, r.batch_size, r.split)
        return evaluator, f"{fp}:{label}"

    shipped = r.variant == SHIPPED
    risk_dir = SHIPPED_RISK_MODEL if shipped else risk_model_dir(r.variant)
    return promotion.GateJob(
        name=r.name,
        gate=r.gate(),
        model_dir=risk_dir,
        make_evaluator=make_risk_eval,
        record_path=run_record_file("select_risk" if shipped else f"train_risk@{r.variant}"),
        tags={"model_dir": _rel(risk_dir)},
        card=risk_card(r.variant),
    )


def build_jobs(cfg: DictConfig, rc: RegistryConfig) -> list[promotion.GateJob]:
    """One gate job per task: fusion network, learned registration, risk variant (gate sets load lazily)."""
    jobs = _fusion_jobs(cfg, rc)
    if "stereo_model" in cfg:
        jobs.append(_stereo_job(cfg, rc))
    jobs.append(_risk_job(cfg, rc))
    return jobs


def settings(rc: RegistryConfig, **switches) -> promotion.PromotionSettings:
    """Promotion settings of the project: aliases and log from the registry group."""
    return promotion.PromotionSettings(
        champion_alias=rc.aliases.champion,
        challenger_alias=rc.aliases.challenger,
        log_path=ROOT / rc.log,
        **switches,
    )


def promote(
    only: set[str] | None = None,
    dry_run: bool = False,
    force: bool = False,
    uri: str | None = None,
    before_apply: Callable[[list[Decision]], None] | None = None,
) -> list[Decision]:
    """Run the gate for every model of the project; returns the decisions (applied unless ``dry_run``).

    ``before_apply(decisions)``: called under the registry lock once every decision is taken.
    """
    setup_logging()
    cfg = params()
    rc = registry_config(cfg)
    jobs = promotion.select(build_jobs(cfg, rc), only)
    return promotion.promote(
        jobs, settings(rc, dry_run=dry_run, force=force, uri=uri), before_apply=before_apply
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m pipelines.promote", description=__doc__.split("\n\n")[0]
    )
    ap.add_argument(
        "--only",
        nargs="+",
        metavar="NAME",
        help="registered model names to gate (default: all configured)",
    )
    ap.add_argument("--dry-run", action="store_true", help="evaluate and decide, change nothing")
    ap.add_argument(
        "--force", action="store_true", help="re-evaluate challengers that were already decided"
    )
    ap.add_argument("--json", action="store_true", help="print the decisions as JSON")
    args = ap.parse_args(argv)
    # no "Downloading artifacts" bar per model checked (as the CLI: traffictwin.api.HTTP_ENV)
    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")
    try:
        decisions = promote(set(args.only) if args.only else None, args.dry_run, args.force)
    except (ValueError, RuntimeError) as exc:  # ConfigError, GateError, dataset/model errors
        print(f"promote: error: {mask_secrets(' '.join(str(exc).split()))}", file=sys.stderr)
        return 1
    except Exception as exc:  # noqa: BLE001 - the store itself (SQLAlchemy, OSError): one line
        first = (str(exc).strip().splitlines() or [""])[0][:300]
        print(f"promote: error: {type(exc).__name__}: {mask_secrets(first)}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps([d.to_dict() for d in decisions], indent=2, default=str))
    else:
        print(promotion.format_table(decisions, dry_run=args.dry_run))
    return 0


if __name__ == "__main__":
    sys.exit(main())
