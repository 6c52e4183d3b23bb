"""Seed groups, the headline roles and the shared scorer of the suite.

A variant trained with several seeds (``replicate_of``) forms a group with its replicates; a
model whose predictions have a standard deviation below ``collapse_std`` is *collapsed* (one
output for every frame): it is reported as a failed run and left out of its group's seed mean.
:class:`Scorer` computes every predictor's bootstrap scores once, on one resampling plan.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from traffictwin.risk.evaluation.bootstrap import (
    ClusterBootstrap,
    Stat,
    bootstrap_scores,
    mean_of_scores,
    seed_draws,
)
from traffictwin.risk.evaluation.predictions import SuitePredictions
from traffictwin.risk.evaluation.scoring import evaluate
from traffictwin.risk.evaluation.settings import SEED_MEAN, SuiteSettings


def variant_groups(
    variants: Sequence[str], replicate_of: Mapping[str, str | None]
) -> dict[str, list[str]]:
    """Base variant → its evaluated runs (the base first, then its replicates in order); chains of
    ``replicate_of`` resolve to the root."""

    def root(v: str) -> str:
        seen = {v}
        while replicate_of.get(v):
            v = str(replicate_of[v])
            if v in seen:
                raise ValueError(f"risk_model.variants: replicate_of forms a cycle at '{v}'")
            seen.add(v)
        return v

    groups: dict[str, list[str]] = {}
    for v in variants:
        groups.setdefault(root(v), []).append(v)
    for b, members in groups.items():
        members.sort(key=lambda m: (m != b, variants.index(m)))
    return groups


@dataclass(frozen=True)
class VariantGroups:
    """The seed groups of the evaluated models: ``members``: base variant → its runs (base
    first); ``group_of``: run → its base; ``used``: base → its runs that did not collapse;
    ``spread``: run → standard deviation of its predictions (normalised risk); ``collapsed``:
    run → whether that is below ``collapse_std``."""

    members: dict[str, list[str]]
    group_of: dict[str, str]
    used: dict[str, list[str]]
    spread: dict[str, float]
    collapsed: dict[str, bool]

    @classmethod
    def of(cls, pred: SuitePredictions, settings: SuiteSettings) -> VariantGroups:
        names = list(pred.label_of)
        spread = {v: float(np.std(pred.table[f"pred_{v}"].to_numpy())) for v in names}
        collapsed = {v: bool(spread[v] < settings.collapse_std) for v in names}
        rep = {v: (settings.variants.get(v) or {}).get("replicate_of") for v in names}
        members = variant_groups(names, rep)
        group_of = {m: b for b, ms in members.items() for m in ms}
        used = {b: [m for m in ms if not collapsed[m]] for b, ms in members.items()}
        return cls(members, group_of, used, spread, collapsed)

    def seed_mean(self, base: str) -> bool:
        """Whether group ``base`` is compared by its seed mean (≥ 2 usable runs)."""
        return len(self.used.get(base, [])) >= 2

    def predictor(self, v: str) -> str:
        """The name a variant's group is compared under: its seed mean when ≥ 2 runs are usable."""
        b = self.group_of[v]
        return f"{b}{SEED_MEAN}" if self.seed_mean(b) else v


@dataclass(frozen=True)
class Roles:
    """The predictors the evaluation leads with: ``main``: the headline variant; ``main_key``:
    the name it is compared under; ``main_label``: its label; ``shipped``: the model served to
    users; ``learned``: the learned group's predictor (``None``: not given)."""

    main: str
    main_key: str
    main_label: str
    shipped: str | None
    learned: str | None

    @classmethod
    def of(cls, groups: VariantGroups, pred: SuitePredictions, settings: SuiteSettings) -> Roles:
        main = settings.main_variant or next(iter(pred.label_of))
        learned = settings.learned
        if learned and groups.seed_mean(learned):
            learned = f"{learned}{SEED_MEAN}"
        key = groups.predictor(main) if groups.group_of[main] == main else main
        return cls(main, key, pred.label_of[main], settings.shipped, learned or None)


class Scorer:
    """Scores of every predictor against every label on one resampling plan, each computed once.

    ``pred``: the suite's predictions; ``groups``: its seed groups; ``plan``: the bootstrap of
    the evaluated frames; ``settings``: thresholds, THW cap and the validation decisions."""

    def __init__(
        self,
        pred: SuitePredictions,
        groups: VariantGroups,
        plan: ClusterBootstrap,
        settings: SuiteSettings,
    ) -> None:
        self.pred, self.groups, self.plan, self.settings = pred, groups, plan, settings
        self.decisions = {
            k: {float(t): float(c) for t, c in v.items()} for k, v in settings.decisions.items()
        }
        self._cache: dict[tuple[str, str], dict[str, Stat]] = {}

    def cuts(self, name: str, label: str) -> Mapping[float, float] | None:
        """The decision cuts chosen on validation (primary label only)."""
        return self.decisions.get(name) if label == self.settings.primary_label else None

    def scores(self, name: str, label: str) -> dict[str, Stat]:
        """Scores of a model, a baseline or a seed group (``<base>[seed_mean]``) against
        ``label``; a seed group's interval resamples its seeds as well as the sequences."""
        if (name, label) not in self._cache:
            if name.endswith(SEED_MEAN):
                base = name.removesuffix(SEED_MEAN)
                runs = self.groups.used[base]
                stream = 1 + sorted(self.groups.used).index(base)
                self._cache[(name, label)] = mean_of_scores(
                    [self.scores(v, label) for v in runs], seed_draws(len(runs), self.plan, stream)
                )
            else:
                s = self.settings
                self._cache[(name, label)] = bootstrap_scores(
                    self.pred.labels[label],
                    self.pred.prediction(name, label),
                    self.plan,
                    s.thresholds_s,
                    s.thw_cap,
                    self.cuts(name, label),
                )
        return self._cache[(name, label)]

    def point(self, name: str, label: str) -> dict[str, Any]:
        """:func:`~traffictwin.risk.evaluation.scoring.evaluate`'s metrics of ``name``."""
        s = self.settings
        return evaluate(
            self.pred.labels[label],
            self.pred.prediction(name, label),
            s.thresholds_s,
            s.thw_cap,
            self.cuts(name, label),
        )
