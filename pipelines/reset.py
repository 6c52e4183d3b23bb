"""`make reset`'s last step: data/ and models/ as the (just restored) dvc.lock says, from the DVC
cache only, and one line each on what could not be restored and on the registry.

``dvc checkout --allow-missing`` restores every output whose cache entry exists and says nothing
about the others (a plain ``dvc checkout`` prints an ERROR and every missing path, which on a
fresh clone is every output). ``dvc status`` then names the outputs that are still not as
dvc.lock says; they are summarised in one line with what gets them (``make run`` rebuilds them,
``make pull`` fetches them from a DVC remote that holds a finished run). When this clone's
MLflow registry (``mlflow.db``) has champions, one more line says that they are unchanged (their
files are MLflow artifacts, not models/) and what ``--model models/…`` needs.

Run from the repository root: ``python -m pipelines.reset``.
"""

from __future__ import annotations

import json
import sqlite3
import subprocess
import sys
from pathlib import Path

from ._paths import ROOT

#: how many paths the summary line names before "…"
SHOWN = 4


def dvc(*args: str) -> subprocess.CompletedProcess:
    """``dvc <args>`` of this environment, in the repository root, output captured."""
    exe = Path(sys.executable).with_name("dvc")
    cmd = [str(exe) if exe.exists() else "dvc", *args]
    return subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)


def not_as_locked(status: dict) -> list[str]:
    """The outputs ``dvc status --json`` reports as changed (deleted, modified, not in cache),
    sorted; changed dependencies and parameters are not outputs and are left out."""
    outs: set[str] = set()
    for entries in status.values():
        for e in entries if isinstance(entries, list) else []:
            if isinstance(e, dict):
                outs.update((e.get("changed outs") or {}).keys())
    return sorted(outs)


def missing_line(paths: list[str]) -> str:
    """One line: how many outputs are not as dvc.lock says, a few of them, and what gets them."""
    if not paths:
        return "make reset: data/ and models/ are as dvc.lock says"
    shown = ", ".join(paths[:SHOWN]) + (", …" if len(paths) > SHOWN else "")
    return (
        f"make reset: {len(paths)} outputs of dvc.lock are not in this clone's DVC cache "
        f"({shown}): `make run` rebuilds them, `make pull` fetches them from a DVC remote that "
        "holds a finished run"
    )


def champions(db: Path) -> list[str]:
    """``name@alias`` of every alias in the MLflow registry ``db`` (SQLite); [] without one."""
    if not db.is_file():
        return []
    try:
        with sqlite3.connect(f"file:{db}?mode=ro", uri=True) as con:
            rows = con.execute("SELECT name, alias FROM registered_model_aliases").fetchall()
    except sqlite3.Error:
        return []
    return sorted(f"{n}@{a}" for n, a in rows if a == "champion")


def registry_line(champs: list[str], models_missing: bool) -> str | None:
    """One line on the registry's champions after the reset, or None without any."""
    if not champs:
        return None
    what = (
        "`--model models/…` needs `make run` or `make pull` first"
        if models_missing
        else "models/ holds the committed run's models"
    )
    return (
        f"make reset: the registry (mlflow.db) is unchanged: {len(champs)} champions stay "
        f"servable as `--model champion` (possibly the run just undone's; `make promote` after "
        f"`make run` replaces them); {what}"
    )


def main() -> int:
    co = dvc("checkout", "--allow-missing", "--quiet")
    if co.returncode != 0:  # not a missing cache entry: a real failure, shown as DVC says it
        sys.stderr.write(co.stderr)
        return co.returncode
    st = dvc("status", "--json")
    try:
        status = json.loads(st.stdout or "{}")
    except json.JSONDecodeError:
        status = {}
    paths = not_as_locked(status)
    print(missing_line(paths))
    line = registry_line(champions(ROOT / "mlflow.db"), any(p.startswith("models/") for p in paths))
    if line:
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
