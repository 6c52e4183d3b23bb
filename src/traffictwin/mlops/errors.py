"""Errors shared by the promotion gate, the registry and the model artifacts (no MLflow, no torch here).

Kept apart from :mod:`traffictwin.mlops.gate` so that the trainers, which log models
(:mod:`traffictwin.mlops.model_artifact`), do not depend on the gate's decision code.
"""

from __future__ import annotations


class GateError(RuntimeError):
    """The gate cannot decide (e.g. the evaluation returned no figure for the gate's metric)."""


class IncompatibleModelError(GateError):
    """A model version is known not to fit the current evaluation (another grid or architecture,
    a format that is never loaded); raised by an evaluator, it lets the gate skip a champion."""


class RegistryError(GateError):
    """A registry operation cannot be done (missing model, alias, version or run)."""


class ChampionChangedError(RegistryError):
    """The champion alias moved between a decision and its application."""


class LockTimeoutError(RegistryError):
    """The registry lock was not acquired in time."""
