"""Shared helpers for stage entry points (the workflow layer; no algorithms here)."""

from __future__ import annotations

import hashlib
import json
import logging
import multiprocessing as mp
import os
import sys
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from datetime import UTC
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from traffictwin.config import load_params
from traffictwin.io.atomic import write_json_atomic

from ._paths import PARAMS, ROOT, run_record_file  # noqa: F401  (ROOT re-exported for stages)


def params(path: str | Path | None = None) -> DictConfig:
    """params.yaml of the repository this stage runs in."""
    return load_params(path or PARAMS)


def setup_logging() -> logging.Logger:
    """The stage's logger; piped (``dvc repro | tee``, CI), MLflow draws no artifact progress
    bars (``MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR=false`` unless set), as tqdm draws none."""
    if not (sys.stderr is not None and sys.stderr.isatty()):
        os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")
    logging.basicConfig(
        level=os.environ.get("TRAFFICTWIN_LOGLEVEL", "INFO"),
        format="%(asctime)s %(name)s %(message)s",
    )
    return logging.getLogger("traffictwin")


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``; ``platform`` elsewhere)."""
    import platform

    try:
        with open("/proc/cpuinfo") as fh:
            names = [ln.split(":", 1)[1].strip() for ln in fh if ln.startswith("model name")]
        if names:
            return names[0]
    except OSError:
        pass
    return platform.processor() or platform.machine()


def load_average() -> list[float] | None:
    """The machine's 1, 5 and 15 minute load averages (runnable processes), or None."""
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


@contextmanager
def stage_timer(stage: str) -> Iterator[dict[str, Any]]:
    """Time ``stage``; yields its run record, a dict the stage fills with what differs between
    identical runs (MLflow run id and model URI, training seconds, ms per pair, ...).

    On success the record is written to ``reports/timings/<stage>.json`` (:func:`run_record_file`)
    with ``stage``, ``seconds`` (wall time, s), ``started`` / ``finished`` (UTC) and the machine
    it ran on, so a wall time can be judged: ``machine.cpu`` (model), ``machine.cpu_count``, ``machine.load_start`` /
    ``machine.load_end`` (1, 5, 15 minute load averages at start and end: a load above the core
    count means the stage shared the machine). Run records are committed to git but are never
    DVC outputs or dependencies, so an identical rerun leaves ``dvc.lock`` unchanged; nothing a
    DVC stage writes as an output may hold such values. A failed stage writes no record.
    """
    record: dict[str, Any] = {}
    machine = {"cpu": cpu_model(), "cpu_count": os.cpu_count(), "load_start": load_average()}
    started = _utc_now()
    t0 = time.perf_counter()
    yield record
    machine["load_end"] = load_average()
    write_json_atomic(
        run_record_file(stage),
        {
            **record,
            "stage": stage,
            "seconds": round(time.perf_counter() - t0, 2),
            "started": started,
            "finished": _utc_now(),
            "machine": machine,
        },
    )


def _utc_now() -> str:
    """The time now, UTC, ISO 8601 to the second (the run record's ``started`` / ``finished``:
    the wall time of a whole ``dvc repro`` is the span of its stages' records)."""
    from datetime import datetime

    return datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def training_record(res: Any, checkpoint: str | Path) -> dict[str, Any]:
    """Run-record fields of a training stage from its fit result: ``run_id`` / ``model_uri`` (MLflow;
    None without tracking), ``train_seconds`` (s), ``train_samples_per_s`` (where the trainer
    reports it) and ``model_sha256`` of the published ``checkpoint``, which ties the record to
    the model it describes (the promotion gate checks it)."""
    seconds = getattr(res, "train_seconds", None)
    if seconds is None:
        seconds = getattr(res, "seconds", None)
    out: dict[str, Any] = {
        "run_id": getattr(res, "run_id", None),
        "model_uri": getattr(res, "model_uri", None),
        "train_seconds": None if seconds is None else round(float(seconds), 2),
    }
    if getattr(res, "samples_per_s", None) is not None:
        out["train_samples_per_s"] = res.samples_per_s
    if getattr(res, "precision", None) is not None:
        out["precision"] = res.precision  # the trainer's resolved precision (bf16-mixed / 32-true)
    with open(checkpoint, "rb") as fh:
        out["model_sha256"] = hashlib.file_digest(fh, "sha256").hexdigest()
    return out


def read_run_record(stage: str) -> dict[str, Any]:
    """The run record of ``stage`` (see :func:`stage_timer`); ``{}`` when the stage has none yet.

    A record that is not a JSON object is a ValueError naming the file.
    """
    path = run_record_file(stage)
    if not path.exists():
        return {}
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: run record is not valid JSON ({exc})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: run record must be a JSON object, got {type(data).__name__}")
    return data


def error_line(exc: BaseException) -> str:
    """``exc`` as one line: its class name and message, the message's lines joined with " | ".

    Library errors name the file, field or parameter themselves; foreign ones (numpy, OpenCV,
    Lightning, OmegaConf) get at least their class, so "high - low < 0" reads as a ValueError.
    """
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    msg = " | ".join(lines)
    name = type(exc).__name__
    return f"{name}: {msg}" if msg else name


