"""Provenance of a pipeline run, computed by the workflow layer and handed to the library.

:func:`provenance_env` returns the git commit of the checkout and the SHA-256 of its
params.yaml as environment variables (``TRAFFICTWIN_GIT_COMMIT``, ``TRAFFICTWIN_PARAMS_HASH``);
``pipelines._common.run_stage`` exports them before a stage runs, and
:mod:`traffictwin.mlops.tracking` tags every MLflow run with them (the library itself runs no
git and reads no params.yaml).
"""

from __future__ import annotations

import hashlib
import os
import subprocess
from pathlib import Path

from traffictwin.mlops.tracking import ENV_DVC_BASELINE, ENV_GIT_COMMIT, ENV_PARAMS_HASH

from ._paths import PARAMS, ROOT


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


def provenance_env(root: str | Path = ROOT, params: str | Path = PARAMS) -> dict[str, str]:
    """``{TRAFFICTWIN_GIT_COMMIT: <commit>, TRAFFICTWIN_PARAMS_HASH: <sha256>}`` of the checkout
    ``root`` and its params file, to export before a stage runs (``os.environ.update(...)``)."""
    return {ENV_GIT_COMMIT: git_commit(root), ENV_PARAMS_HASH: params_hash(params)}
