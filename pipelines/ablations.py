"""Ablations: the comparisons the default run leaves out to stay within its time budget, run as
DVC experiments beside it, their results kept in ``reports/ablations/<name>.json``.

Usage (``make ablations`` runs every one)::

    python -m pipelines.ablations run [NAME ...]   # dvc exp run --temp per ablation, then collect
    python -m pipelines.ablations collect [NAME ...]  # results of finished experiments only
    python -m pipelines.ablations run seeds_1 seeds_2 --until evaluate_fusion  # up to one stage

Each ablation of ``ablations`` (params.yaml, conf/config.yaml) is a named list of Hydra overrides
(e.g. ``fusion_variants=per_config``: a network per pose-noise configuration). It
runs as ``dvc exp run --temp -n ablation-<name> -S <override> ...``: in a temporary copy of the
repository, so the workspace (and its committed default results) is untouched, with the data
stages restored from DVC's run cache; the experiment keeps its own metrics. ``collect`` copies
what the report shows from the experiment's commit — the ``test`` / ``diff`` / ``targets`` blocks
of ``reports/metrics/fusion.json`` (key ``fusion``) and ``risk.json`` (``risk``), with the
experiment's name, commit and overrides — into ``reports/ablations/<name>.json``; the ``report`` stage shows them beside the
default run's numbers (a DVC dependency of it). The seed replicates (``seeds_<k>``: the fusion
network's and the learned registration's training seed + k) are also compared with the default run
pair by pair: ``reports/ablations/fusion_seeds.json`` (:func:`collect_fusion_seeds`). Not a DVC
stage: it runs the pipeline itself.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from typing import Any

from traffictwin.config import ConfigError, get
from traffictwin.io.atomic import write_json_atomic

from ._common import params, setup_logging
from ._paths import REPORTS, ROOT

ABLATIONS = REPORTS / "ablations"
PREFIX = "ablation-"
# the seed replicates of the fusion claims: ablations named seeds_<k> (training seed + k), compared
# with the default run on evaluate_fusion's per-pair samples (the report reads the result)
SEED_PREFIX = "seeds_"
FUSION_SEEDS = ABLATIONS / "fusion_seeds.json"
FUSION_SAMPLES = "reports/fusion_eval_samples.csv"
# what the report shows of an ablation's run: the evaluation rows and differences the default
# run does not have (its own rows stay in reports/metrics/)
KEPT = {  # file in the experiment -> (key in reports/ablations/<name>.json, its blocks kept)
    "reports/metrics/fusion.json": ("fusion", ("test", "diff", "targets", "cross")),
    "reports/metrics/risk.json": ("risk", ("models", "diff", "seeds", "targets")),
}


def ablations(cfg: Any) -> dict[str, list[str]]:
    """``ablations`` of params.yaml: ``{name: [Hydra override, ...]}`` (checked)."""
    node = get(cfg, "ablations", dict)
    out: dict[str, list[str]] = {}
    for name, overrides in node.items():
        if not isinstance(overrides, list) or not all(isinstance(o, str) for o in overrides):
            raise ConfigError(
                f"params.yaml: 'ablations.{name}' must be a list of Hydra overrides (strings)"
            )
        out[str(name)] = list(overrides)
    return out


def _git(*args: str) -> str:
    return subprocess.run(
        ["git", *args], cwd=ROOT, check=True, capture_output=True, text=True
    ).stdout


def experiment_rev(name: str) -> str | None:
    """The commit of DVC experiment ``ablation-<name>`` (the newest of that name), or None."""
    out = _git(
        "for-each-ref", "--sort=-creatordate", "--format=%(objectname) %(refname)", "refs/exps"
    )
    for line in out.splitlines():
        rev, ref = line.split(" ", 1)
        if ref.rsplit("/", 1)[-1] == f"{PREFIX}{name}":
            return rev
    return None


def collect(name: str, overrides: list[str]) -> dict[str, Any]:
    """``reports/ablations/<name>.json`` from the experiment's commit; raises if it never ran."""
    rev = experiment_rev(name)
    if rev is None:
        raise RuntimeError(
            f"ablation {name!r}: no DVC experiment {PREFIX}{name} (run `python -m pipelines.ablations run {name}`)"
        )
    result: dict[str, Any] = {
        "name": name,
        "experiment": f"{PREFIX}{name}",
        "commit": rev,
        "baseline": _git("rev-parse", f"{rev}^").strip(),
        "overrides": overrides,
    }
    for path, (short, keys) in KEPT.items():
        try:
            data = json.loads(_git("show", f"{rev}:{path}"))
        except subprocess.CalledProcessError:
            continue
        result[short] = {k: data[k] for k in keys if k in data}
    write_json_atomic(ABLATIONS / f"{name}.json", result)
    return result


