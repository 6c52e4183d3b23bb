"""Scheduled retraining: new data batch -> `dvc repro` -> promotion gate -> summary.

    python -m pipelines.retrain [--seed N] [--targets STAGE ...] [--only NAME ...] [--no-promote]

1. **Lock.** ``fcntl.flock`` on ``registry.retrain.lock`` (default ``.retrain.lock``): a second
   retraining while one runs exits with status 75 at once and a message naming the lock and its
   holder (it writes no summary: the summary belongs to the run that holds the lock).
2. **Recovery.** A journal ``<lock without .lock>.journal/`` (default ``.retrain.journal/``) left
   by a run that was killed with SIGKILL (or lost its machine) is undone first: its ``dvc repro``
   process group is stopped if still running, then the repository is restored from it (below).
   Only then does this run start; the recovery is recorded in its summary (``recovered``). If the
   restore cannot be verified, the run stops (exit 1) and keeps the journal for the next try.
3. **Journal.** Before anything is changed: the ``dvc status`` of the checkout, the locked outputs
   present, copies of conf/, params.yaml, dvc.lock and reports/, the new seeds and this process's
   pid go into the journal (written to ``….journal.tmp/`` and renamed, so it exists only complete).
4. **New data.** Each key in ``registry.retrain.seed_keys`` (default the global ``seed``, from
   which every dataset seed derives) is bumped by ``seed_step`` (or set to ``--seed``) as a Hydra
   override: params.yaml is recomposed from conf/ with ``profile=<current> <key>=<new seed> …``
   (conf/ itself is never edited; the overrides are recorded in the summary). The new seed makes
   DVC regenerate the datasets: a new data version, recorded in dvc.lock (md5 of every ``data/``
   output) and cached by DVC (``dvc push`` sends it to a remote).
5. **Pipeline.** ``dvc repro`` (optionally only ``--targets``) as a child in its own session and
   process group (its pid is journaled).
6. **Gate.** :func:`pipelines.promote.promote` (register, compare with champion; every decision
   is taken before any alias moves), optionally only for the models named by ``--only``.
   ``--no-promote`` skips it and never opens the registry.
7. **Summary.** ``<registry.retrain.summary>.json`` and ``.md``, on every exit path of a run that
   holds the lock: ``succeeded``, ``failed`` or ``interrupted`` (a signal).

**Restore** (a failure or a signal before the gate moves an alias, or a stale journal): conf/,
params.yaml, dvc.lock and reports/ are copied back from the journal, ``dvc checkout --force``
puts every locked output back from the DVC cache (also the outputs of a stage that failed, which
DVC deletes before it runs a stage), and the result is verified: ``dvc status`` must equal the
status before the run and every locked output present then must be present again. The summary
says ``restored: true`` only when verified, else ``false`` with the reasons
(``restore_problems``); then the journal is kept so the next run retries the restore.

**Signals.** SIGTERM, SIGINT and SIGHUP stop the child's process group (SIGINT, then SIGTERM,
then SIGKILL after a grace period), restore, write an ``interrupted`` summary, release the lock
and exit with 128 + the signal number. A second signal during that cleanup is ignored. Once the
gate has started moving aliases, signals are held until the run has finished (the aliases and
the new outputs belong together): the summary then says ``succeeded`` with the ``signal`` and
the exit status is still 128 + signal. A run SIGKILLed while the gate moved aliases keeps its new
outputs (recovery says so) since the registry may already point at them.

Logs: the schedules write stdout/stderr outside reports/ (which a restore replaces):
``logs/retrain/`` (crontab) or the systemd journal.

Test hook: ``TRAFFICTWIN_RETRAIN_FAIL_AT=after_params|after_repro|before_apply`` raises there.
"""

from __future__ import annotations

import argparse
import fcntl
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import FrameType
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
SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)
# stopping the child's process group: each signal, then this many seconds for the group to exit
STOP_SEQUENCE = ((signal.SIGINT, 10.0), (signal.SIGTERM, 10.0), (signal.SIGKILL, 5.0))


class RetrainError(RuntimeError):
    """A retraining step failed (message names the step)."""


class LockBusy(RuntimeError):
    """Another retraining holds the lock."""


class Interrupted(BaseException):
    """A termination signal arrived (raised in the main thread by :class:`SignalGuard`)."""

    def __init__(self, signum: int) -> None:
        super().__init__(f"received {signal.Signals(signum).name}")
        self.signum = signum


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


