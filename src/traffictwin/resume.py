"""Resuming a killed training run where it stopped, bit for bit.

A training function given a *resume folder* (outside every DVC output; the workflow passes
``.cache/traffictwin/resume/<stage>``) keeps there:

- ``last.ckpt`` — Lightning's full training state (weights, optimiser, LR scheduler, loops,
  callbacks: best-checkpoint bookkeeping, early stopping, the metric history) written by
  :class:`ResumeCheckpoint` at the start of every epoch after the first, plus every random
  state the next epoch draws from: torch / numpy / python global RNGs and each
  ``torch.Generator`` of the LightningModule (augmentation) and of the training DataLoader
  (sampler order);
- the best-epoch checkpoint (``best/best.ckpt``: the ModelCheckpoint folder of
  :func:`traffictwin.trainer.fit_run`, a subfolder that only the run writes: absent when a run
  starts afresh, so Lightning finds it empty, and restored with the rest when it resumes);
- ``resume.json`` — the fingerprint of everything that determines the run (config, data
  manifest hash, the library's source) and the MLflow run id.

:func:`prepare` returns the checkpoint to resume from only when ``resume.json``'s fingerprint
equals the new run's (else it empties the folder: a changed config or dataset starts afresh),
and :func:`finish` removes the folder once the outputs are written.

Why at the start of an epoch, with the RNG states restored by the callback there: a checkpoint
taken at the *end* of an epoch (ModelCheckpoint's ``save_last``) is written before Lightning
steps a ``ReduceLROnPlateau`` scheduler, and Lightning does not step it again after a restart,
and it holds the random states of a moment that the resumed run reaches at another point of
its own start-up (the module's ``on_train_start`` re-seeds the augmentation generator, the
loader is built anew). Saved and restored at the same hook, the resumed run continues from the
state the uninterrupted run had there, so the weights come out identical
(``tests/test_resume.py``).

A kill during epoch ``k`` redoes epoch ``k`` from its start. Metrics of that partial epoch that
had already reached MLflow are logged again at the same steps (same values).
"""

from __future__ import annotations

import hashlib
import json
import os
import random
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from lightning.pytorch.callbacks import Callback

from traffictwin.io.atomic import write_json_atomic

LAST = "last.ckpt"
STATE = "resume.json"
FORMAT = "traffictwin-resume/1"


def source_digest() -> str:
    """SHA-256 over the traffictwin package's ``.py`` files (relative path + bytes): a resumed
    run must be trained by the same code."""
    package = Path(__file__).resolve().parent
    h = hashlib.sha256()
    for p in sorted(package.rglob("*.py")):
        h.update(p.relative_to(package).as_posix().encode() + b"\0" + p.read_bytes() + b"\0")
    return h.hexdigest()


def fingerprint(config: Mapping[str, Any]) -> str:
    """SHA-256 of ``config`` (JSON, sorted keys; anything not JSON by ``str``) and :func:`source_digest`."""
    text = json.dumps(dict(config), sort_keys=True, default=str)
    return hashlib.sha256(f"{FORMAT}\n{text}\n{source_digest()}".encode()).hexdigest()


def prepare(
    folder: str | Path, fp: str, *, clear: bool = True
) -> tuple[Path | None, dict[str, Any]]:
    """``(last.ckpt to resume from or None, resume.json content)`` for a run of fingerprint ``fp``.

    A folder whose ``resume.json`` has another fingerprint (or none, or is unreadable) is emptied
    and gets a fresh ``resume.json``; the run then starts from scratch. ``clear=False`` (DDP
    ranks other than zero) only reads.
    """
    folder = Path(folder)
    try:
        state = json.loads((folder / STATE).read_text())
    except (OSError, json.JSONDecodeError):
        state = None
    if isinstance(state, dict) and state.get("fingerprint") == fp and (folder / LAST).is_file():
        return folder / LAST, state
    if not clear:
        return None, {}
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    state = {"format": FORMAT, "fingerprint": fp}
    write_json_atomic(folder / STATE, state)
    return None, state


