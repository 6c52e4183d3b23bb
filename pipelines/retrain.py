"""Scheduled retraining: new data batch -> `dvc repro` -> promotion gate -> summary.

    python -m pipelines.retrain [--seed N] [--targets STAGE ...] [--only NAME ...] [--no-promote]

1. **Lock** ``registry.retrain.lock`` (``fcntl.flock``; its ``dvc repro`` inherits it): a second
   run while either lives exits 75 at once, naming the holder, and writes no summary.
2. **Recover** from the journal a killed run left (``recovered``); unverified: exit 1, kept.
3. **Journal** (``<lock without .lock>.journal/``) before anything changes: copies of conf/,
   params.yaml, dvc.lock, reports/, the ``dvc status``, the seeds, the step.
4. **New data**: each ``registry.retrain.seed_keys`` bumped by ``seed_step`` (or ``--seed``) as a
   Hydra override; params.yaml recomposed from conf/ (never edited); ``dvc repro [--targets]``.
   ``--targets`` whose stages and upstream stages consume no seed key (e.g. ``environment``) are
   refused before anything is written (exit 1, one line): a new seed would retrain nothing.
5. **Gate**: :func:`pipelines.promote.promote` (``--only``; ``--no-promote`` skips it).
6. **Summary** ``<registry.retrain.summary>.{json,md}`` on every exit path of a run holding the
   lock: ``succeeded``, ``failed`` or ``interrupted``.

**Restore**: a failure or SIGTERM/SIGINT/SIGHUP before the gate moves an alias puts the journal
back, runs ``dvc checkout --force`` and verifies it (:mod:`pipelines._checkout`); ``restored``
says whether it matched (else the journal stays for the next run). Exit 1, or 128 + the signal.
Once the gate moves aliases, signals are only noted: aliases and outputs belong together.

**Supervision is the scheduler's** (``pipelines/schedules/``, ``.github/workflows/retrain.yml``):
the time limit, and SIGTERM then SIGKILL to the whole tree (``dvc repro`` and its stages stay in
this process's group and cgroup). Signalled alone, this process waits for its ``dvc repro`` to
exit before it restores. Logs go outside reports/ (a restore replaces it).

Test hook: ``TRAFFICTWIN_RETRAIN_FAIL_AT=after_params|after_repro|before_apply`` raises there.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pipelines import promote as promote_mod
from pipelines._checkout import RESTORED, data_versions, dvc_state, journal_for, recover, undo
from pipelines._common import params, setup_logging
from pipelines._paths import CONF, PARAMS, ROOT
from pipelines._provenance import git_commit
from traffictwin.config import ConfigError, dump_params, get
from traffictwin.io.atomic import write_json_atomic, write_text_atomic
from traffictwin.mlops import promotion
from traffictwin.mlops import registry as reg
from traffictwin.mlops.config import compose_with_seeds, seed_overrides
from traffictwin.mlops.journal import Journal, LockBusy, exclusive_lock
from traffictwin.mlops.retrain_summary import summary_markdown
from traffictwin.mlops.uris import mask_secrets

EXIT_LOCKED = 75  # EX_TEMPFAIL: try again later
FAIL_ENV = "TRAFFICTWIN_RETRAIN_FAIL_AT"
SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)
PRINTED = ("status", "seeds", "champions_before", "champions_after", "error", "failed_step")
PRINTED += ("restored", "signal", "duration_s")


class RetrainError(RuntimeError):
    """A retraining step failed (message names the step)."""


class Interrupted(BaseException):
    """A termination signal arrived (raised in the main thread by :class:`Signals`)."""

    def __init__(self, signum: int) -> None:
        super().__init__(f"received {signal.Signals(signum).name}")
        self.signum = signum


def _inject(step: str) -> None:
    if os.environ.get(FAIL_ENV) == step:
        raise RetrainError(f"injected failure at '{step}' ({FAIL_ENV})")


class Signals:
    """SIGTERM/SIGINT/SIGHUP raise :class:`Interrupted` once; after :meth:`hold` only noted."""

    def __init__(self) -> None:
        self.received: int | None = None
        self.held = False

    def __enter__(self) -> Signals:
        self._old = {s: signal.signal(s, self._handle) for s in SIGNALS}
        return self

    def __exit__(self, *exc: object) -> None:
        for s, h in self._old.items():
            signal.signal(s, h)

    def _handle(self, signum: int, frame: object) -> None:
        first, self.received = self.received is None, self.received or signum
        if first and not self.held:
            raise Interrupted(signum)

    def hold(self) -> None:
        self.held = True


def champions(cl, names: list[str], alias: str) -> dict[str, str | None]:
    return {
        n: None if (mv := reg.get_alias(cl, n, alias)) is None else str(mv.version) for n in names
    }


@dataclass
class _Run:
    """One retraining's state, shared by its steps."""

    s: dict[str, Any]
    journal: Journal
    rc: Any
    log: Any
    step: str = "recover"
    applied: bool = False
    cl: Any = None
    names: list[str] = field(default_factory=list)
    child: subprocess.Popen | None = None


