"""MLflow tracking: where runs go and how they are tagged (docs/design.md "Tracking").

Where runs go
    ``MLFLOW_TRACKING_URI`` if set (a server for a team; always wins), else the SQLite file
    ``mlflow.db`` at the *repository* root as an absolute path. The repository root is
    (first that applies) ``TRAFFICTWIN_REPO_ROOT``; ``DVC_ROOT``; the nearest folder above the
    working directory with ``dvc.yaml`` or ``.git``.

    ``DVC_ROOT`` is what makes queued experiments work: ``dvc exp run --queue`` / ``--temp`` /
    ``--run-all`` run the pipeline in a temp copy under ``.dvc/tmp/exps/…``, where walking up
    from the working directory would find the *copy* (and its database is deleted with it).
    DVC sets ``DVC_ROOT`` for every stage command; for queued and temp runs it deliberately
    points to the parent repository, not the executor's temp folder
    (``dvc/repo/experiments/queue/base.py``: "Override DVC_ROOT env var to point to the parent
    DVC repo root"; documented at https://dvc.org/doc/user-guide/env).

    Experiments this module creates get their artifact location beside the SQLite database
    (``<db folder>/mlartifacts/<experiment>``), again so that a run started inside a temp copy
    does not store checkpoints and models in a folder that DVC deletes afterwards (MLflow's
    default is ``./mlruns`` relative to the working directory of whoever creates the experiment).

How runs are tagged (:func:`base_tags`)
    ``git_commit`` (the experiment's baseline commit ``DVC_EXP_BASELINE_REV`` inside a DVC
    experiment, else ``TRAFFICTWIN_GIT_COMMIT``), ``profile``, ``dvc_stage``, ``dvc_exp_name``
    (``DVC_EXP_NAME``, set by ``dvc exp run``), ``params_hash`` (``TRAFFICTWIN_PARAMS_HASH``:
    SHA-256 of the params.yaml the stage runs with) and ``pipeline_run``:
    ``TRAFFICTWIN_PIPELINE_RUN`` if set, else derived from the git commit, the params hash and
    the DVC experiment name, so every stage of one ``dvc repro`` / ``dvc exp run`` shares it and
    ``traffictwin runs compare`` can group by it.

    The data version is the tag :data:`DATA_TAG` (``data_manifest_hash``: SHA-256 of the
    dataset's ``manifest.json``, which records the SHA-256 of every shard) on every training
    run, fusion and risk alike; :func:`log_dataset` also records the dataset folder as an
    MLflow dataset input (``mlflow.log_input``) carrying the same hash.

    Run names and descriptions (:func:`run_label`) say what the run is: the stage's name, the DVC
    experiment's name and the parameters that differ from the committed params.yaml
    (``TRAFFICTWIN_PARAMS_OVERRIDES``, JSON ``{key: [committed, now]}``), e.g.
    ``fusion-network [lr-low: fusion_model.optim.lr=0.002]``.

    Provenance comes in through the environment: the workflow layer computes the commit, the
    params hash and the overrides (``pipelines/_provenance.py``) and exports them before a stage
    runs. This module
    runs no git and reads no params file; a variable that is not set reads as ``""``.

How runs end (:func:`start_run`)
    ``FINISHED`` when the block completes, ``FAILED`` when it raises, ``KILLED`` on SIGTERM or
    SIGINT: for the run's duration both signals raise :class:`RunInterrupted` in the main thread
    (once; a repeated signal during the clean-up is ignored), so the stack unwinds (Lightning
    tears its trainer down), the run is ended with that status and the previous handlers are
    restored. A SIGKILL cannot be handled: such a run stays ``RUNNING``.
"""

from __future__ import annotations

import hashlib
import os
import signal
import threading
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