def record(folder: str | Path, **values: Any) -> None:
    """Add ``values`` (e.g. the MLflow run id) to the folder's ``resume.json``."""
    path = Path(folder) / STATE
    state = json.loads(path.read_text())
    state.update(values)
    write_json_atomic(path, state)


def finish(folder: str | Path | None) -> None:
    """Remove the resume folder (after the run's outputs were written)."""
    if folder is not None and Path(folder).exists():
        shutil.rmtree(folder)


def _generators(trainer: Any, pl_module: Any) -> dict[str, torch.Generator]:
    """Every ``torch.Generator`` the next training epoch draws from, by a stable name: the
    module's attributes and the training loader's (its own, its sampler's, a wrapped sampler's)."""
    found: dict[str, torch.Generator] = {}
    for k, v in sorted(vars(pl_module).items()):
        if isinstance(v, torch.Generator):
            found[f"module.{k}"] = v
    for i, dl in enumerate(_train_loaders(trainer)):
        sampler = getattr(dl, "sampler", None)
        batch_sampler = getattr(dl, "batch_sampler", None)
        for name, obj in (
            ("loader", dl),
            ("sampler", sampler),
            ("sampler.base", getattr(sampler, "base", None)),
            ("batch_sampler.sampler", getattr(batch_sampler, "sampler", None)),
        ):
            g = getattr(obj, "generator", None)
            if isinstance(g, torch.Generator):
                found[f"train{i}.{name}"] = g
    return found