def _samples_text(rev: str) -> str:
    """evaluate_fusion's per-pair samples (CSV text) as committed at ``rev``."""
    try:
        return _git("show", f"{rev}:{FUSION_SAMPLES}")
    except subprocess.CalledProcessError as exc:
        raise RuntimeError(
            f"commit {rev[:8]} has no {FUSION_SAMPLES} (did evaluate_fusion run?)"
        ) from exc


def _frame(text: str) -> Any:
    """A samples CSV text as a pandas DataFrame."""
    import io

    import pandas as pd

    return pd.read_csv(io.StringIO(text))


def collect_fusion_seeds(names: list[str], cfg: Any) -> dict[str, Any]:
    """``reports/ablations/fusion_seeds.json``: the default run (the experiments' baseline commit)
    and the seed experiments ``names`` on the same test pairs, every fusion row and claim with its
    seeds × scenarios interval (:func:`traffictwin.fusion.evaluation.seeds.seed_replicates`)."""
    from traffictwin.fusion.config import pose_configurations
    from traffictwin.fusion.evaluation.keys import fusion_ci_config
    from traffictwin.fusion.evaluation.seeds import seed_replicates

    revs = {}
    for name in names:
        rev = experiment_rev(name)
        if rev is None:
            raise RuntimeError(
                f"seed replicate {name!r}: no DVC experiment {PREFIX}{name} "
                f"(run `python -m pipelines.ablations run {name} --until evaluate_fusion`)"
            )
        revs[name] = rev
    # each experiment's baseline commit holds the default run it is compared with: the same
    # default samples in every baseline (commits may differ in code the evaluation never reads)
    bases = {n: _git("rev-parse", f"{r}^").strip() for n, r in revs.items()}
    texts = {n: _samples_text(b) for n, b in bases.items()}
    if len(set(texts.values())) != 1:
        raise RuntimeError(
            f"seed replicates on different default runs: {FUSION_SAMPLES} differs between their "
            f"baseline commits ({', '.join(f'{n}: {b[:8]}' for n, b in bases.items())}); "
            "re-run them on one default run"
        )
    base = next(iter(bases.values()))
    runs = {
        "default": _frame(texts[names[0]]),
        **{n: _frame(_samples_text(r)) for n, r in revs.items()},
    }
    result = seed_replicates(runs, fusion_ci_config(cfg), list(pose_configurations(cfg)))
    result["commits"] = {"default": base, **revs}
    write_json_atomic(FUSION_SEEDS, result)
    return result


def run(name: str, overrides: list[str], until: str | None = None) -> None:
    """``dvc exp run --temp -n ablation-<name> -S ... [until]`` (the workspace stays as it is);
    ``until``: a stage of dvc.yaml — only it and what it depends on run (e.g. ``evaluate_fusion``
    for the fusion seed replicates, which leaves out the twin and the report)."""
    cmd = ["dvc", "exp", "run", "--temp", "-n", f"{PREFIX}{name}"]
    for o in overrides:
        cmd += ["-S", o]
    if until:
        cmd.append(until)
    subprocess.run(cmd, cwd=ROOT, check=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m pipelines.ablations", description=__doc__.split("\n\n")[0]
    )
    ap.add_argument("action", choices=("run", "collect"))
    ap.add_argument("names", nargs="*", help="ablations to run (default: every one of params.yaml)")
    ap.add_argument(
        "--until",
        metavar="STAGE",
        help="run only this stage of dvc.yaml and what it depends on (default: the whole pipeline)",
    )
    a = ap.parse_args(argv)
    log = setup_logging()
    try:
        todo = ablations(params())
        unknown = sorted(set(a.names) - set(todo))
        if unknown:
            raise ConfigError(
                f"unknown ablation(s) {unknown}; params.yaml 'ablations' has {sorted(todo)}"
            )
        for name in a.names or list(todo):
            if a.action == "run":
                log.info("ablation %s: dvc exp run --temp with %s", name, todo[name])
                run(name, todo[name], a.until)
            res = collect(name, todo[name])
            log.info(
                "ablation %s: %s from experiment %s",
                name,
                ABLATIONS / f"{name}.json",
                res["commit"][:8],
            )
        seeds = sorted(n for n in (a.names or list(todo)) if n.startswith(SEED_PREFIX))
        if seeds:
            res = collect_fusion_seeds(seeds, params())
            every = [e for m in res["findings"].values() for c in m.values() for e in c.values()]
            held = sum(e["holds"] for e in every)
            log.info(
                "seed replicates %s: %s (%d/%d fusion findings keep their verdict with seeds)",
                ", ".join(res["seeds"]),
                FUSION_SEEDS,
                held,
                len(every),
            )
    except (ValueError, RuntimeError, subprocess.CalledProcessError) as exc:
        print(f"ablations: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
