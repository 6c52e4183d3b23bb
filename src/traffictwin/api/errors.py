"""Errors and warnings of the public API (:mod:`traffictwin.api`): one line naming the input,
argument or model and what was expected."""

from __future__ import annotations


class ApiError(ValueError):
    """A user-facing error in one line naming the file / argument / model and what was expected."""


class InputFileError(ApiError):
    """An input file or folder is missing, unreadable or not of the expected format."""


class InputValueError(ApiError):
    """An argument's value (masses, pose, cell, speed, image array, threshold) is invalid."""


class ModelDomainError(ApiError):
    """An input outside what the model was trained on (grid, cell, camera, speed)."""


class ApiWarning(UserWarning):
    """An input the model does not use or cannot check (one line; the CLI prints it to stderr)."""