class ResumeCheckpoint(Callback):
    """Writes ``<folder>/last.ckpt`` at the start of every epoch after the first (atomically) and
    carries the random states in it; after ``trainer.fit(ckpt_path=...)`` restores them at the
    same hook, before the epoch draws anything. See the module docstring."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        self._restore: dict[str, Any] | None = None
        self._saving = False
        self._module: Any = None
        self._trainer: Any = None

    @property
    def state_key(self) -> str:
        return "traffictwin.ResumeCheckpoint"

    def setup(self, trainer: Any, pl_module: Any, stage: str) -> None:
        self._trainer, self._module = trainer, pl_module

    def state_dict(self) -> dict[str, Any]:
        """The random states now (called while :meth:`on_train_epoch_start` saves)."""
        if self._trainer is None:
            return {}
        np_state = np.random.get_state()
        return {
            "torch": torch.get_rng_state(),
            "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
            "numpy": [np_state[0], torch.from_numpy(np_state[1].astype(np.int64)), *np_state[2:]],
            "python": random.getstate(),
            "generators": {
                k: g.get_state() for k, g in _generators(self._trainer, self._module).items()
            },
        }

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self._restore = dict(state_dict) or None

    def on_train_epoch_start(self, trainer: Any, pl_module: Any) -> None:
        if self._restore is not None:
            self._apply(trainer, pl_module, self._restore)
            self._restore = None
            return
        if trainer.current_epoch == 0 or trainer.sanity_checking:
            return
        tmp = self.folder / f".{LAST}.tmp"
        self._saving = True
        try:
            # the full training state (optimiser, schedulers, callbacks, loops), said explicitly:
            # left unset, Lightning logs "`weights_only` was not set, defaulting to `False`" at
            # every epoch. (The flag chooses what is *saved*; the file holds tensors and plain
            # containers only and is read back with torch.load(weights_only=True): fit_run.)
            trainer.save_checkpoint(tmp, weights_only=False)
        finally:
            self._saving = False
        if trainer.is_global_zero:
            os.replace(tmp, self.folder / LAST)

    def on_save_checkpoint(self, trainer: Any, pl_module: Any, checkpoint: dict[str, Any]) -> None:
        """``last.ckpt`` records the previous epoch as fully done: Lightning has already counted
        the new epoch as *ready* when ``on_train_epoch_start`` runs; with that count a restart
        would take the epoch for finished and skip its batches."""
        if not self._saving:
            return
        progress = checkpoint["loops"]["fit_loop"]["epoch_progress"]
        for part in ("total", "current"):
            p = progress[part]
            if not p["ready"] == p["started"] + 1 == p["processed"] + 1 == p["completed"] + 1:
                raise RuntimeError(f"resume: unexpected epoch progress at epoch start: {progress}")
            p["ready"] = p["completed"]

    @staticmethod
    def _apply(trainer: Any, pl_module: Any, s: Mapping[str, Any]) -> None:
        torch.set_rng_state(s["torch"])
        if s.get("cuda") and torch.cuda.is_available():
            torch.cuda.set_rng_state_all(s["cuda"])
        kind, keys, *rest = s["numpy"]
        np.random.set_state((kind, keys.numpy().astype(np.uint32), *rest))
        py = s["python"]
        random.setstate((py[0], tuple(py[1]), py[2]))
        now = _generators(trainer, pl_module)
        missing = sorted(set(s["generators"]) - set(now))
        if missing:
            raise RuntimeError(
                f"resume: random generator(s) {missing} of the checkpoint are not in this run"
            )
        for k, state in s["generators"].items():
            now[k].set_state(state)
        _replay_loader_draws(trainer)


def _train_loaders(trainer: Any) -> list[Any]:
    loaders = trainer.train_dataloader
    if loaders is None:
        return []
    return list(loaders) if isinstance(loaders, (list, tuple)) else [loaders]


def _replay_loader_draws(trainer: Any) -> None:
    """Redo the draw a DataLoader iterator makes when it is created (its base seed: one int64 from
    the loader's generator, else from torch's global RNG) if Lightning created this epoch's
    iterator before the random states were restored (it does so for the first epoch of a
    ``fit`` call). An uninterrupted run creates the iterator after ``on_train_epoch_start``, where
    the states were saved, so without this the resumed run's dropout masks would differ. A loader
    with persistent workers makes no draw in later epochs (its iterator is reused), so none is
    redone."""
    from torch.utils.data import DataLoader

    combined = getattr(trainer.fit_loop, "_combined_loader", None)
    if combined is None or getattr(combined, "_iterator", None) is None:
        return
    for dl in _train_loaders(trainer):
        if isinstance(dl, DataLoader) and not (dl.num_workers > 0 and dl.persistent_workers):
            torch.empty((), dtype=torch.int64).random_(generator=dl.generator)


class Session:
    """One training run's use of a resume folder (``folder=None``: no resuming, a temp folder).

    ``resume_from``: the ``last.ckpt`` to pass to ``trainer.fit(ckpt_path=...)`` (``None``: start
    afresh); :meth:`run_id`: the MLflow run to continue; :meth:`workdir`: the run's working
    folder, where ``fit_run`` keeps the best-epoch checkpoint (in its ``best/`` subfolder; the
    resume folder, so a resumed run still has it); :meth:`callbacks`:
    :class:`ResumeCheckpoint`; :meth:`started` records the MLflow run; :meth:`finish` removes the
    folder after the outputs are written.
    """

    def __init__(self, folder: str | Path | None, config: Mapping[str, Any]) -> None:
        from traffictwin.trainer import global_rank

        self.folder = Path(folder) if folder is not None else None
        self.resume_from: Path | None = None
        self.state: dict[str, Any] = {}
        if self.folder is not None:
            self.resume_from, self.state = prepare(
                self.folder, fingerprint(config), clear=global_rank() == 0
            )

    def run_id(self) -> str | None:
        return self.state.get("mlflow_run_id") if self.resume_from is not None else None

    def workdir(self, prefix: str) -> Any:
        """Context manager giving the checkpoint folder (the resume folder or a temp folder)."""
        import tempfile
        from contextlib import nullcontext

        if self.folder is not None:
            return nullcontext(str(self.folder))
        return tempfile.TemporaryDirectory(prefix=prefix)

    def callbacks(self) -> list[Any]:
        return [ResumeCheckpoint(self.folder)] if self.folder is not None else []

    def started(self, run: Any) -> None:
        if run is not None and self.folder is not None:
            record(self.folder, mlflow_run_id=run.info.run_id)

    def finish(self) -> None:
        finish(self.folder)
