"""The fusion losses registry: every training loss of the fusion network, registered once by name
with its settings (the block ``fusion_model.loss.<name>``) and its function.

Torch-free, so the parameter check and the stages that only read the names (``fusion_variants``)
load no torch: an entry names its function in :mod:`traffictwin.fusion.losses` (where the
training stages import it from), loaded on first use. Registered losses, in order:

- ``mass`` (default): KL from the label's full mass vector to the prediction (:func:`~traffictwin.fusion.losses.mass_loss`);
- ``paper``: the paper's eq. 7 (:func:`~traffictwin.fusion.losses.paper_loss`);
- ``paper_kl``: eq. 7 + the annealed KL regulariser (:func:`~traffictwin.fusion.losses.paper_kl_loss`).

Adding a loss is one function in :mod:`traffictwin.fusion.losses`, one settings dataclass and one
registration here, and its block in ``conf/fusion_model/*.yaml``::

    @dataclass
    class MyLoss:
        occupied_weight: float = spec(min=1.0)

    register_loss("my_loss", "what it minimises", settings=MyLoss, fn="my_loss")

A loss function is ``fn(e, y, settings, epoch) -> scalar tensor``: evidences and label masses
``(N, 2, H, W)``, its settings (an instance of the dataclass), the 0-based training epoch (for
annealed terms) or None for the validation loss (regularisers off); it returns the mean over cells
and batch. ``fusion_model.loss.name``, a variant's ``loss`` and the settings blocks are checked
against :data:`LOSSES`.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from traffictwin.config import spec

__all__ = [
    "FusionLoss",
    "LOSSES",
    "register_loss",
    "unregister_loss",
    "MassLoss",
    "PaperLoss",
    "PaperKLLoss",
]

FUNCTIONS = "traffictwin.fusion.losses"  # the module a function named by a string lives in


@dataclass(frozen=True)
class FusionLoss:
    """A registered fusion loss: ``settings`` is the dataclass of ``fusion_model.loss.<name>``
    (bounds via :func:`traffictwin.config.spec`); ``fn`` the function or its name in
    :mod:`traffictwin.fusion.losses`."""

    name: str
    description: str
    settings: type
    fn: str | Callable[..., Any]

    def function(self) -> Callable[..., Any]:
        """The loss function (importing :mod:`traffictwin.fusion.losses`, and torch, when named)."""
        if callable(self.fn):
            return self.fn
        return getattr(importlib.import_module(FUNCTIONS), self.fn)


LOSSES: dict[str, FusionLoss] = {}


def register_loss(
    name: str, description: str, *, settings: type, fn: str | Callable[..., Any]
) -> FusionLoss:
    """Register loss ``name`` with its settings dataclass and function (see the module docstring)."""
    if name in LOSSES:
        raise ValueError(f"fusion loss {name!r} is registered twice")
    if not name.isidentifier() or name == "name":  # a key of fusion_model.loss beside its ``name``
        raise ValueError(f"fusion loss name {name!r} must be an identifier other than 'name'")
    LOSSES[name] = FusionLoss(name, description, settings, fn)
    return LOSSES[name]


def unregister_loss(name: str) -> None:
    """Remove loss ``name`` (tests register toy losses)."""
    del LOSSES[name]


# -- the losses -------------------------------------------------------------------------------------
@dataclass
class MassLoss:
    """``fusion_model.loss.mass``: o_w of the full-mass-vector KL loss."""

    occupied_weight: float = spec(min=1.0)


@dataclass
class PaperLoss:
    """``fusion_model.loss.paper``: eq. 7's occupied weight o_w."""

    occupied_weight: float = spec(min=1.0)


@dataclass
class PaperKLLoss:
    """``fusion_model.loss.paper_kl``: eq. 7 + the KL regulariser, its weight ramped up as
    ``kl_weight * min(1, epoch / kl_anneal_epochs)``."""

    occupied_weight: float = spec(min=1.0)
    kl_weight: float = spec(min=0.0)
    kl_anneal_epochs: int = spec(min=1)


register_loss(
    "mass",
    "KL divergence from the label's (m_F, m_O, u) to the predicted one",
    settings=MassLoss,
    fn="mass_loss",
)
register_loss(
    "paper", "the paper's eq. 7 (expected squared error)", settings=PaperLoss, fn="paper_loss"
)
register_loss(
    "paper_kl",
    "eq. 7 + the annealed KL regulariser (Sensoy et al.)",
    settings=PaperKLLoss,
    fn="paper_kl_loss",
)