def stage_errors() -> tuple[type[BaseException], ...]:
    """The failure types that mean "the input or the settings are wrong" (each ends a stage with
    one line): the library's own (ValueError: ConfigError; RuntimeError: DatasetError, model
    loading errors), file system errors, bad config keys (KeyError, OmegaConf and Hydra errors),
    numerical blow-ups (FloatingPointError, incl. :class:`traffictwin.trainer.TrainingDiverged`),
    Lightning's MisconfigurationException (e.g. an accelerator this machine lacks) and OpenCV's
    ``cv2.error``. Anything else (TypeError, AttributeError, ...) is a bug and keeps its traceback.

    Python evaluates this on every exception that reaches :func:`run_stage` (an argparse usage
    error too): Lightning's exception is added only where Lightning is loaded (elsewhere none can
    have been raised), so a stage that trains nothing does not import it (~8 s) to print one line."""
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    types: list[type[BaseException]] = [
        ValueError,
        RuntimeError,
        OSError,
        KeyError,
        FloatingPointError,
        OmegaConfBaseException,
        HydraException,
    ]
    lightning = sys.modules.get("lightning.fabric.utilities.exceptions")
    if lightning is not None:
        types.append(lightning.MisconfigurationException)
    try:
        import cv2

        types.append(cv2.error)
    except ImportError:  # pragma: no cover - OpenCV is a dependency
        pass
    return tuple(types)


def run_stage(main: Callable[[], object], name: str) -> None:
    """Run a stage's ``main``; bad input ends with one line ``<name>: error: <class>: <message>``
    (:func:`error_line`) and exit 2; a SIGTERM/SIGINT during a tracked MLflow run (which then
    ends KILLED, see :func:`traffictwin.mlops.tracking.start_run`) with one line and exit
    128 + the signal number; Ctrl-C elsewhere (``KeyboardInterrupt``) with one line and 130.

    The failure types caught are :func:`stage_errors`; library errors name the file, field or
    parameter themselves and a traceback would only bury that line. Set
    ``TRAFFICTWIN_TRACEBACK=1`` to see the traceback anyway.
    """
    from traffictwin.mlops.tracking import RunInterrupted

    from ._provenance import provenance_env

    os.environ.update(provenance_env())  # git commit + params hash for the MLflow tags
    try:
        main()
    except RunInterrupted as exc:
        if os.environ.get("TRAFFICTWIN_TRACEBACK"):
            raise
        print(f"{name}: interrupted: {exc}", file=sys.stderr)
        sys.exit(128 + exc.signum)
    except KeyboardInterrupt:
        if os.environ.get("TRAFFICTWIN_TRACEBACK"):
            raise
        print(f"{name}: interrupted (Ctrl-C)", file=sys.stderr)
        sys.exit(130)
    except stage_errors() as exc:
        if os.environ.get("TRAFFICTWIN_TRACEBACK"):
            raise
        print(f"{name}: error: {error_line(exc)}", file=sys.stderr)
        sys.exit(2)


# state of the shard workers: set once per process by :func:`map_shards`, read by a stage's work function
WORKER_STATE: dict[str, Any] = {}


def _set_worker_state(state: dict[str, Any]) -> None:
    """A pool worker's set-up: ``state`` into :data:`WORKER_STATE`; Ctrl-C (SIGINT, sent to the
    whole process group) is ignored, so the parent alone handles it and terminates the pool
    (no traceback per worker)."""
    import signal

    if mp.parent_process() is not None:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    WORKER_STATE.clear()
    WORKER_STATE.update(state)


def map_shards(
    work: Callable[[int], Any],
    indices: Iterable[int],
    *,
    workers: int,
    state: dict[str, Any],
    desc: str,
    unit: str = "shard",
    ordered: bool = False,
) -> Iterator[Any]:
    """Yield ``work(i)`` for every shard index, with a progress bar.

    ``workers > 1``: a fork pool of that many processes (results in completion order unless
    ``ordered``); otherwise in this process. Either way ``state`` is in :data:`WORKER_STATE`
    of the process that runs ``work``, so work functions take only the index (cheap to send).
    """
    from tqdm import tqdm

    idx = list(indices)
    if workers <= 1 or len(idx) <= 1:
        _set_worker_state(state)
        yield from tqdm(
            map(work, idx),
            total=len(idx),
            desc=desc,
            unit=unit,
            disable=True if os.environ.get("TQDM_DISABLE") else None,
        )
        return
    with mp.get_context("fork").Pool(
        min(workers, len(idx)), initializer=_set_worker_state, initargs=(state,)
    ) as pool:
        it = pool.imap(work, idx) if ordered else pool.imap_unordered(work, idx)
        yield from tqdm(
            it,
            total=len(idx),
            desc=desc,
            unit=unit,
            disable=True if os.environ.get("TQDM_DISABLE") else None,
        )