def _prepare(run: _Run, seed: int | None, promote_models: bool, only: set[str] | None) -> None:
    """Recover a killed run, record the state before, put the new seeds into params.yaml."""
    rec = recover(ROOT, run.journal, run.log)
    if rec is not None:
        run.s["recovered"] = rec
        if rec.get("problems"):
            why, kept = "; ".join(rec["problems"]), run.journal.path
            raise RetrainError(
                f"could not restore what the killed retraining pid {rec['pid']} left: {why}; fix it, then rerun (the journal {kept} is kept)"
            )
    run.step = "prepare"
    cfg = params()  # as the recovery left it
    run.rc = rc = promote_mod.registry_config(cfg)
    profile = get(cfg, "profile.name", str)
    run.s.update(profile=profile, git_commit=git_commit(ROOT), data_before=data_versions(ROOT))
    if promote_models:
        run.names = [n for n in promote_mod.model_names(cfg, rc) if not only or n in only]
        run.cl = reg.client()
        run.s["champions_before"] = champions(run.cl, run.names, rc.aliases.champion)
    run.step = "new_data"
    seeds = seed_overrides(cfg, rc.retrain.seed_keys, rc.retrain.seed_step, seed)
    composed, overrides = compose_with_seeds(CONF, profile, seeds)
    run.s.update(seeds=seeds, overrides=overrides)
    run.step = "journal"
    state = {"pid": os.getpid(), "started": run.s["started"], "seeds": seeds, "step": "new_data"}
    run.journal.begin(ROOT, RESTORED, {**state, "dvc_before": dvc_state(ROOT)})
    run.step = "new_data"
    dump_params(composed, PARAMS)
    run.log.info("retrain: new data seeds %s", seeds)
    _inject("after_params")


def _repro(run: _Run, targets: list[str] | None, lock_fd: int | None) -> None:
    run.step = "dvc_repro"
    run.journal.update(step=run.step)
    t = time.time()
    fds = () if lock_fd is None else (lock_fd,)  # the lock stays held while `dvc repro` lives
    run.child = subprocess.Popen(["dvc", "repro", *(targets or [])], cwd=ROOT, pass_fds=fds)
    code = run.child.wait()
    run.child = None
    run.s["repro_s"] = round(time.time() - t, 1)
    if code != 0:
        raise RetrainError(f"`dvc repro` failed with status {code}")
    run.s["data_after"] = data_versions(ROOT)
    _inject("after_repro")


def _gate(run: _Run, promote_models: bool, only: set[str] | None, signals: Signals) -> None:
    run.step = "promote"
    if run.cl is not None:  # versions above these that an interrupted gate registers are orphans
        run.s["registry_before"] = reg.latest_versions(run.cl, run.names)
    run.journal.update(step=run.step, registry_before=run.s.get("registry_before"))
    run.s["decisions"] = []
    if not promote_models:
        return

    def before_apply(_decisions) -> None:  # every decision taken, under the registry lock
        _inject("before_apply")
        signals.hold()  # aliases and new outputs belong together: finish first
        run.step = "apply"
        run.journal.update(step=run.step)
        run.applied = True

    decisions = promote_mod.promote(only, before_apply=before_apply)
    run.s["decisions"] = [d.to_dict() for d in decisions]


def _undo(run: _Run, exc: BaseException) -> None:
    """Record the failure and restore the checkout from the journal where this run changed it."""
    s, journal = run.s, run.journal
    s["status"] = "interrupted" if isinstance(exc, Interrupted) else "failed"
    s["failed_step"], s["error"] = run.step, f"{type(exc).__name__}: {exc}"
    run.log.error("retrain %s in step %s: %s", s["status"], run.step, s["error"])
    if run.child is not None:  # never restore under a running `dvc repro`
        run.log.warning("retrain: waiting for `dvc repro` (pid %d) to exit", run.child.pid)
        run.child.wait()
    if run.step == "recover":  # this run had changed nothing yet
        problems = (s.get("recovered") or {}).get("problems") or []
        if not problems and journal.path.exists():
            problems = [s["error"]]
    elif run.applied:
        problems = ["the gate had started moving aliases: nothing restored"]
        journal.discard()
    elif journal.path.exists():
        problems, s["orphans"] = undo(ROOT, journal, run.log, run.cl)
    else:
        problems = []  # nothing had been changed yet
    s["restored"] = not problems
    if problems:
        s["restore_problems"] = problems


def seedless_targets(root, targets: list[str], seed_keys: list[str]) -> list[str]:
    """The ``targets`` whose stage and upstream stages (DVC's own graph) consume none of
    ``seed_keys``: a new data seed would not change what ``dvc repro`` of them makes. A key is
    consumed by a stage whose ``params`` list it, a group above it or a key below it."""
    from dvc.dependency.param import ParamsDependency
    from dvc.repo import Repo

    def consumes(param: str) -> bool:
        return any(
            param == k or k.startswith(f"{param}.") or param.startswith(f"{k}.") for k in seed_keys
        )

    out = []
    with Repo(str(root)) as repo:
        for t in targets:
            ref = t if ":" in t else f"{Path(root) / 'dvc.yaml'}:{t}"  # not the cwd's
            stages = repo.stage.collect(ref, with_deps=True)
            params = {
                p
                for st in stages
                for d in st.deps
                if isinstance(d, ParamsDependency)
                for p in d.params
            }
            if not any(consumes(p) for p in params):
                out.append(t)
    return out


