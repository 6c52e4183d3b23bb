"""MLflow tracking: where runs go and how they are tagged (DESIGN.md "Tracking").

Tracking URI: ``MLFLOW_TRACKING_URI`` if set, else SQLite ``mlflow.db`` at the repository
root, as an absolute path (so queued ``dvc exp run`` temp copies still reach it when the
variable is exported; see :func:`repo_root`).
"""

from __future__ import annotations

import os
import subprocess
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator, Mapping

ENV_URI = "MLFLOW_TRACKING_URI"
ENV_REPO = "TRAFFICTWIN_REPO_ROOT"


def repo_root(start: str | Path | None = None) -> Path:
    """The project root: ``TRAFFICTWIN_REPO_ROOT`` if set, else the nearest folder with dvc.yaml or .git."""
    env = os.environ.get(ENV_REPO)
    if env:
        return Path(env).resolve()
    here = Path(start or os.getcwd()).resolve()
    for p in (here, *here.parents):
        if (p / "dvc.yaml").exists() or (p / ".git").exists():
            return p
    return here


def tracking_uri(root: str | Path | None = None) -> str:
    """``MLFLOW_TRACKING_URI`` if set, else ``sqlite:////abs/path/mlflow.db`` at the repo root."""
    env = os.environ.get(ENV_URI)
    if env:
        return env
    db = (Path(root) if root else repo_root()).resolve() / "mlflow.db"
    return f"sqlite:///{db}"


def git_commit(root: str | Path | None = None) -> str:
    """Current git commit hash (``"unknown"`` outside a git checkout)."""
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=root or repo_root(), capture_output=True, text=True, timeout=10
        )
        return out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def setup(root: str | Path | None = None) -> str:
    """Point MLflow at :func:`tracking_uri`; returns the URI."""
    import mlflow

    uri = tracking_uri(root)
    mlflow.set_tracking_uri(uri)
    return uri


def base_tags(profile: str, stage: str, extra: Mapping[str, Any] | None = None) -> dict[str, str]:
    """Tags every run carries: git commit, profile, DVC stage, DVC experiment name (if any)."""
    tags = {
        "git_commit": git_commit(),
        "profile": profile,
        "dvc_stage": stage,
        "dvc_exp_name": os.environ.get("DVC_EXP_NAME", ""),
        "pipeline_run": os.environ.get("TRAFFICTWIN_PIPELINE_RUN", ""),
    }
    if extra:
        tags.update({k: str(v) for k, v in extra.items()})
    return tags


@contextmanager
def start_run(
    experiment: str,
    run_name: str,
    *,
    profile: str,
    stage: str,
    tags: Mapping[str, Any] | None = None,
    params: Mapping[str, Any] | None = None,
) -> Iterator[Any]:
    """Start an MLflow run in ``experiment`` with the project's tags and (once) ``params``."""
    import mlflow

    setup()
    mlflow.set_experiment(experiment)
    with mlflow.start_run(run_name=run_name, tags=base_tags(profile, stage, tags)) as run:
        if params:
            log_params(params)
        yield run


def log_params(params: Mapping[str, Any]) -> None:
    """Log params in batches (MLflow caps one call at 100), values stringified to 500 chars."""
    import mlflow

    items = [(k, str(v)[:500]) for k, v in params.items()]
    for i in range(0, len(items), 100):
        mlflow.log_params(dict(items[i : i + 100]))
