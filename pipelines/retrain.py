"""Scheduled retraining: new data batch -> `dvc repro` -> promotion gate -> summary.

    python -m pipelines.retrain [--seed N] [--targets STAGE ...] [--no-promote]

1. **Lock.** ``fcntl.flock`` on ``registry.retrain.lock`` (default ``.retrain.lock``): a second
   retraining while one runs exits with status 75 and a message naming the lock and its holder.
2. **New data.** Each key in ``registry.retrain.seed_keys`` (default the global ``seed``, from
   which every dataset seed derives) is bumped by ``seed_step`` (or set to ``--seed``) *in conf/*
   (the single source of truth: the key's line in ``conf/config.yaml`` or in the group file of
   ``conf/<group>/``), then params.yaml is recomposed from conf/ with the current profile. The
   new seed makes DVC regenerate the datasets: a new data version, recorded in dvc.lock (md5 of
   every ``data/`` output) and cached by DVC (``dvc push`` sends it to a remote). Because the
   change lives in conf/, the committed params.yaml stays equal to the composition of conf/.
3. **Pipeline.** ``dvc repro`` (optionally only ``--targets``).
4. **Gate.** :func:`pipelines.promote.promote` (register, compare with champion, move aliases).
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
import re
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

from pipelines._common import ROOT, params, setup_logging
from traffictwin.config import ConfigError, compose_config, dump_params, get
from traffictwin.io.atomic import write_bytes_atomic, write_json_atomic, write_text_atomic
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


# ------------------------------------------------------------------ conf/ edit (the new data seed)


def conf_file_for(key: str, conf: Path) -> tuple[Path, str]:
    """The conf/ file that defines ``key`` at its top level and the key's name in it.

    ``seed`` -> (conf/config.yaml, "seed"); ``risk_data.seed`` -> (conf/risk_data/<default>.yaml, "seed")
    where ``<default>`` is the group's option in conf/config.yaml's defaults list.
    """
    parts = key.split(".")
    if len(parts) == 1:
        return conf / "config.yaml", key
    if len(parts) != 2:
        raise ConfigError(
            f"registry.retrain.seed_keys: '{key}' must be a top-level key or <group>.<key>"
        )
    group, name = parts
    defaults = yaml.safe_load((conf / "config.yaml").read_text()).get("defaults", [])
    option = next((d[group] for d in defaults if isinstance(d, dict) and group in d), None)
    if option is None:
        raise ConfigError(
            f"conf/config.yaml: no defaults entry for group '{group}' (from seed key '{key}')"
        )
    return conf / group / f"{option}.yaml", name


def set_conf_value(path: Path, name: str, value: int) -> None:
    """Replace the top-level ``name: <int>`` line of ``path`` (comments kept); error if not exactly one."""
    text = path.read_text()
    pat = re.compile(rf"^({re.escape(name)}:[ \t]*)(-?\d+)([ \t]*(#.*)?)$", re.M)
    hits = pat.findall(text)
    if len(hits) != 1:
        raise ConfigError(
            f"{path}: expected exactly one top-level line '{name}: <integer>', found {len(hits)}"
        )
    write_text_atomic(path, pat.sub(lambda m: f"{m.group(1)}{value}{m.group(3)}", text))


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
    """Copies of conf/, params.yaml, dvc.lock and reports/ to restore after a failure."""

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


def model_names(cfg) -> list[str]:
    prefix = get(cfg, "registry.fusion.name_prefix", str)
    return [reg.fusion_name(c, prefix) for c in get(cfg, "registry.fusion.configs", list)] + [
        get(cfg, "registry.risk.name", str)
    ]


def write_summary(base: Path, s: dict[str, Any]) -> None:
    write_json_atomic(base.with_name(base.name + ".json"), s)
    lines = [
        f"# Retraining {s['status']}: {s['started']}",
        "",
        f"- duration: {s.get('duration_s', 0):.0f} s; profile `{s.get('profile')}`; git `{str(s.get('git_commit'))[:10]}`",
    ]
    for k, (a, b) in (s.get("seeds") or {}).items():
        lines.append(f"- data seed `{k}`: {a} → {b}")
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
            f = lambda v: "–" if v is None else f"{v:.5g}"
            lines.append(
                f"| {d['name']} | v{d['challenger_version']} | {('v' + d['champion_version']) if d['champion_version'] else '–'} "
                f"| {d['metric']} | {f(d['challenger_value'])} | {f(d['champion_value'])} | {d['action']} |"
            )
        lines.append("")
        lines.append(f"Champions after: {s.get('champions_after')}")
    write_text_atomic(base.with_name(base.name + ".md"), "\n".join(lines) + "\n")


def retrain(
    root: Path,
    seed: int | None = None,
    targets: list[str] | None = None,
    promote_models: bool = True,
) -> dict:
    """The whole flow (see module docstring) under the lock; returns the summary dict."""
    from pipelines import promote as promote_mod
    from traffictwin.mlops.tracking import git_commit

    log = setup_logging()
    cfg = params(root / "params.yaml")
    summary_base = root / get(cfg, "registry.retrain.summary", str)
    keys = get(cfg, "registry.retrain.seed_keys", list)
    step_size = get(cfg, "registry.retrain.seed_step", int, min=1)
    profile = get(cfg, "profile.name", str)
    champion_alias = get(cfg, "registry.aliases.champion", str)
    names = model_names(cfg)
    t0 = time.time()
    s: dict[str, Any] = {
        "status": "running",
        "started": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "profile": profile,
        "git_commit": git_commit(root),
        "targets": targets or [],
        "data_before": data_versions(root),
    }
    cl = reg.client()
    s["champions_before"] = champions(cl, names, champion_alias)
    step = "snapshot"
    with tempfile.TemporaryDirectory(prefix="retrain-snap-") as tmp:
        snap = Snapshot(root, Path(tmp))
        applied = False
        try:
            step = "new_data"
            seeds = {}
            for k in keys:
                old = get(cfg, k, int)
                new = seed if seed is not None else old + step_size
                path, name = conf_file_for(k, root / "conf")
                set_conf_value(path, name, new)
                seeds[k] = (old, new)
            composed = compose_config(root / "conf", [f"profile={profile}"])
            for k, (_, new) in seeds.items():
                got = get(composed, k, int)
                if got != new:
                    raise ConfigError(
                        f"conf/: '{k}' composes to {got}, not the new seed {new} (overridden by profile '{profile}'?)"
                    )
            dump_params(composed, root / "params.yaml")
            s["seeds"] = seeds
            log.info("retrain: new data seeds %s", seeds)
            _inject("after_params")

            step = "dvc_repro"
            t = time.time()
            proc = subprocess.run(["dvc", "repro", *(targets or [])], cwd=root)
            s["repro_s"] = round(time.time() - t, 1)
            if proc.returncode != 0:
                raise RetrainError(f"`dvc repro` failed with status {proc.returncode}")
            s["data_after"] = data_versions(root)
            _inject("after_repro")

            step = "promote"
            decisions = []
            if promote_models:
                decisions = promote_mod.promote(
                    root, dry_run=True
                )  # decide all first: nothing moves on error
                _inject("before_apply")
                step = "apply"
                applied = True
                log_path = root / get(cfg, "registry.log", str)
                for d in decisions:
                    reg.apply(
                        cl,
                        d,
                        log_path=log_path,
                        champion_alias=champion_alias,
                        challenger_alias=get(cfg, "registry.aliases.challenger", str),
                    )
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
            s["champions_after"] = champions(cl, names, champion_alias)
            s["duration_s"] = round(time.time() - t0, 1)
            s["finished"] = time.strftime("%Y-%m-%dT%H:%M:%S")
            write_summary(summary_base, s)
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
    ap.add_argument("--no-promote", action="store_true", help="skip the promotion gate")
    args = ap.parse_args(argv)
    try:
        cfg = params(ROOT / "params.yaml")
        lock = ROOT / get(cfg, "registry.retrain.lock", str)
    except ConfigError as exc:
        print(f"retrain: error: {exc}", file=sys.stderr)
        return 1
    try:
        with retrain_lock(lock):
            s = retrain(ROOT, args.seed, args.targets, not args.no_promote)
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
