"""What :func:`~traffictwin.risk.evaluation.suite.evaluate_suite` evaluates, and how: the
predictor and label names and the suite's settings (:class:`SuiteSettings`)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from traffictwin.risk.evaluation.bootstrap import CIConfig

#: label columns of the three regions (docs/design.md "Risk metric"), the headline corridor first
REGION_LABELS = ("risk_thw_corridor", "risk_thw_paper", "risk_thw_fov")
#: baselines, in report order; ``geometric_learned``: the corridor rule on the learned stereo
#: network's disparity; ``geometric_gt``: the corridor rule on ground-truth disparity
BASELINES = (
    "train_mean",
    "train_median",
    "speed_only",
    "geometric_sgm",
    "geometric_learned",
    "geometric_gt",
)
#: the corridor rules among the baselines and the disparity each reads (a rule runs where the
#: source has its disparity)
RULE_INPUTS = (
    ("geometric_sgm", "disp_sgm"),
    ("geometric_learned", "disp_learned"),
    ("geometric_gt", "disp_gt"),
)
#: predictors fed ground-truth disparity (not available at inference): a reference, not an oracle —
#: the corridor rule's straight band is not the true (curved) corridor of the label
GT_INPUT = ("geometric_gt",)
#: oracles (true geometry along the true corridor): none is evaluated
ORACLES: tuple[str, ...] = ()
#: suffix of a variant's seed-averaged predictor (the variant and its ``replicate_of`` runs)
SEED_MEAN = "[seed_mean]"


@dataclass(frozen=True)
class Holdout:
    """Generalisation to unseen road templates: ``group``: the runs trained without
    ``templates``; ``reference``: the same model trained on every template."""

    templates: tuple[str, ...]
    group: str
    reference: str


@dataclass(frozen=True)
class SuiteSettings:
    """Settings of :func:`~traffictwin.risk.evaluation.suite.evaluate_suite`.

    ``primary_label``: the label column the baselines and decisions refer to; ``region_labels``:
    the region label columns compared with each other; ``thresholds_s``: THW thresholds (s), the
    primary first; ``thw_cap``: THW cap (s) of the THW errors; ``geometric``:
    :class:`~traffictwin.risk.baselines.GeometricParams` of the corridor rules (``None`` = no
    geometric baselines); ``batch_size``: frames per network forward pass; ``split``: the
    evaluated split; ``main_variant``: the headline (default: the first model); ``variants``:
    ``risk_model.variants`` entries (``replicate_of``, ``objective``, ``seed_offset``; missing =
    none / mse / 0); ``ci``: the bootstrap; ``collapse_std``: a model whose predictions have a
    smaller standard deviation (normalised risk) is collapsed. Choices made on validation (stage
    ``select_risk``): ``rule_params``: rule name (``geometric_sgm``/``geometric_gt``) → its
    tuned :class:`GeometricParams` (default ``geometric``); ``decisions``: predictor → {THW
    threshold s: decision cut on its risk} for the primary label; ``shipped``: the model served
    to users (targets); ``learned``: the learned variant group compared with the SGM rule
    (targets); ``holdout``: the unseen-template check (``None``: none); ``acceptance``: the
    targets' thresholds (``acceptance.risk``, :func:`traffictwin.acceptance.thresholds`)."""

    primary_label: str
    thresholds_s: tuple[float, ...]
    region_labels: tuple[str, ...] = REGION_LABELS
    thw_cap: float = 10.0
    geometric: Any = None
    batch_size: int = 256
    split: str = "test"
    main_variant: str | None = None
    variants: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    ci: CIConfig = field(default_factory=CIConfig)
    collapse_std: float = 1e-3
    rule_params: Mapping[str, Any] = field(default_factory=dict)
    decisions: Mapping[str, Mapping[float, float]] = field(default_factory=dict)
    shipped: str | None = None
    learned: str | None = None
    holdout: Holdout | None = None
    acceptance: Mapping[str, Any] = field(default_factory=dict)

    @property
    def t0(self) -> float:
        """The primary THW threshold (s)."""
        return self.thresholds_s[0]

    def rule(self, name: str) -> Any:
        """The corridor parameters of rule ``name`` (tuned on validation, else ``geometric``)."""
        return self.rule_params.get(name, self.geometric)