# ------------------------------------------------------------------ signals and processes


class SignalGuard:
    """Turns SIGTERM/SIGINT/SIGHUP into :class:`Interrupted` in the main thread, at most once.

    Inside :meth:`deferred` (and for good after :meth:`hold`) a signal is only noted in
    ``received``; leaving the outermost :meth:`deferred` raises it then. Not entered (no
    handlers installed), it only records what :meth:`deferred` and :meth:`hold` are told.
    """

    def __init__(self) -> None:
        self.received: int | None = None
        self._depth = 0
        self._held = False
        self._raised = False
        self._old: dict[int, Any] = {}

    def __enter__(self) -> SignalGuard:
        for s in SIGNALS:
            self._old[s] = signal.signal(s, self._handle)
        return self

    def __exit__(self, *exc: object) -> None:
        for s, h in self._old.items():
            signal.signal(s, h)
        self._old.clear()

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self.received is None:
            self.received = signum
        if self._depth or self._held or self._raised:
            return
        self._raised = True
        raise Interrupted(signum)

    def hold(self) -> None:
        """From now on signals are only noted (the cleanup must not be interrupted)."""
        self._held = True

    @contextmanager
    def deferred(self) -> Iterator[None]:
        """Note signals during the block; raise the first one when the block ends normally."""
        self._depth += 1
        try:
            yield
        finally:
            self._depth -= 1
        if not (self._depth or self._held or self._raised) and self.received is not None:
            self._raised = True
            raise Interrupted(self.received)


def _proc_stat(pid: int) -> tuple[str, int, int] | None:
    """(state, process group, start time in clock ticks) from ``/proc/<pid>/stat``; None if gone."""
    try:
        raw = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    f = raw[raw.rindex(")") + 2 :].split()
    return f[0], int(f[2]), int(f[19])


def process_start(pid: int) -> int | None:
    """Start time of process ``pid`` (clock ticks since boot; None where /proc is missing)."""
    st = _proc_stat(pid)
    return None if st is None else st[2]


def alive(pid: int, start: int | None = None) -> bool:
    """Whether ``pid`` runs (zombies count as dead) and, given ``start``, is the same process
    that had that start time (not a later one that reused the pid)."""
    if not Path("/proc/self/stat").exists():  # no procfs: best effort
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        except PermissionError:
            return True
        return True
    st = _proc_stat(pid)
    if st is None or st[0] in "ZXx":
        return False
    return start is None or st[2] == start


def group_alive(pgid: int) -> bool:
    """Whether any live (non-zombie) process is in process group ``pgid``."""
    proc = Path("/proc")
    if not (proc / "self" / "stat").exists():
        try:
            os.killpg(pgid, 0)
        except ProcessLookupError:
            return False
        except PermissionError:
            return True
        return True
    for d in proc.iterdir():
        if d.name.isdigit():
            st = _proc_stat(int(d.name))
            if st is not None and st[1] == pgid and st[0] not in "ZXx":
                return True
    return False


def stop_group(pgid: int, log, child: subprocess.Popen | None = None) -> bool:
    """Stop process group ``pgid`` (SIGINT, SIGTERM, SIGKILL, each with a grace period; see
    :data:`STOP_SEQUENCE`); reaps ``child`` (the group leader) if given. True when it is gone."""
    for sig, grace in STOP_SEQUENCE:
        try:
            os.killpg(pgid, sig)
        except ProcessLookupError:
            break
        log.warning("retrain: sent %s to process group %d", sig.name, pgid)
        deadline = time.monotonic() + grace
        while time.monotonic() < deadline:
            if child is not None:
                child.poll()
            if not group_alive(pgid):
                break
            time.sleep(0.05)
        else:
            continue
        break
    if child is not None:
        try:
            child.wait(timeout=5)
        except subprocess.TimeoutExpired:
            pass
    return not group_alive(pgid)


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


def _lock_outs(root: Path) -> list[dict[str, Any]]:
    lock = root / "dvc.lock"
    if not lock.exists():
        return []
    doc = yaml.safe_load(lock.read_text()) or {}
    return [
        o for stage in (doc.get("stages") or {}).values() for o in (stage.get("outs") or []) if o
    ]


def data_versions(root: Path) -> dict[str, str]:
    """md5 of every ``data/`` output recorded in dvc.lock (the data version)."""
    out = {
        o["path"]: o.get("md5", "")
        for o in _lock_outs(root)
        if str(o.get("path", "")).startswith("data/")
    }
    return dict(sorted(out.items()))