ENV_URI = "MLFLOW_TRACKING_URI"
ENV_REPO = "TRAFFICTWIN_REPO_ROOT"
ENV_PIPELINE_RUN = "TRAFFICTWIN_PIPELINE_RUN"
ENV_DVC_ROOT = "DVC_ROOT"
ENV_DVC_EXP_NAME = "DVC_EXP_NAME"
ENV_DVC_BASELINE = "DVC_EXP_BASELINE_REV"
ENV_GIT_COMMIT = "TRAFFICTWIN_GIT_COMMIT"
ENV_PARAMS_HASH = "TRAFFICTWIN_PARAMS_HASH"
ENV_PARAMS_OVERRIDES = "TRAFFICTWIN_PARAMS_OVERRIDES"
#: how many overrides a run's name lists (the rest: "+N more"; the description lists them all)
NAME_OVERRIDES = 3
ARTIFACTS_DIR = "mlartifacts"

DATA_TAG = "data_manifest_hash"  # the one data-version tag name (fusion, registration, risk)
DATASET_DIGEST_CHARS = 16  # MLflow's dataset digest column holds at most 36 characters

TAG_KEYS = ("git_commit", "profile", "dvc_stage", "dvc_exp_name", "params_hash", "pipeline_run")


def work_root(start: str | Path | None = None) -> Path:
    """The checkout this process runs in: nearest folder at/above ``start`` (default cwd) with dvc.yaml or .git.

    Inside a queued DVC experiment this is the temp copy (where params.yaml and the data are).
    """
    here = Path(start or os.getcwd()).resolve()
    for p in (here, *here.parents):
        if (p / "dvc.yaml").exists() or (p / ".git").exists():
            return p
    return here


def repo_root(start: str | Path | None = None) -> Path:
    """The repository whose ``mlflow.db`` collects the runs.

    ``TRAFFICTWIN_REPO_ROOT`` if set, else ``DVC_ROOT`` (set by DVC for stage commands; the
    parent repository even in queued/temp experiments), else :func:`work_root`.
    """
    for var in (ENV_REPO, ENV_DVC_ROOT):
        env = os.environ.get(var)
        if env:
            return Path(env).resolve()
    return work_root(start)


def tracking_uri(root: str | Path | None = None) -> str:
    """``MLFLOW_TRACKING_URI`` if set, else ``sqlite:////abs/path/mlflow.db`` at :func:`repo_root`."""
    env = os.environ.get(ENV_URI)
    if env:
        return env
    db = (Path(root) if root else repo_root()).resolve() / "mlflow.db"
    return f"sqlite:///{db}"


def sqlite_path(uri: str) -> Path | None:
    """The database file of a ``sqlite:///`` URI (``None`` for any other scheme)."""
    if not uri.startswith("sqlite:///"):
        return None
    return Path(uri.removeprefix("sqlite:///"))


def artifact_location(experiment: str, uri: str) -> str | None:
    """Artifact folder for a new ``experiment`` on a local SQLite store: beside the database file.

    ``None`` (let the server decide) for non-SQLite URIs.
    """
    db = sqlite_path(uri)
    if db is None:
        return None
    return (db.parent.resolve() / ARTIFACTS_DIR / experiment).as_uri()


def git_commit(root: str | Path | None = None) -> str:
    """The git commit runs belong to: ``DVC_EXP_BASELINE_REV`` inside a DVC experiment (a queued
    experiment's temp copy has its own throw-away HEAD), else ``TRAFFICTWIN_GIT_COMMIT``; ``""``
    if neither is set.

    ``root`` is ignored (kept for callers that still pass the checkout; the workflow layer
    resolves the commit of its checkout).
    """
    return os.environ.get(ENV_DVC_BASELINE) or os.environ.get(ENV_GIT_COMMIT, "")


def params_hash() -> str:
    """SHA-256 (hex) of the params.yaml the stage runs with: ``TRAFFICTWIN_PARAMS_HASH``, ``""`` if unset.

    Used as an identity only: this module does not interpret the parameters.
    """
    return os.environ.get(ENV_PARAMS_HASH, "")


