"""Metrics for the risk network (Feth et al., sec. 4) and the evaluation of several predictors.

One module per concern: :mod:`.scoring` (point metrics of one predictor against one label:
MSE / MAE, THW errors, confusion matrix, accuracy, balanced accuracy, ROC-AUC), :mod:`.bootstrap`
(the sequence-level cluster bootstrap of every metric, paired differences, Holm's correction),
:mod:`.settings` (:class:`SuiteSettings`, the predictor and label names), :mod:`.predictions`
(every predictor's per-frame risk), :mod:`.scorer` (seed groups, collapse, the shared scorer),
:mod:`.breakdowns` (critical shares, regions, situations, unseen templates), :mod:`.targets`
(the targets) and :mod:`.suite` (:func:`evaluate_suite`: the whole evaluation, whose dict
is ``reports/metrics/risk.json``).

Statistics: every reported metric carries a sequence-level bootstrap interval (the test frames of
one driving sequence are correlated, so whole sequences are resampled); one set of draws serves
every predictor, so differences are *paired*. A variant trained with several seeds
(``replicate_of``) is scored by the mean over its seeds of each metric, resample by resample.
A model whose test predictions have a standard deviation below ``collapse_std`` is *collapsed*
(one output for every frame): it is reported as a failed run and never interpreted.

The names below are the package's public interface (importers use ``traffictwin.risk.evaluation``).
"""

from traffictwin.risk.evaluation.bootstrap import (
    CIConfig,
    ClusterBootstrap,
    Stat,
    bootstrap_p,
    bootstrap_scores,
    difference_json,
    difference_of_scores,
    holm,
    mean_of_scores,
    scores_with_ci,
    seed_draws,
    spread_stat,
    weighted_median_stat,
)
from traffictwin.risk.evaluation.breakdowns import critical_shares
from traffictwin.risk.evaluation.scorer import variant_groups
from traffictwin.risk.evaluation.scoring import (
    LOWER_IS_BETTER,
    PAPER,
    classification_metrics,
    confusion_labels,
    confusion_table,
    evaluate,
    example_indices,
    label_agreement,
    regression_metrics,
    roc_auc,
    summarise_paper_comparison,
)
from traffictwin.risk.evaluation.settings import (
    BASELINES,
    GT_INPUT,
    ORACLES,
    REGION_LABELS,
    SEED_MEAN,
    Holdout,
    SuiteSettings,
)
from traffictwin.risk.evaluation.suite import evaluate_suite, main_series, tracking_metrics
from traffictwin.risk.evaluation.targets import TARGET_NAMES, judge

__all__ = [
    "BASELINES",
    "GT_INPUT",
    "LOWER_IS_BETTER",
    "ORACLES",
    "PAPER",
    "REGION_LABELS",
    "SEED_MEAN",
    "TARGET_NAMES",
    "CIConfig",
    "ClusterBootstrap",
    "Holdout",
    "Stat",
    "SuiteSettings",
    "bootstrap_p",
    "bootstrap_scores",
    "classification_metrics",
    "confusion_labels",
    "confusion_table",
    "critical_shares",
    "difference_json",
    "difference_of_scores",
    "evaluate",
    "evaluate_suite",
    "example_indices",
    "holm",
    "judge",
    "label_agreement",
    "main_series",
    "mean_of_scores",
    "regression_metrics",
    "roc_auc",
    "scores_with_ci",
    "seed_draws",
    "spread_stat",
    "summarise_paper_comparison",
    "tracking_metrics",
    "variant_groups",
    "weighted_median_stat",
]