# ------------------------------------------------------------------ snapshot / DVC state / restore


class Snapshot:
    """Copies of conf/, params.yaml, dvc.lock and reports/ (in ``dest``) to restore after a failure.

    ``Snapshot(root, dest)`` takes the copies; ``Snapshot.open(root, dest)`` reads an existing one
    (a journal's). The flow itself never edits conf/; the copy makes a restore return the whole
    input tree.
    """

    FILES = ("params.yaml", "dvc.lock")
    DIRS = ("conf", "reports")

    def __init__(self, root: Path, dest: Path, *, take: bool = True) -> None:
        self.root, self.dest = Path(root), Path(dest)
        if not take:
            self.present = json.loads((self.dest / "snapshot.json").read_text())
            return
        self.dest.mkdir(parents=True, exist_ok=True)
        self.present = {}
        for rel in self.FILES:
            p = self.root / rel
            self.present[rel] = p.exists()
            if p.exists():
                shutil.copy2(p, self.dest / rel)
        for rel in self.DIRS:
            p = self.root / rel
            self.present[rel] = p.exists()
            if p.exists():
                shutil.copytree(p, self.dest / rel, symlinks=True)
        write_json_atomic(self.dest / "snapshot.json", self.present)

    @classmethod
    def open(cls, root: Path, dest: Path) -> Snapshot:
        """An existing snapshot in ``dest`` (written by ``Snapshot(root, dest)``)."""
        return cls(root, dest, take=False)

    def restore_files(self) -> None:
        """Put conf/, params.yaml, dvc.lock and reports/ back as they were (idempotent)."""
        for rel in self.FILES:
            p = self.root / rel
            if self.present.get(rel):
                write_bytes_atomic(p, (self.dest / rel).read_bytes())
            else:
                p.unlink(missing_ok=True)
        for rel in self.DIRS:
            shutil.rmtree(self.root / rel, ignore_errors=True)
            if self.present.get(rel):
                shutil.copytree(self.dest / rel, self.root / rel, symlinks=True)


def _dvc(root: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["dvc", *args], cwd=root, capture_output=True, text=True)


def dvc_state(root: Path) -> dict[str, Any]:
    """``{"status": <dvc status --json>, "outs": [locked outputs present]}`` of the checkout."""
    proc = _dvc(root, "status", "--json")
    if proc.returncode != 0:
        raise RetrainError(f"`dvc status` failed ({proc.returncode}): {proc.stderr.strip()[-800:]}")
    lines = [ln for ln in proc.stdout.splitlines() if ln.strip()]
    try:
        status = json.loads(lines[-1]) if lines else {}
    except json.JSONDecodeError:
        raise RetrainError(f"`dvc status --json` printed no JSON: {proc.stdout[-400:]!r}") from None
    outs = sorted({str(o["path"]) for o in _lock_outs(root) if (root / str(o["path"])).exists()})
    return {"status": status, "outs": outs}


def verify_state(root: Path, before: dict[str, Any]) -> list[str]:
    """Reasons the checkout differs from ``before`` (a :func:`dvc_state`); empty when it matches."""
    try:
        now = dvc_state(root)
    except RetrainError as exc:
        return [str(exc)]
    problems = []
    missing = [p for p in before["outs"] if not (root / p).exists()]
    if missing:
        problems.append(f"locked outputs missing after the restore: {', '.join(missing)}")
    if now["status"] != before["status"]:
        differ = sorted(
            k
            for k in set(now["status"]) | set(before["status"])
            if now["status"].get(k) != before["status"].get(k)
        )
        problems.append(
            f"`dvc status` differs from before the run for: {', '.join(differ)} "
            f"(now: {json.dumps({k: now['status'].get(k) for k in differ})[:600]})"
        )
    return problems