def params_overrides() -> dict[str, list[str | None]]:
    """``{key: [committed, now]}`` from ``TRAFFICTWIN_PARAMS_OVERRIDES`` (``{}`` if unset or not JSON)."""
    import json

    try:
        data = json.loads(os.environ.get(ENV_PARAMS_OVERRIDES, "") or "{}")
    except ValueError:
        return {}
    return data if isinstance(data, dict) else {}


def run_label(
    run_name: str,
    stage: str,
    profile: str,
    params: Mapping[str, Any] | None = None,
) -> tuple[str, str]:
    """``(name, description)`` of a run: ``run_name`` plus, in brackets, the DVC experiment's
    name (``DVC_EXP_NAME``) and up to :data:`NAME_OVERRIDES` of the parameters that differ
    from the committed params.yaml (:func:`params_overrides`; only those among the run's
    ``params`` when it logs any of them; another profile is the one override ``profile``); the
    description names the stage, the profile, the
    experiment and every override with its committed value."""
    exp = os.environ.get(ENV_DVC_EXP_NAME, "")
    changed = params_overrides()
    if params and any(k in params for k in changed):
        changed = {k: v for k, v in changed.items() if k in params or k == "profile"}
    pairs = [f"{k}={v[1]}" for k, v in changed.items()]
    shown = ", ".join(pairs[:NAME_OVERRIDES])
    if len(pairs) > NAME_OVERRIDES:
        shown += f" +{len(pairs) - NAME_OVERRIDES} more"
    inner = ": ".join(x for x in (exp, shown) if x)
    name = f"{run_name} [{inner}]" if inner else run_name
    note = f"DVC stage `{stage}` on the `{profile}` profile"
    if exp:
        note += f", DVC experiment `{exp}`"
    if changed:
        note += "; changed from the committed params.yaml: " + ", ".join(
            f"`{k}` = {v[1]} (was {v[0]})" for k, v in changed.items()
        )
    return name, note


def pipeline_run_id(
    commit: str | None = None, phash: str | None = None, exp_name: str | None = None
) -> str:
    """Id shared by all stages of one pipeline run.

    ``TRAFFICTWIN_PIPELINE_RUN`` if set; else ``<commit[:8]>-<h[:8]>`` where ``h`` hashes the
    params hash and the DVC experiment name (so two experiments of one commit differ, and
    every stage of one ``dvc repro`` -- same commit, same params.yaml -- agrees).
    """
    env = os.environ.get(ENV_PIPELINE_RUN)
    if env:
        return env
    commit = git_commit() if commit is None else commit
    phash = params_hash() if phash is None else phash
    exp_name = os.environ.get(ENV_DVC_EXP_NAME, "") if exp_name is None else exp_name
    h = hashlib.sha256(f"{phash}\n{exp_name}".encode()).hexdigest()
    return f"{commit[:8]}-{h[:8]}"


def setup(root: str | Path | None = None) -> str:
    """Point MLflow at :func:`tracking_uri`; returns the URI."""
    import mlflow

    uri = tracking_uri(root)
    mlflow.set_tracking_uri(uri)
    return uri


#: what each MLflow experiment holds: its description in the MLflow UI (``mlflow.note.content``)
EXPERIMENT_DESCRIPTIONS = {
    "fusion": "Evidential grid fusion networks (DeepLabV3+ on two prealigned maps), one run per "
    "training stage (train_fusion, its variants); evaluate_fusion adds test/... metrics.",
    "registration": "Learned map registration (relative pose of map 2 to map 1), one run per "
    "train_registration.",
    "risk": "Risk predictors from stereo: DAVE-2 networks per variant and seed (train_risk), the "
    "shipped predictor chosen on validation (select_risk, run risk-shipped).",
}
NOTE_TAG = "mlflow.note.content"  # the MLflow UI's description of an experiment or run
#: the experiment tag by which the MLflow UI (3.x) picks an experiment's first page: without it
#: the UI may open on its GenAI overview; model training opens on the runs table
KIND_TAG, KIND = "mlflow.experimentKind", "custom_model_development"


