"""Provenance of a pipeline run, computed by the workflow layer and handed to the library.

:func:`provenance_env` returns the git commit of the checkout and the SHA-256 of its
params.yaml as environment variables (``TRAFFICTWIN_GIT_COMMIT``, ``TRAFFICTWIN_PARAMS_HASH``)
and what the params.yaml the stage runs with changes against the committed one
(``TRAFFICTWIN_PARAMS_OVERRIDES``: a DVC experiment's ``-S`` overrides, as JSON);
``pipelines._common.run_stage`` exports them before a stage runs, and
:mod:`traffictwin.mlops.tracking` tags every MLflow run with them (the library itself runs no
git and reads no params.yaml).
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
from pathlib import Path

import yaml

from traffictwin.config import flatten
from traffictwin.io.yamlio import safe_load
from traffictwin.mlops.tracking import (
    ENV_DVC_BASELINE,
    ENV_GIT_COMMIT,
    ENV_PARAMS_HASH,
    ENV_PARAMS_OVERRIDES,
)

from ._paths import PARAMS, ROOT

#: conf/ composed with another profile, one JSON file per state of conf/ and profile (relative to
#: the repository; git-ignored): every stage of a `dvc exp run -S profile=ci` compares against the
#: same composition, and Hydra takes about half a second to make it
COMPOSED = Path(".cache") / "traffictwin" / "composed"


def composed_profile(root: str | Path, profile: str) -> dict:
    """``root``'s conf/ composed with ``profile=<profile>`` (plain containers), read from
    :data:`COMPOSED` when a stage already composed the same conf/ files for the same profile (the
    key hashes every file of conf/ and the profile's name); an unknown profile raises as Hydra does."""
    from traffictwin.config import compose_config
    from traffictwin.io.atomic import write_text_atomic

    conf = Path(root) / "conf"
    key = hashlib.sha256(profile.encode() + b"\0")
    for f in sorted(p for p in conf.rglob("*") if p.is_file()):
        key.update(f.relative_to(conf).as_posix().encode() + b"\0" + f.read_bytes() + b"\0")
    cached = Path(root) / COMPOSED / f"{key.hexdigest()}.json"
    try:
        return json.loads(cached.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        pass
    composed = compose_config(conf, [f"profile={profile}"])
    try:
        write_text_atomic(cached, json.dumps(composed))
    except OSError:  # a read-only checkout: composed again next time
        pass
    return composed


def git_commit(root: str | Path = ROOT) -> str:
    """The commit runs belong to: ``DVC_EXP_BASELINE_REV`` inside a DVC experiment (a queued
    experiment's temp copy has its own throw-away HEAD), else ``HEAD`` of ``root``;
    ``"unknown"`` outside a git checkout."""
    base = os.environ.get(ENV_DVC_BASELINE)
    if base:
        return base
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            cwd=root,
            capture_output=True,
            text=True,
            timeout=10,
        )
        return out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def params_hash(path: str | Path = PARAMS) -> str:
    """SHA-256 (hex) of the params file's bytes; ``""`` if it cannot be read."""
    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()
    except OSError:
        return ""


def params_overrides(
    root: str | Path = ROOT, params: str | Path = PARAMS, commit: str | None = None
) -> dict[str, list[str]]:
    """``{"a.b": [committed, now]}`` for every flattened key whose value in the params file
    differs from the same file at git ``commit`` (default :func:`git_commit`: the DVC
    experiment's baseline), values as text (``None`` where a side lacks the key); ``{}`` when
    either side cannot be read (no git checkout, the file not committed). Another profile is
    one entry ``profile`` (the dozens of keys a profile sets are not listed): the rest is
    compared with ``root``'s conf/ composed with the new profile."""
    commit = git_commit(root) if commit is None else commit
    path = Path(params)
    try:
        rel = path.resolve().relative_to(Path(root).resolve()).as_posix()
        now = safe_load(path.read_text(encoding="utf-8"))
        out = subprocess.run(
            ["git", "show", f"{commit}:{rel}"],
            cwd=root,
            capture_output=True,
            text=True,
            timeout=10,
        )
        if out.returncode != 0:
            return {}
        committed = safe_load(out.stdout)
    except (OSError, ValueError, subprocess.SubprocessError, yaml.YAMLError):
        return {}
    if not isinstance(now, dict) or not isinstance(committed, dict):
        return {}
    out: dict[str, list[str | None]] = {}
    old_profile = (committed.get("profile") or {}).get("name")
    new_profile = (now.get("profile") or {}).get("name")
    if old_profile != new_profile and (Path(root) / "conf").is_dir():
        # another profile (`-S profile=ci`): one override `profile`, and against the committed
        # conf/ composed with that profile only what else was changed
        try:
            committed = composed_profile(root, str(new_profile))
        except Exception:  # noqa: BLE001 - an unknown profile: the plain diff below
            pass
        else:
            out["profile"] = [str(old_profile), str(new_profile)]
    a, b = flatten(committed), flatten(now)
    out.update(
        {
            k: [None if k not in a else str(a[k]), None if k not in b else str(b[k])]
            for k in sorted(set(a) | set(b))
            if a.get(k, ...) != b.get(k, ...)
        }
    )
    return out


def provenance_env(root: str | Path = ROOT, params: str | Path = PARAMS) -> dict[str, str]:
    """``{TRAFFICTWIN_GIT_COMMIT: <commit>, TRAFFICTWIN_PARAMS_HASH: <sha256>,
    TRAFFICTWIN_PARAMS_OVERRIDES: <JSON of params_overrides>}`` of the checkout ``root`` and its
    params file, to export before a stage runs (``os.environ.update(...)``)."""
    commit = git_commit(root)
    overrides = params_overrides(root, params, commit)
    return {
        ENV_GIT_COMMIT: commit,
        ENV_PARAMS_HASH: params_hash(params),
        ENV_PARAMS_OVERRIDES: json.dumps(overrides, sort_keys=True),
    }