def _checkout_locked(root: Path, log) -> list[str]:
    """``dvc checkout --force`` of every stage dvc.lock records and dvc.yaml defines (a lock may
    keep foreach items of another profile, whose outputs are not cached here); folders that the
    checkout creates for outputs it cannot restore are removed again. Returns problems."""
    lock = root / "dvc.lock"
    locked = (yaml.safe_load(lock.read_text()) or {}).get("stages") or {} if lock.exists() else {}
    listed = _dvc(root, "stage", "list", "--name-only")
    if listed.returncode != 0:
        return [f"dvc stage list failed ({listed.returncode}): {listed.stderr.strip()[-800:]}"]
    stages = sorted(set(locked) & set(listed.stdout.split()))
    if not stages:
        return []
    outs = [str(o["path"]) for n in stages for o in (locked[n].get("outs") or [])]
    absent = {a for p in outs for a in Path(p).parents if a.parts and not (root / a).exists()}
    proc = _dvc(root, "checkout", "--force", *stages)
    for d in sorted(absent, key=lambda a: len(a.parts), reverse=True):
        try:
            (root / d).rmdir()  # only if empty: a folder the checkout made for nothing
        except OSError:
            pass
    if proc.returncode != 0:  # e.g. an output that was missing before too: the verification decides
        log.warning(
            "restore: dvc checkout --force exited %d: %s",
            proc.returncode,
            proc.stderr.strip()[-800:],
        )
        return [f"dvc checkout --force failed ({proc.returncode}): {proc.stderr.strip()[-800:]}"]
    return []


def restore(root: Path, snap: Snapshot, before: dict[str, Any], log) -> list[str]:
    """Files back from ``snap``, locked outputs back with ``dvc checkout --force``, then verified
    against ``before``; returns the reasons it is not as before (empty: verified)."""
    snap.restore_files()
    checkout = _checkout_locked(root, log)
    problems = verify_state(root, before)
    if problems:
        problems = checkout + problems  # a checkout error alone is no problem if all is as before
    for p in problems:
        log.error("restore: %s", p)
    return problems


# ------------------------------------------------------------------ journal (SIGKILL recovery)


def journal_path(lock: Path) -> Path:
    """``.retrain.lock`` -> ``.retrain.journal`` (same folder)."""
    return lock.with_name(lock.name.removesuffix(".lock") + ".journal")