def retrain(
    seed: int | None = None,
    targets: list[str] | None = None,
    promote_models: bool = True,
    only: set[str] | None = None,
    signals: Signals | None = None,
    lock_fd: int | None = None,
) -> dict:
    """The whole flow (module docstring) in this checkout, under the run lock (``lock_fd``: its
    descriptor); ``signals``: the installed :class:`Signals`. Returns the summary dict."""
    signals = signals or Signals()
    rc = promote_mod.registry_config(params())
    started = time.strftime("%Y-%m-%dT%H:%M:%S")
    s: dict[str, Any] = {"status": "running", "started": started, "targets": targets or []}
    run = _Run(s, journal_for(ROOT / rc.retrain.lock), rc, setup_logging())
    t0 = time.time()
    try:
        _prepare(run, seed, promote_models, only)
        _repro(run, targets, lock_fd)
        _gate(run, promote_models, only, signals)
        signals.hold()  # done: a signal from now on no longer undoes the run
        s["status"] = "succeeded"
        run.journal.discard()
    except (Exception, KeyboardInterrupt, Interrupted) as exc:  # noqa: BLE001 - restore on anything
        signals.hold()
        _undo(run, exc)
    finally:
        signals.hold()
        if signals.received is not None:
            s["signal"] = signal.Signals(signals.received).name
        try:
            after = champions(run.cl, run.names, run.rc.aliases.champion) if run.cl else None
        except Exception as exc:  # noqa: BLE001 - the summary must still be written
            after = f"unknown ({type(exc).__name__}: {exc})"
        s.update(champions_after=after, duration_s=round(time.time() - t0, 1))
        s["finished"] = time.strftime("%Y-%m-%dT%H:%M:%S")
        base = ROOT / run.rc.retrain.summary
        write_json_atomic(base.with_name(base.name + ".json"), s)
        write_text_atomic(base.with_name(base.name + ".md"), summary_markdown(s))
    return s


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m pipelines.retrain", description=__doc__.split("\n\n")[0]
    )
    ap.add_argument("--seed", type=int, help="set the data seed key(s) (default: old + seed_step)")
    ap.add_argument("--targets", nargs="+", help="only `dvc repro` these stages (default: all)")
    ap.add_argument("--only", nargs="+", metavar="NAME", help="gate only these registered models")
    ap.add_argument("--no-promote", action="store_true", help="skip the promotion gate")
    args = ap.parse_args(argv)
    try:
        cfg = params()
        rc = promote_mod.registry_config(cfg)
        if args.only:
            promotion.select(promote_mod.build_jobs(cfg, rc), args.only)  # unknown name: error now
        if args.targets:  # refuse before the seed is written (nothing changed yet)
            keys = list(rc.retrain.seed_keys)
            idle = seedless_targets(ROOT, args.targets, keys)
            if idle:
                raise ConfigError(
                    f"--targets {' '.join(idle)}: neither the stage nor any stage it depends on "
                    f"consumes the data seed key(s) {', '.join(keys)} "
                    "(registry.retrain.seed_keys), so a new seed would retrain nothing; nothing "
                    "changed — name a stage that depends on the data (e.g. train_fusion) or drop "
                    "--targets"
                )
    except (ConfigError, reg.RegistryError) as exc:
        print(f"retrain: error: {mask_secrets(str(exc))}", file=sys.stderr)
        return 1
    only = set(args.only) if args.only else None
    try:
        with Signals() as signals, exclusive_lock(ROOT / rc.retrain.lock, "retraining run") as fd:
            s = retrain(args.seed, args.targets, not args.no_promote, only, signals, fd)
    except LockBusy as exc:
        print(f"retrain: {exc}", file=sys.stderr)
        return EXIT_LOCKED
    except Interrupted as exc:  # before the lock was taken: nothing was changed
        print(f"retrain: {exc} before starting", file=sys.stderr)
        return 128 + exc.signum
    print(json.dumps({k: s.get(k) for k in PRINTED}, default=str))
    if s["status"] != "succeeded":
        kept = "previous data and champions kept" if s.get("restored") else "NOT restored: "
        kept += "; ".join(s.get("restore_problems") or [])
        print(
            mask_secrets(
                f"retrain: {s['status']} in step '{s.get('failed_step')}': {s.get('error')} ({kept})"
            ),
            file=sys.stderr,
        )
    if s.get("signal"):
        return 128 + int(signal.Signals[s["signal"]])
    return 0 if s["status"] == "succeeded" else 1


if __name__ == "__main__":
    sys.exit(main())
