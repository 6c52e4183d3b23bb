"""Promotion gate: register the freshly trained models, compare each with its champion, move aliases.

Not a DVC stage (it changes the MLflow registry, which DVC cannot cache); run after `dvc repro`:

    python -m pipelines.promote [--only traffictwin-fusion-A traffictwin-risk] [--dry-run] [--force]

For every model named in ``registry`` (params.yaml): the run id in ``model_meta.json`` is
registered (once) as a version of ``traffictwin-fusion-<cfg>`` / ``traffictwin-risk``, aliased
``challenger``, and it and the current ``champion`` are both evaluated on the same fixed test set
(test split of the current data) with the evaluation stages' metric code. All decisions are taken
first, then applied, so an evaluation failure moves no alias. Exit status 0 on success (whatever
the decisions), 1 on an error (message names the file/model/key).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from pipelines._common import ROOT, params, setup_logging
from traffictwin.config import ConfigError, get
from traffictwin.mlops import registry as reg


def build_jobs(cfg, root: Path, only: set[str] | None = None) -> list[dict]:
    """One job per registered model: name, gate, candidate, evaluator factory (lazy), fingerprint."""
    jobs = []
    f = "registry.fusion"
    prefix = get(cfg, f"{f}.name_prefix", str)
    configs = get(cfg, f"{f}.configs", list)
    known = set(get(cfg, "configurations", dict))
    for c in configs:
        if c not in known:
            raise ConfigError(
                f"params.yaml: '{f}.configs' lists '{c}', not one of configurations {sorted(known)}"
            )
        name = reg.fusion_name(c, prefix)
        if only and name not in only:
            continue
        gate = reg.Gate(
            get(cfg, f"{f}.metric", str),
            get(cfg, f"{f}.mode", str, choices=("min", "max")),
            get(cfg, f"{f}.margin", float, min=0.0),
        )

        def make_eval(c=c):
            x, y, fp = reg.fusion_test_set(
                root / get(cfg, f"{f}.data_dir", str) / c,
                get(cfg, f"{f}.split", str),
                get(cfg, f"{f}.max_pairs", (int, type(None))),
            )
            return reg.fusion_evaluator(x, y, get(cfg, f"{f}.batch_size", int, min=1)), fp

        jobs.append(
            {
                "name": name,
                "gate": gate,
                "model_dir": root / get(cfg, f"{f}.model_dir", str) / c,
                "make_eval": make_eval,
            }
        )
    r = "registry.risk"
    name = get(cfg, f"{r}.name", str)
    if not only or name in only:
        gate = reg.Gate(
            get(cfg, f"{r}.metric", str),
            get(cfg, f"{r}.mode", str, choices=("min", "max")),
            get(cfg, f"{r}.margin", float, min=0.0),
        )
        model_dir = root / get(cfg, f"{r}.model_dir", str) / get(cfg, f"{r}.variant", str)

        def make_eval_risk(model_dir=model_dir):
            cand = reg.read_candidate(name, model_dir)
            label = cand.meta.get("label") or get(cfg, "risk_model.label", str)
            orb = get(cfg, f"{r}.orb_csv", (str, type(None)))
            data, fp = reg.risk_test_set(
                root / get(cfg, f"{r}.risk_dir", str),
                root / get(cfg, f"{r}.disparity_dir", str),
                root / orb if orb else None,
                get(cfg, f"{r}.split", str),
                get(cfg, f"{r}.max_frames", (int, type(None))),
            )
            thr = get(cfg, "evaluation.risk.thresholds_s", list, default=[1.5, 1.0])
            cap = get(cfg, "evaluation.risk.thw_cap_s", float, default=10.0)
            return reg.risk_evaluator(
                data, label, thr, cap, get(cfg, f"{r}.batch_size", int, min=1)
            ), f"{fp}:{label}"

        jobs.append(
            {"name": name, "gate": gate, "model_dir": model_dir, "make_eval": make_eval_risk}
        )
    if only:
        unknown = only - {j["name"] for j in jobs}
        if unknown:
            raise ConfigError(
                f"--only: unknown model(s) {sorted(unknown)}; known: "
                f"{[reg.fusion_name(c, prefix) for c in configs] + [name]}"
            )
    return jobs


def promote(
    root: Path = ROOT,
    only: set[str] | None = None,
    dry_run: bool = False,
    force: bool = False,
    uri: str | None = None,
) -> list[reg.Decision]:
    """Run the gate for every configured model; returns the decisions (applied unless ``dry_run``)."""
    log = setup_logging()
    cfg = params(root / "params.yaml")
    champion = get(cfg, "registry.aliases.champion", str)
    challenger = get(cfg, "registry.aliases.challenger", str)
    log_path = root / get(cfg, "registry.log", str)
    jobs = build_jobs(cfg, root, only)
    cl = reg.client(uri)
    # candidates are read before anything else, so a missing model stops the gate before any change
    for j in jobs:
        j["cand"] = reg.read_candidate(j["name"], j["model_dir"])
    decisions = []
    for j in jobs:
        t0 = time.perf_counter()
        mv = reg.ensure_version(
            cl,
            j["name"],
            j["cand"].run_id,
            j["cand"].model_uri,
            tags={
                "model_dir": str(j["model_dir"].relative_to(root))
                if j["model_dir"].is_relative_to(root)
                else str(j["model_dir"])
            },
        )
        evaluate, fp = j["make_eval"]()
        d = reg.decide(
            cl,
            j["name"],
            mv,
            evaluate,
            j["gate"],
            test_fingerprint=fp,
            champion_alias=champion,
            force=force,
        )
        log.info(
            "%s v%s: %s — %s (%.1f s)",
            d.name,
            d.challenger_version,
            d.action,
            d.reason,
            time.perf_counter() - t0,
        )
        decisions.append(d)
    if not dry_run:
        for d in decisions:
            reg.apply(
                cl, d, log_path=log_path, champion_alias=champion, challenger_alias=challenger
            )
    return decisions


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
    try:
        decisions = promote(ROOT, set(args.only) if args.only else None, args.dry_run, args.force)
    except (reg.RegistryError, ConfigError) as exc:
        print(f"promote: error: {exc}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps([d.to_dict() for d in decisions], indent=2, default=str))
    else:
        for d in decisions:
            fig = (
                ""
                if d.challenger_value is None
                else f"  challenger {d.challenger_value:.6g}"
                + (
                    ""
                    if d.champion_value is None
                    else f"  champion v{d.champion_version} {d.champion_value:.6g}"
                )
            )
            print(f"{d.name:28s} v{d.challenger_version:>3s}  {d.action:9s}{fig}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
