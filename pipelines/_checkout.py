"""The checkout's DVC state, and putting it back after a failed run (used by ``retrain.py``).

:data:`RESTORED` are the paths a retraining may change besides DVC outputs. Its journal
(:class:`~traffictwin.mlops.journal.Journal`) holds a snapshot of them and :func:`dvc_state` before
the run; :func:`undo` returns the checkout to where it was: the files back, ``dvc checkout
--force`` for every locked output (also those of a failed stage, which DVC deletes before it runs
one), verified (``dvc status`` as before, every locked output present then present again), and
model versions an interrupted gate registered since retired. :func:`recover` does it for a
journal that a killed run left.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path
from typing import Any

from traffictwin.io.yamlio import safe_load
from traffictwin.mlops import registry as reg
from traffictwin.mlops.journal import Journal, Snapshot

RESTORED = ("params.yaml", "dvc.lock", "conf", "reports")


class CheckoutError(RuntimeError):
    """A DVC command about the checkout's state failed (the message names it)."""


def _dvc(root: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["dvc", *args], cwd=root, capture_output=True, text=True)


def _locked_stages(root: Path) -> dict[str, Any]:
    lock = root / "dvc.lock"
    return ((safe_load(lock.read_text()) or {}).get("stages") or {}) if lock.exists() else {}


def _lock_outs(root: Path) -> list[dict[str, Any]]:
    return [o for st in _locked_stages(root).values() for o in (st.get("outs") or []) if o]


def data_versions(root: Path) -> dict[str, str]:
    """md5 of every ``data/`` output recorded in dvc.lock (the data version)."""
    outs = [(str(o.get("path", "")), o.get("md5", "")) for o in _lock_outs(root)]
    return dict(sorted((p, md5) for p, md5 in outs if p.startswith("data/")))


def dvc_state(root: Path) -> dict[str, Any]:
    """``{"status": <dvc status --json>, "outs": [locked outputs present]}`` of the checkout."""
    proc = _dvc(root, "status", "--json")
    if proc.returncode != 0:
        raise CheckoutError(
            f"`dvc status` failed ({proc.returncode}): {proc.stderr.strip()[-800:]}"
        )
    lines = [ln for ln in proc.stdout.splitlines() if ln.strip()]
    try:
        status = json.loads(lines[-1]) if lines else {}
    except json.JSONDecodeError:
        raise CheckoutError(
            f"`dvc status --json` printed no JSON: {proc.stdout[-400:]!r}"
        ) from None
    outs = sorted({str(o["path"]) for o in _lock_outs(root) if (root / str(o["path"])).exists()})
    return {"status": status, "outs": outs}


def verify_state(root: Path, before: dict[str, Any]) -> list[str]:
    """Reasons the checkout differs from ``before`` (a :func:`dvc_state`); empty when it matches."""
    try:
        now = dvc_state(root)
    except CheckoutError as exc:
        return [str(exc)]
    problems = []
    missing = [p for p in before["outs"] if not (root / p).exists()]
    if missing:
        problems.append(f"locked outputs missing after the restore: {', '.join(missing)}")
    old, new = before["status"], now["status"]
    differ = sorted(k for k in set(new) | set(old) if new.get(k) != old.get(k))
    if differ:
        problems.append(
            f"`dvc status` differs from before the run for: {', '.join(differ)} "
            f"(now: {json.dumps({k: new.get(k) for k in differ})[:600]})"
        )
    return problems


def _checkout_locked(root: Path, log) -> list[str]:
    """``dvc checkout --force`` of every stage dvc.lock records and dvc.yaml defines (a lock may
    keep foreach items of another profile, whose outputs are not cached here); folders that the
    checkout creates for outputs it cannot restore are removed again. Returns problems."""
    locked = _locked_stages(root)
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
        err = f"dvc checkout --force failed ({proc.returncode}): {proc.stderr.strip()[-800:]}"
        log.warning("restore: %s", err)
        return [err]
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


def journal_for(lock: Path) -> Journal:
    """The journal beside the run lock: ``.retrain.lock`` -> ``.retrain.journal``."""
    return Journal(lock.with_name(lock.name.removesuffix(".lock") + ".journal"))


def retire_orphans(cl, before: dict[str, int], log) -> list[str]:
    """Versions an interrupted gate registered for outputs now rolled back: deleted (or tagged
    orphan where an alias points at one) so the registry holds no version of undone data."""
    why = "registered by an interrupted retraining whose outputs were rolled back"
    done = reg.retire_versions_after(cl, before, why)
    for d in done:
        log.warning("restore: %s", d)
    return done


def undo(root: Path, journal: Journal, log, cl=None) -> tuple[list[str], list[str]]:
    """Restore ``root`` from ``journal`` and retire the versions registered since its
    ``registry_before`` (``cl``: the registry client, default a new one); the journal is discarded
    once the restore is verified. Returns (problems, retired versions)."""
    try:
        st = journal.read()
        problems = restore(root, journal.snapshot(root), st["dvc_before"], log)
    except Exception as err:  # noqa: BLE001 - reported, the journal is kept
        st, problems = journal.state, [f"restore failed: {type(err).__name__}: {err}"]
    orphans: list[str] = []
    if st.get("registry_before"):
        try:
            orphans = retire_orphans(cl or reg.client(), st["registry_before"], log)
        except Exception as exc:  # noqa: BLE001 - reported; the files are restored either way
            problems.append(f"orphan versions not retired: {type(exc).__name__}: {exc}")
    if not problems:
        journal.discard()  # else kept: the next run retries the restore
    return problems, orphans


def recover(root: Path, journal: Journal, log) -> dict[str, Any] | None:
    """Undo what a killed run left (None: no journal). The caller holds the run lock, which the
    killed run and its ``dvc repro`` held: so they are gone. ``problems`` in the returned record
    mean the restore could not be verified, and the journal is kept."""
    shutil.rmtree(journal.tmp, ignore_errors=True)  # an unfinished journal: nothing was changed yet
    if not journal.path.exists():
        return None
    st = journal.read()
    rec: dict[str, Any] = {k: st.get(k) for k in ("pid", "started", "step")}
    log.warning("retrain: recovering from the journal of killed run %s", rec)
    if st.get("step") == "apply":
        rec["restored"] = False
        rec["note"] = (
            "killed while the gate moved aliases: its new outputs were kept, "
            "the registry may point at them; check `champion` aliases"
        )
        journal.discard()
        return rec
    problems, orphans = undo(root, journal, log)
    if orphans:
        rec["orphans"] = orphans
    rec["restored"] = not problems
    if problems:
        rec["problems"] = problems
    return rec