class Journal:
    """What a running retraining changes, on disk before it changes it: ``state.json`` (pid and
    its start time, seeds, step, child process group, ``dvc_before``) and ``snapshot/``."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.tmp = self.path.with_name(self.path.name + ".tmp")
        self.state: dict[str, Any] = {}

    def snapshot(self, root: Path) -> Snapshot:
        return Snapshot.open(root, self.path / "snapshot")

    def begin(self, root: Path, state: dict[str, Any]) -> None:
        """Snapshot ``root`` and write ``state``; the journal appears complete or not at all."""
        if self.path.exists():
            raise RetrainError(f"journal {self.path} exists: an unrecovered retraining")
        shutil.rmtree(self.tmp, ignore_errors=True)
        try:
            Snapshot(root, self.tmp / "snapshot")
            write_json_atomic(self.tmp / "state.json", state)
            os.replace(self.tmp, self.path)
        except BaseException:
            shutil.rmtree(self.tmp, ignore_errors=True)
            raise
        self.state = dict(state)

    def update(self, **kw: Any) -> None:
        self.state.update(kw)
        write_json_atomic(self.path / "state.json", self.state)

    def read(self) -> dict[str, Any]:
        try:
            self.state = json.loads((self.path / "state.json").read_text())
        except (OSError, ValueError) as exc:
            raise RetrainError(
                f"journal {self.path} is unreadable ({exc}); restore conf/, params.yaml, dvc.lock "
                f"and reports/ from {self.path / 'snapshot'} by hand, run `dvc checkout --force`, "
                "then remove the journal"
            ) from None
        return self.state

    def discard(self) -> None:
        shutil.rmtree(self.path, ignore_errors=True)
        shutil.rmtree(self.tmp, ignore_errors=True)


def recover(root: Path, journal: Journal, log) -> dict[str, Any] | None:
    """Undo what a killed retraining left (see module docstring); None when there is no journal.

    Raises :class:`LockBusy` if the journal's process still runs; returns the recovery record,
    whose ``problems`` (if any) mean the restore could not be verified and the journal is kept.
    """
    shutil.rmtree(journal.tmp, ignore_errors=True)  # an unfinished journal: nothing was changed yet
    if not journal.path.exists():
        return None
    st = journal.read()
    pid = int(st.get("pid", -1))
    if pid != os.getpid() and alive(pid, st.get("pid_start")):
        raise LockBusy(f"retraining pid {pid} of journal {journal.path} still runs")
    rec: dict[str, Any] = {"pid": pid, "started": st.get("started"), "step": st.get("step")}
    log.warning("retrain: recovering from the journal of killed run pid %d (%s)", pid, rec)
    child = st.get("child_pid")
    if child:
        leader = _proc_stat(int(child))
        reused = leader is not None and leader[2] != st.get("child_start")
        if not reused and group_alive(int(child)):
            rec["child_stopped"] = stop_group(int(child), log)
    if st.get("step") == "apply":
        rec["restored"] = False
        rec["note"] = (
            "killed while the gate moved aliases: its new outputs were kept, "
            "the registry may point at them; check `champion` aliases"
        )
        journal.discard()
        return rec
    problems = restore(root, journal.snapshot(root), st["dvc_before"], log)
    if st.get("registry_before"):
        try:
            rec["orphans"] = retire_orphans(reg.client(), st["registry_before"], log)
        except Exception as exc:  # noqa: BLE001 - reported; the files are restored either way
            problems.append(f"orphan versions not retired: {type(exc).__name__}: {exc}")
    rec["restored"] = not problems
    if problems:
        rec["problems"] = problems
    else:
        journal.discard()
    return rec


def retire_orphans(cl, before: dict[str, int], log) -> list[str]:
    """Versions an interrupted gate registered for outputs now rolled back: deleted (or tagged
    orphan where an alias points at one) so the registry holds no version of undone data."""
    done = reg.retire_versions_after(
        cl, before, "registered by an interrupted retraining whose outputs were rolled back"
    )
    for d in done:
        log.warning("restore: %s", d)
    return done


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
    if s.get("recovered"):
        lines.append(f"- recovered first from a killed run: {s['recovered']}")
    if s.get("signal"):
        lines.append(f"- signal: {s['signal']}")
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


def _recover_first(s: dict[str, Any], journal: Journal, guard: SignalGuard, log) -> None:
    with guard.deferred():  # a signal during the recovery is raised once it is done
        rec = recover(ROOT, journal, log)
    if rec is None:
        return
    s["recovered"] = rec
    if rec.get("problems"):
        raise RetrainError(
            f"could not restore what the killed retraining pid {rec['pid']} left: "
            f"{'; '.join(rec['problems'])}; fix it, then rerun (the journal {journal.path} is kept)"
        )


def retrain(
    seed: int | None = None,
    targets: list[str] | None = None,
    promote_models: bool = True,
    only: set[str] | None = None,
    guard: SignalGuard | None = None,
) -> dict:
    """The whole flow (see module docstring) in this checkout; call it under :func:`retrain_lock`.

    ``guard``: the installed :class:`SignalGuard` (default: none installed). Returns the summary
    dict, also written to ``registry.retrain.summary``; ``signal`` in it names a signal received.
    """
    log = setup_logging()
    guard = guard or SignalGuard()
    t0 = time.time()
    s: dict[str, Any] = {
        "status": "running",
        "started": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "targets": targets or [],
    }
    cfg = params()
    rc = promote_mod.registry_config(cfg)
    journal = Journal(journal_path(ROOT / rc.retrain.lock))
    summary = ROOT / rc.retrain.summary
    step = "recover"
    child: subprocess.Popen | None = None
    applied = began = False
    cl, names = None, []
    try:
        _recover_first(s, journal, guard, log)
        step = "prepare"
        cfg = params()  # as the recovery left it
        rc = promote_mod.registry_config(cfg)
        summary = ROOT / rc.retrain.summary
        profile = get(cfg, "profile.name", str)
        s.update(profile=profile, git_commit=git_commit(ROOT), data_before=data_versions(ROOT))
        if promote_models:
            names = [n for n in promote_mod.model_names(cfg, rc) if not only or n in only]
            cl = reg.client()
            s["champions_before"] = champions(cl, names, rc.aliases.champion)

        step = "new_data"
        seeds = seed_overrides(cfg, rc.retrain.seed_keys, rc.retrain.seed_step, seed)
        composed, overrides = compose_with_seeds(CONF, profile, seeds)
        s["seeds"] = seeds
        s["overrides"] = overrides
        step = "journal"
        journal.begin(
            ROOT,
            {
                "pid": os.getpid(),
                "pid_start": process_start(os.getpid()),
                "started": s["started"],
                "seeds": seeds,
                "step": "new_data",
                "dvc_before": dvc_state(ROOT),
            },
        )
        began = True
        step = "new_data"
        dump_params(composed, PARAMS)
        log.info("retrain: new data seeds %s", seeds)
        _inject("after_params")

        step = "dvc_repro"
        journal.update(step=step)
        t = time.time()
        with guard.deferred():  # the child's pid is journaled before a signal can stop this run
            child = subprocess.Popen(
                ["dvc", "repro", *(targets or [])], cwd=ROOT, start_new_session=True
            )
            journal.update(child_pid=child.pid, child_start=process_start(child.pid))
        code = child.wait()
        child = None
        s["repro_s"] = round(time.time() - t, 1)
        if code != 0:
            raise RetrainError(f"`dvc repro` failed with status {code}")
        s["data_after"] = data_versions(ROOT)
        _inject("after_repro")

        step = "promote"
        if cl is not None:  # versions above these that an interrupted gate registers are orphans
            s["registry_before"] = reg.latest_versions(cl, names)
        journal.update(step=step, registry_before=s.get("registry_before"))
        decisions = []
        if promote_models:
            # decide all first (under the registry lock, held until the aliases moved):
            # nothing moves on error
            def before_apply(_decisions) -> None:
                nonlocal step, applied
                _inject("before_apply")
                guard.hold()  # aliases and new outputs belong together: finish first
                step = "apply"
                journal.update(step=step)
                applied = True

            decisions = promote_mod.promote(only, before_apply=before_apply)
        guard.hold()  # done: a signal from now on no longer undoes the run
        s["decisions"] = [d.to_dict() for d in decisions]
        s["status"] = "succeeded"
        journal.discard()
    except (Exception, KeyboardInterrupt, Interrupted) as exc:  # noqa: BLE001 - restore on anything
        guard.hold()
        if isinstance(exc, Interrupted):
            s["status"] = "interrupted"
        else:
            s["status"] = "failed"
        s["failed_step"] = step
        s["error"] = f"{type(exc).__name__}: {exc}"
        log.error("retrain %s in step %s: %s", s["status"], step, s["error"])
        if child is not None:
            s["child_stopped"] = stop_group(child.pid, log, child)
        if step == "recover":  # this run had changed nothing yet
            rec = s.get("recovered")
            if rec is not None:
                problems = rec.get("problems") or []
            else:
                problems = [] if isinstance(exc, Interrupted) else [s["error"]]
        elif applied:
            problems = ["the gate had started moving aliases: nothing restored"]
            journal.discard()
        elif began:
            try:
                before = journal.read()["dvc_before"]
                problems = restore(ROOT, journal.snapshot(ROOT), before, log)
            except Exception as err:  # noqa: BLE001 - reported, the journal is kept
                problems = [f"restore failed: {type(err).__name__}: {err}"]
            if cl is not None and s.get("registry_before"):
                s["orphans"] = retire_orphans(cl, s["registry_before"], log)
            if not problems:
                journal.discard()  # else kept: the next run retries the restore
        else:
            problems = []  # nothing had been changed yet
        s["restored"] = not problems
        if problems:
            s["restore_problems"] = problems
    finally:
        guard.hold()
        if guard.received is not None:
            s["signal"] = signal.Signals(guard.received).name
        try:
            s["champions_after"] = champions(cl, names, rc.aliases.champion) if cl else None
        except Exception as exc:  # noqa: BLE001 - the summary must still be written
            s["champions_after"] = f"unknown ({type(exc).__name__}: {exc})"
        s["duration_s"] = round(time.time() - t0, 1)
        s["finished"] = time.strftime("%Y-%m-%dT%H:%M:%S")
        write_summary(summary, s)
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
        with SignalGuard() as guard, retrain_lock(ROOT / rc.retrain.lock):
            only = set(args.only) if args.only else None
            s = retrain(args.seed, args.targets, not args.no_promote, only, guard)
    except LockBusy as exc:
        print(f"retrain: {exc}", file=sys.stderr)
        return EXIT_LOCKED
    except Interrupted as exc:  # before the lock was taken: nothing was changed
        print(f"retrain: {exc} before starting", file=sys.stderr)
        return 128 + exc.signum
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
                    "restored",
                    "signal",
                    "duration_s",
                )
            },
            default=str,
        )
    )
    if s["status"] != "succeeded":
        kept = (
            "previous data and champions kept"
            if s.get("restored")
            else f"NOT restored: {'; '.join(s.get('restore_problems') or [])}"
        )
        print(
            f"retrain: {s['status']} in step '{s.get('failed_step')}': {s.get('error')} ({kept})",
            file=sys.stderr,
        )
    if s.get("signal"):
        return 128 + int(signal.Signals[s["signal"]])
    return 0 if s["status"] == "succeeded" else 1


if __name__ == "__main__":
    sys.exit(main())
