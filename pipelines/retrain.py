"""Scheduled retraining: new data batch -> `dvc repro` -> promotion gate -> summary.

    python -m pipelines.retrain [--seed N] [--targets STAGE ...] [--only NAME ...] [--no-promote]

1. **Lock.** ``fcntl.flock`` on ``registry.retrain.lock`` (default ``.retrain.lock``): a second
   retraining while one runs exits with status 75 and a message naming the lock and its holder.
2. **New data.** Each key in ``registry.retrain.seed_keys`` (default the global ``seed``, from
   which every dataset seed derives) is bumped by ``seed_step`` (or set to ``--seed``) as a Hydra
   override: params.yaml is recomposed from conf/ with ``profile=<current> <key>=<new seed> …``
   (conf/ itself is never edited; the overrides are recorded in the summary). The new seed makes
   DVC regenerate the datasets: a new data version, recorded in dvc.lock (md5 of every ``data/``
   output) and cached by DVC (``dvc push`` sends it to a remote).
3. **Pipeline.** ``dvc repro`` (optionally only ``--targets``).
4. **Gate.** :func:`pipelines.promote.promote` (register, compare with champion; every decision
   is taken before any alias moves), optionally only for the models named by ``--only``.
5. **Summary.** ``<registry.retrain.summary>.json`` and ``.md``.

Failure anywhere before the gate applies its decisions restores conf/, params.yaml, dvc.lock
and reports/ from a snapshot and runs ``dvc checkout --force``, so the data and models are the
previous version again; the gate decides everything before it moves any alias, so ``champion``
is untouched. Then a ``failed`` summary is written and the exit status is 1.

Test hook: ``TRAFFICTWIN_RETRAIN_FAIL_AT=after_params|after_repro|before_apply`` raises there.
"""

from __future__ import annotations

import argparse
import fcntl
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import yaml

from pipelines import promote as promote_mod
from pipelines._common import params, setup_logging
from pipelines._paths import CONF, PARAMS, ROOT
from pipelines._provenance import git_commit
from traffictwin.config import ConfigError, compose_config, dump_params, get
from traffictwin.io.atomic import write_bytes_atomic, write_json_atomic, write_text_atomic
from traffictwin.mlops import promotion
from traffictwin.mlops import registry as reg

EXIT_LOCKED = 75  # EX_TEMPFAIL: try again later
FAIL_ENV = "TRAFFICTWIN_RETRAIN_FAIL_AT"


class RetrainError(RuntimeError):
    """A retraining step failed (message names the step)."""


class LockBusy(RuntimeError):
    """Another retraining holds the lock."""


