"""Lightning + MLflow helpers shared by the fusion and risk trainers (docs/design.md "Tracking").

Stable API (the fusion and the risk stages both use it), re-exported here from the modules
:mod:`~traffictwin.trainer.settings` (where Lightning runs), :mod:`~traffictwin.trainer.sampling`
(DDP shares), :mod:`~traffictwin.trainer.callbacks`, :mod:`~traffictwin.trainer.tracking`
(MLflow), :mod:`~traffictwin.trainer.fit` (the driver) and :mod:`~traffictwin.trainer.publish`
(model files and result):

- :class:`TrainerSettings` — the ``trainer`` config group (accelerator, devices, num_nodes,
  strategy, precision, num_workers, optional deterministic / num_threads), validated once with
  :func:`traffictwin.config.typed` by :meth:`TrainerSettings.from_cfg`.
- :func:`seed_everything` — seeds python/numpy/torch (and dataloader workers).
- :func:`build_trainer` — a ``lightning.Trainer`` from the settings, with no Lightning logger
  (metrics go to MLflow through :class:`History`, which logs one value per epoch).
- :class:`NetModule` — the one trainer shape: LightningModule with an injected network and
  loss, Adam (+ optional plateau decay); the fusion and risk modules subclass it.
- :class:`RankShardSampler` / :func:`rank_layout` — under DDP, this rank's share of a
  sampler's indices, for the loaders the DataModules build themselves: training gets the
  same per-epoch draw split evenly over the ranks, evaluation every sample exactly once
  (Lightning's own DistributedSampler would repeat samples to even out the ranks).
- :func:`best_checkpoint` / :func:`early_stopping` — callbacks on a monitored metric.
- :class:`FiniteGuard` — the one finite-loss guard of every trainer (:func:`build_trainer` adds
  one when the caller gave none): a NaN/inf training loss or monitored metric stops the run with
  :class:`TrainingDiverged` naming the stage, epoch, step, learning rate and the parameter to lower.
- :class:`History` — the metric rows (per epoch, or per validation for the risk net's
  per-iteration curves), logged to the active MLflow run (rank zero only), written as CSV.
- :func:`mlflow_logger` / :func:`log_final_metrics` — Lightning's ``MLFlowLogger`` on the
  stage's MLflow run, through which :class:`History` and the final metrics are logged.
- :func:`global_rank` / :func:`tracked_run` — an MLflow run on rank zero only (under DDP the
  launcher re-runs the stage script in every rank; the other ranks get ``None``).
- :func:`log_checkpoint` / :func:`log_model` — the best checkpoint as an artifact and the
  network as an MLflow model of weights + JSON (no pickled code, SHA-256 sealed) that
  :func:`traffictwin.mlops.registry.load_registered` restores with the problem's loader.
- :func:`fit_run` — the one training driver (:class:`FitLoop`, :class:`RunRecord`, yields
  :class:`Fitted`; :func:`fit_and_publish` publishes it inside the run); :class:`ModelOutputs`, :func:`fit_metrics`, :func:`log_fitted_model`,
  :func:`publish` and :class:`FitResult` — publishing the best epoch of a run.
- One checkpoint format for every trained network (:data:`MODEL_FORMAT`):
  :func:`model_checkpoint` builds it, :func:`save_model_checkpoint` writes it atomically,
  :func:`read_model_checkpoint` reads it back with ``weights_only=True`` and checks it, and
  :func:`net_state_dict` gives the network's weights. A model folder's ``model.ckpt`` and
  ``model_meta.json`` are one unit: :func:`save_model_files` writes them (meta last, recording
  the checkpoint's SHA-256) and :func:`check_model_pair` refuses a pair that does not match.

The names load on first use (a module ``__getattr__`` imports :mod:`~traffictwin.trainer.exports`),
so a stage that only needs a light submodule (``from traffictwin.trainer.settings import
check_device``, :mod:`~traffictwin.trainer.sampling`) does not import Lightning.
"""

from __future__ import annotations

from typing import Any


def __getattr__(name: str) -> Any:
    """``name`` from the re-exported API (imports Lightning on the first call)."""
    if name.startswith("__"):  # dunder probes (copy, pickle, doctest) need not load the API
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import traffictwin.trainer.exports as api

    # bind every re-exported name here, as eager imports would: the function ``publish`` then
    # replaces the submodule of that name that importing the API set on this package
    globals().update({k: v for k, v in vars(api).items() if not k.startswith("_")})
    try:
        return globals()[name]
    except KeyError:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