def ensure_experiment(name: str, uri: str | None = None) -> str:
    """Id of experiment ``name``, creating it (artifacts beside a SQLite db, its description from
    :data:`EXPERIMENT_DESCRIPTIONS`, :data:`KIND_TAG` = model training, so the UI opens on the
    runs table) if missing; makes it active."""
    import mlflow
    from mlflow.exceptions import MlflowException

    uri = uri or mlflow.get_tracking_uri()
    exp = mlflow.get_experiment_by_name(name)
    desc = EXPERIMENT_DESCRIPTIONS.get(name)
    tags = {KIND_TAG: KIND, **({NOTE_TAG: desc} if desc else {})}
    if exp is None:
        try:
            exp_id = mlflow.create_experiment(
                name, artifact_location=artifact_location(name, uri), tags=tags
            )
        except MlflowException:  # created concurrently by another stage
            exp = mlflow.get_experiment_by_name(name)
            if exp is None:
                raise
            exp_id = exp.experiment_id
    else:
        exp_id = exp.experiment_id
        for key, value in tags.items():
            if (exp.tags or {}).get(key) != value:
                mlflow.MlflowClient(uri).set_experiment_tag(exp_id, key, value)
    mlflow.set_experiment(experiment_id=exp_id)
    retire_empty_default(uri)
    return exp_id


def retire_empty_default(uri: str) -> bool:
    """Mark MLflow's ``Default`` experiment (id 0, which every new SQLite store gets from MLflow
    itself) deleted while it holds no run, so the UI opens on the project's experiments; only on
    a local SQLite store (a server's experiments are not this project's to tidy). Deleted, it is
    not created again (``mlflow gc`` would purge it; MLflow then creates it anew). Returns
    whether it was deleted now."""
    from mlflow.entities import ViewType
    from mlflow.exceptions import MlflowException
    from mlflow.tracking import MlflowClient

    if sqlite_path(uri) is None:
        return False
    client = MlflowClient(uri)
    try:
        default = client.get_experiment("0")
    except MlflowException:
        return False
    if default.name != "Default" or default.lifecycle_stage != "active":
        return False
    if client.search_runs(["0"], max_results=1, run_view_type=ViewType.ALL):
        return False
    client.delete_experiment("0")
    return True


def base_tags(profile: str, stage: str, extra: Mapping[str, Any] | None = None) -> dict[str, str]:
    """Tags every run carries (see the module docstring); ``extra`` adds or overrides."""
    commit = git_commit()
    phash = params_hash()
    exp_name = os.environ.get(ENV_DVC_EXP_NAME, "")
    tags = {
        "git_commit": commit,
        "profile": profile,
        "dvc_stage": stage,
        "dvc_exp_name": exp_name,
        "params_hash": phash,
        "pipeline_run": pipeline_run_id(commit, phash, exp_name),
    }
    if extra:
        tags.update({k: str(v) for k, v in extra.items()})
    return tags


class RunInterrupted(BaseException):
    """SIGTERM or SIGINT arrived during a tracked run (raised by the handlers of :func:`interruptible`).

    A ``BaseException`` like ``KeyboardInterrupt``, so ``except Exception`` blocks let it pass;
    ``signum`` is the signal's number (a stage exits with 128 + signum).
    """

    def __init__(self, signum: int) -> None:
        self.signum = int(signum)
        super().__init__(f"received {signal.Signals(self.signum).name}")