@contextmanager
def retrain_lock(path: Path) -> Iterator[None]:
    """Hold an exclusive ``fcntl.flock`` on ``path`` (created if needed) for the block."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fh = open(path, "a+")
    try:
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            fh.seek(0)
            holder = fh.read().strip() or "unknown holder"
            raise LockBusy(
                f"another retraining run holds the lock {path} ({holder}); not starting a second one"
            ) from None
        fh.seek(0)
        fh.truncate()
        fh.write(f"pid {os.getpid()} since {time.strftime('%Y-%m-%dT%H:%M:%S')}\n")
        fh.flush()
        yield
    finally:
        fh.close()  # closing the descriptor releases the lock


def _inject(step: str) -> None:
    if os.environ.get(FAIL_ENV) == step:
        raise RetrainError(f"injected failure at '{step}' ({FAIL_ENV})")


# ------------------------------------------------------------------ the new data seed


def seed_overrides(cfg, keys: list[str], step: int, seed: int | None) -> dict[str, tuple[int, int]]:
    """``{key: (old, new)}`` for every seed key: new = ``seed`` if given, else old + ``step``."""
    out = {}
    for k in keys:
        old = get(cfg, k, int)
        out[k] = (old, seed if seed is not None else old + step)
    return out


def compose_with_seeds(
    conf: Path, profile: str, seeds: dict[str, tuple[int, int]]
) -> tuple[dict[str, Any], list[str]]:
    """params composed from ``conf`` with ``profile=<profile>`` and ``<key>=<new>`` overrides, and the
    overrides; error if a seed does not compose to its new value (e.g. fixed by the profile)."""
    overrides = [f"profile={profile}", *(f"{k}={new}" for k, (_, new) in seeds.items())]
    composed = compose_config(conf, overrides)
    for k, (_, new) in seeds.items():
        got = get(composed, k, int)
        if got != new:
            raise ConfigError(
                f"conf/: '{k}' composes to {got}, not the new seed {new} (overridden by profile '{profile}'?)"
            )
    return composed, overrides


def data_versions(root: Path) -> dict[str, str]:
    """md5 of every ``data/`` output recorded in dvc.lock (the data version)."""
    lock = root / "dvc.lock"
    if not lock.exists():
        return {}
    doc = yaml.safe_load(lock.read_text()) or {}
    out = {}
    for stage in (doc.get("stages") or {}).values():
        for o in stage.get("outs", []) or []:
            if str(o.get("path", "")).startswith("data/"):
                out[o["path"]] = o.get("md5", "")
    return dict(sorted(out.items()))


# ------------------------------------------------------------------ snapshot / restore


class Snapshot:
    """Copies of conf/, params.yaml, dvc.lock and reports/ to restore after a failure.

    (The flow itself never edits conf/; the copy makes a restore return the whole input tree.)
    """

    def __init__(self, root: Path, tmp: Path) -> None:
        self.root, self.tmp = root, tmp
        self.files = {}
        for rel in ("params.yaml", "dvc.lock"):
            p = root / rel
            self.files[rel] = p.read_bytes() if p.exists() else None
        shutil.copytree(root / "conf", tmp / "conf")
        self.had_reports = (root / "reports").exists()
        if self.had_reports:
            shutil.copytree(root / "reports", tmp / "reports", symlinks=True)

    def restore(self, log) -> list[str]:
        problems = []
        lock_path = self.root / "dvc.lock"
        lock_now = (
            (yaml.safe_load(lock_path.read_text()) or {}).get("stages", {})
            if lock_path.exists()
            else {}
        )
        for rel, data in self.files.items():
            p = self.root / rel
            if data is None:
                p.unlink(missing_ok=True)
            else:
                write_bytes_atomic(p, data)
        for sub in ("conf", "reports"):
            if sub == "reports" and not self.had_reports:
                shutil.rmtree(self.root / sub, ignore_errors=True)
                continue
            shutil.rmtree(self.root / sub, ignore_errors=True)
            shutil.copytree(self.tmp / sub, self.root / sub, symlinks=True)
        if self.files["dvc.lock"] is not None:
            # only the stages this run changed (their lock entry differs from the snapshot's), that the
            # previous dvc.lock knows (others never ran: nothing to restore) and that the current dvc.yaml
            # still defines (a lock may keep foreach items of another profile, whose outputs are not cached here)
            lock_then = (yaml.safe_load(self.files["dvc.lock"]) or {}).get("stages", {}) or {}
            locked = {n for n in lock_then if lock_now.get(n) != lock_then[n]}
            listed = subprocess.run(
                ["dvc", "stage", "list", "--name-only"],
                cwd=self.root,
                capture_output=True,
                text=True,
            )
            if listed.returncode != 0:
                problems.append(
                    f"dvc stage list failed ({listed.returncode}): {listed.stderr.strip()[-800:]}"
                )
                log.error("restore: %s", problems[-1])
                return problems
            stages = sorted(locked & set(listed.stdout.split()))
            if not stages:
                return problems
            proc = subprocess.run(
                ["dvc", "checkout", "--force", *stages],
                cwd=self.root,
                capture_output=True,
                text=True,
            )
            if proc.returncode != 0:
                problems.append(
                    f"dvc checkout --force failed ({proc.returncode}): {proc.stderr.strip()[-800:]}"
                )
                log.error("restore: %s", problems[-1])
        return problems


# ------------------------------------------------------------------ main flow


def champions(cl, names: list[str], alias: str) -> dict[str, str | None]:
    out = {}
    for n in names:
        mv = reg.get_alias(cl, n, alias)
        out[n] = None if mv is None else str(mv.version)
    return out


def _fig(v: float | None) -> str:
    return "–" if v is None else f"{v:.5g}"


def write_summary(base: Path, s: dict[str, Any]) -> None:
    write_json_atomic(base.with_name(base.name + ".json"), s)
    lines = [
        f"# Retraining {s['status']}: {s['started']}",
        "",
        f"- duration: {s.get('duration_s', 0):.0f} s; profile `{s.get('profile')}`; git `{str(s.get('git_commit'))[:10]}`",
    ]
    for k, (a, b) in (s.get("seeds") or {}).items():
        lines.append(f"- data seed `{k}`: {a} → {b}")
    if s.get("overrides"):
        lines.append(f"- params.yaml = conf/ composed with `{' '.join(s['overrides'])}`")
    if s.get("error"):
        lines += [
            f"- **error** in step `{s.get('failed_step')}`: {s['error']}",
            f"- restored: {s.get('restored')} {s.get('restore_problems') or ''}; champions: {s.get('champions_after')}",
        ]
    changed = [
        p
        for p, h in (s.get("data_after") or {}).items()
        if (s.get("data_before") or {}).get(p) != h
    ]
    if s["status"] == "succeeded":
        lines.append(
            f"- new data version: {len(changed)} of {len(s.get('data_after') or {})} data outputs changed "
            f"({', '.join(changed) or 'none'})"
        )
    if s.get("decisions"):
        lines += [
            "",
            "| model | challenger | champion before | metric | challenger | champion | decision |",
            "| --- | --- | --- | --- | --- | --- | --- |",
        ]
        for d in s["decisions"]:
            lines.append(
                f"| {d['name']} | v{d['challenger_version']} | {('v' + d['champion_version']) if d['champion_version'] else '–'} "
                f"| {d['metric']} | {_fig(d['challenger_value'])} | {_fig(d['champion_value'])} | {d['action']} |"
            )
        lines.append("")
        lines.append(f"Champions after: {s.get('champions_after')}")
    write_text_atomic(base.with_name(base.name + ".md"), "\n".join(lines) + "\n")


def retrain(
    seed: int | None = None,
    targets: list[str] | None = None,
    promote_models: bool = True,
    only: set[str] | None = None,
) -> dict:
    """The whole flow (see module docstring) in this checkout, under the lock; returns the summary dict."""
    log = setup_logging()
    cfg = params()
    rc = promote_mod.registry_config(cfg)
    profile = get(cfg, "profile.name", str)
    names = [n for n in promote_mod.model_names(cfg, rc) if not only or n in only]
    t0 = time.time()
    s: dict[str, Any] = {
        "status": "running",
        "started": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "profile": profile,
        "git_commit": git_commit(ROOT),
        "targets": targets or [],
        "data_before": data_versions(ROOT),
    }
    cl = reg.client()
    s["champions_before"] = champions(cl, names, rc.aliases.champion)
    step = "snapshot"
    with tempfile.TemporaryDirectory(prefix="retrain-snap-") as tmp:
        snap = Snapshot(ROOT, Path(tmp))
        applied = False
        try:
            step = "new_data"
            seeds = seed_overrides(cfg, rc.retrain.seed_keys, rc.retrain.seed_step, seed)
            composed, overrides = compose_with_seeds(CONF, profile, seeds)
            dump_params(composed, PARAMS)
            s["seeds"] = seeds
            s["overrides"] = overrides
            log.info("retrain: new data seeds %s", seeds)
            _inject("after_params")

            step = "dvc_repro"
            t = time.time()
            proc = subprocess.run(["dvc", "repro", *(targets or [])], cwd=ROOT)
            s["repro_s"] = round(time.time() - t, 1)
            if proc.returncode != 0:
                raise RetrainError(f"`dvc repro` failed with status {proc.returncode}")
            s["data_after"] = data_versions(ROOT)
            _inject("after_repro")

            step = "promote"
            decisions = []
            if promote_models:
                # decide all first (under the registry lock, held until the aliases moved):
                # nothing moves on error
                def before_apply(_decisions) -> None:
                    nonlocal step, applied
                    _inject("before_apply")
                    step = "apply"
                    applied = True

                decisions = promote_mod.promote(only, before_apply=before_apply)
            s["decisions"] = [d.to_dict() for d in decisions]
            s["status"] = "succeeded"
        except (Exception, KeyboardInterrupt) as exc:  # noqa: BLE001 - restore on anything
            s["status"] = "failed"
            s["failed_step"] = step
            s["error"] = f"{type(exc).__name__}: {exc}"
            log.error("retrain failed in step %s: %s", step, s["error"])
            problems = (
                snap.restore(log)
                if not applied
                else ["the gate had started moving aliases: nothing restored"]
            )
            s["restored"] = not problems
            if problems:
                s["restore_problems"] = problems
        finally:
            s["champions_after"] = champions(cl, names, rc.aliases.champion)
            s["duration_s"] = round(time.time() - t0, 1)
            s["finished"] = time.strftime("%Y-%m-%dT%H:%M:%S")
            write_summary(ROOT / rc.retrain.summary, s)
    return s


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m pipelines.retrain", description=__doc__.split("\n\n")[0]
    )
    ap.add_argument(
        "--seed",
        type=int,
        default=None,
        help="set the data seed key(s) to this value (default: old + seed_step)",
    )
    ap.add_argument(
        "--targets",
        nargs="+",
        default=None,
        help="only `dvc repro` these stages (default: the whole DAG)",
    )
    ap.add_argument(
        "--only",
        nargs="+",
        metavar="NAME",
        default=None,
        help="gate only these registered models (default: every configured model)",
    )
    ap.add_argument("--no-promote", action="store_true", help="skip the promotion gate")
    args = ap.parse_args(argv)
    try:
        cfg = params()
        rc = promote_mod.registry_config(cfg)
        if args.only:
            promotion.select(promote_mod.build_jobs(cfg, rc), args.only)  # unknown name: error now
    except (ConfigError, reg.RegistryError) as exc:
        print(f"retrain: error: {exc}", file=sys.stderr)
        return 1
    try:
        with retrain_lock(ROOT / rc.retrain.lock):
            only = set(args.only) if args.only else None
            s = retrain(args.seed, args.targets, not args.no_promote, only)
    except LockBusy as exc:
        print(f"retrain: {exc}", file=sys.stderr)
        return EXIT_LOCKED
    print(
        json.dumps(
            {
                k: s.get(k)
                for k in (
                    "status",
                    "seeds",
                    "champions_before",
                    "champions_after",
                    "error",
                    "failed_step",
                    "duration_s",
                )
            },
            default=str,
        )
    )
    if s["status"] != "succeeded":
        print(
            f"retrain: error in step '{s.get('failed_step')}': {s.get('error')} (previous data and champions kept)",
            file=sys.stderr,
        )
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