@contextmanager
def interruptible(
    signals: tuple[int, ...] = (signal.SIGTERM, signal.SIGINT),
) -> Iterator[list[int]]:
    """While inside, each of ``signals`` raises :class:`RunInterrupted` (the first one only; later
    ones are noted and ignored, so clean-up is not interrupted). Yields the list of the signals
    received. The previous handlers are restored on exit. Outside the main thread (where Python
    cannot install handlers) nothing is installed."""
    received: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield received
        return

    def handler(signum: int, frame: Any) -> None:
        received.append(signum)
        if len(received) == 1:
            raise RunInterrupted(signum)

    previous = {s: signal.getsignal(s) for s in signals}
    for s in signals:
        signal.signal(s, handler)
    try:
        yield received
    finally:
        for s, h in previous.items():
            signal.signal(s, h if h is not None else signal.SIG_DFL)


def end_status(exc: BaseException | None, received: list[int] | None = None) -> str:
    """The MLflow status a run ends with: ``FINISHED`` (no exception), ``KILLED`` (a signal was
    received, or the exception is :class:`RunInterrupted` / ``KeyboardInterrupt``), else ``FAILED``."""
    if exc is None:
        return "FINISHED"
    if received or isinstance(exc, (RunInterrupted, KeyboardInterrupt)):
        return "KILLED"
    return "FAILED"


@contextmanager
def start_run(
    experiment: str,
    run_name: str,
    *,
    profile: str,
    stage: str,
    tags: Mapping[str, Any] | None = None,
    params: Mapping[str, Any] | None = None,
    run_id: str | None = None,
) -> Iterator[Any]:
    """Start an MLflow run in ``experiment`` with the project's tags and (once) ``params``; it
    ends ``FINISHED``, ``FAILED`` on an exception, ``KILLED`` on SIGTERM/SIGINT (module docstring).

    ``run_id``: continue that run instead (a resumed training; ignored when the store has no
    such run in ``experiment``, e.g. another tracking URI): the same tags and params are set again.
    """
    import mlflow
    from mlflow.exceptions import MlflowException

    uri = setup()
    exp_id = ensure_experiment(experiment, uri)
    if run_id is not None:
        try:
            if mlflow.get_run(run_id).info.experiment_id != exp_id:
                run_id = None
        except MlflowException:
            run_id = None
    with interruptible() as received:
        name, note = run_label(run_name, stage, profile, params)
        run = mlflow.start_run(
            run_id=run_id,
            run_name=None if run_id else name,
            tags={NOTE_TAG: note, **base_tags(profile, stage, tags)},
        )
        try:
            if params:
                log_params(params)
            yield run
        except BaseException as exc:
            mlflow.end_run(end_status(exc, received))
            raise
        mlflow.end_run(end_status(None))


def log_params(params: Mapping[str, Any]) -> None:
    """Log params in batches (MLflow caps one call at 100), values stringified to 500 chars."""
    import mlflow

    items = [(k, str(v)[:500]) for k, v in params.items()]
    for i in range(0, len(items), 100):
        mlflow.log_params(dict(items[i : i + 100]))


def log_dataset(
    path: str | Path,
    manifest_hash: str,
    *,
    name: str | None = None,
    context: str = "training",
) -> None:
    """Record the dataset folder ``path`` as an input of the active run (``mlflow.log_input``).

    A metadata-only dataset (nothing is uploaded): source = the folder, digest = the first
    :data:`DATASET_DIGEST_CHARS` characters of ``manifest_hash``, and the full hash as the input
    tag :data:`DATA_TAG`. ``name`` defaults to the folder's last two path parts
    (``prealigned/A``).
    """
    import warnings

    import mlflow
    from mlflow.data.dataset_source_registry import resolve_dataset_source
    from mlflow.data.meta_dataset import MetaDataset

    folder = Path(path).resolve()
    with warnings.catch_warnings():  # MLflow registers the local source twice and says so
        warnings.simplefilter("ignore", UserWarning)
        source = resolve_dataset_source(str(folder))
    ds = MetaDataset(
        source,
        name=name or "/".join(folder.parts[-2:]),
        digest=manifest_hash[:DATASET_DIGEST_CHARS],
    )
    mlflow.log_input(ds, context=context, tags={DATA_TAG: manifest_hash})
