"""Fusion evaluation (paper V-A, Figs. 4–7): every registered method on every configuration's test set.

The stage ``evaluate_fusion`` reads params and paths and writes the outputs; everything in
between is in this package, with paths and settings as explicit arguments (names re-exported here):

- :mod:`.keys` — rows, metric keys, :class:`EvalSettings`, the bootstrap cluster;
- :mod:`.data` — :func:`load_test_sets` / :func:`load_raw_pairs`: the same pair ids (and so the
  same noise draws) for every configuration and method, masses and grid shape checked;
- :mod:`.method_run` — :func:`evaluate_method`: per-sample metrics of one registered method
  (:data:`traffictwin.fusion.methods.METHODS`) on a :class:`~traffictwin.fusion.methods.FusionInput`,
  and one row's aggregates (summary, cross-table cell, :func:`pose_bins`);
- :mod:`.loop` — :func:`evaluate`: every method without a network once per configuration, every *row* of
  networks (``networks[row][cfg]``: ``dnn`` = the one network at every configuration, plus the
  ``fusion_variants`` rows such as ``registered+network``, ``dnn[paper]`` or the ablation's
  per-configuration networks ``dnn[per-config]``) where it has a model, the per-configuration
  networks on the other configurations (cross table), pose-error bins, cluster-bootstrap
  intervals, paired differences and the targets: an :class:`Evaluation`;
- :mod:`.intervals` — :func:`row_intervals`, :func:`paired_intervals`: the statistics
  (:mod:`traffictwin.stats`; cluster = scenario = ``pair_id // 1000``);
- :mod:`.targets` — :data:`JUDGES` (the targets), :func:`fusion_targets` (typed verdicts per
  configuration against the acceptance thresholds ``acceptance.fusion``);
- :mod:`.outputs` — :func:`plot_tables`, :func:`figures`, :func:`qualitative_panels`: DVC plot
  data and figures; :func:`mlflow_metrics`, :func:`methods_table`: the flat numbers of one network's MLflow run,
  every method's numbers as one table artifact (JSON-safe values: :mod:`traffictwin.io.jsonio`).

Metrics layout (``fusion.json``); ``<row>`` is a method name or a network row (``dnn``,
``dnn[<loss>]``, ``registered+network``):

- ``test.<cfg>.<row>.<metric>`` — point estimates (:data:`SUMMARY_KEYS`, ``u_auroc``,
  method diagnostics); the headline is ``kld_fou_mean`` (KLD(b));
- ``test.<cfg>.<row>.<metric>_ci: {lo, hi}`` — 95 % cluster-bootstrap interval of each
  metric of :data:`CI_KEYS`;
- ``diff.<cfg>.<row>.vs_<base>.<metric>: {estimate, lo, hi, n_pairs}`` — paired difference
  ``row − base`` (same pairs, same resamples) for ``base`` in :data:`DIFF_BASELINES` and the
  metrics of :data:`DIFF_KEYS`;
- ``label.<cfg>.u_mean`` (+ ``u_mean_ci``) — mean u of the labels over the evaluated pairs;
- ``targets.<name>: {description, threshold, status, per_config: {<cfg>: {value, lo, hi,
  status, ci_beyond_threshold}}}`` — the targets (:func:`fusion_targets`), status
  ``pass`` / ``fail`` / ``not evaluated``;
- ``cross.dnn[per-config]-<net>.<cfg>.<metric>`` (with the ablation),
  ``bins.{translation,rotation}.<row>.<bin>.<metric>``,
  ``n_pairs.{per_config,registered,cross}``, ``bootstrap.{n_boot,seed,level,cluster}``.

fusion.json and the samples table hold only what the same data and params reproduce exactly.
Wall times differ between identical runs and are in :attr:`Evaluation.timings` (the stage puts
them in its run record): ``ms_per_pair.<cfg>.<row>``, ``runtime_ms_per_pair.<row>`` and the
targets judged on them (:data:`TIMING_TARGETS`).
"""

from traffictwin.fusion.evaluation.data import load_raw_pairs, load_test_sets
from traffictwin.fusion.evaluation.intervals import paired_intervals, row_intervals
from traffictwin.fusion.evaluation.keys import (
    BIN_KEYS,
    CI_KEYS,
    CROSS_KEYS,
    CROSS_ROWS,
    DIFF_BASELINES,
    DIFF_KEYS,
    FIGURE_METHODS,
    HEADLINE,
    HYBRID,
    LEARNED,
    LEARNED_NETWORK,
    LEARNED_REFINED,
    LEARNED_REFINED_NETWORK,
    NETWORK,
    PER_CONFIG_NETWORK,
    SCENARIO_STRIDE,
    SUMMARY_KEYS,
    EvalSettings,
    fusion_ci_config,
    row_method,
    scenario_of,
)
from traffictwin.fusion.evaluation.loop import Evaluation, evaluate
from traffictwin.fusion.evaluation.method_run import evaluate_method, pose_bins
from traffictwin.fusion.evaluation.outputs import (
    figure_inputs,
    methods_table,
    mlflow_metrics,
    plot_tables,
    qualitative_panels,
)
from traffictwin.fusion.evaluation.targets import JUDGES, TIMING_TARGETS, fusion_targets
from traffictwin.fusion.pairs import evenly_spaced  # the one pair selection
from traffictwin.stats import CIConfig

__all__ = [
    "EvalSettings",
    "CIConfig",
    "Evaluation",
    "SUMMARY_KEYS",
    "CROSS_KEYS",
    "CROSS_ROWS",
    "BIN_KEYS",
    "CI_KEYS",
    "DIFF_KEYS",
    "DIFF_BASELINES",
    "FIGURE_METHODS",
    "HEADLINE",
    "HYBRID",
    "LEARNED",
    "LEARNED_NETWORK",
    "LEARNED_REFINED",
    "LEARNED_REFINED_NETWORK",
    "NETWORK",
    "PER_CONFIG_NETWORK",
    "SCENARIO_STRIDE",
    "JUDGES",
    "TIMING_TARGETS",
    "row_method",
    "scenario_of",
    "fusion_ci_config",
    "evenly_spaced",
    "load_test_sets",
    "load_raw_pairs",
    "evaluate_method",
    "evaluate",
    "row_intervals",
    "paired_intervals",
    "fusion_targets",
    "pose_bins",
    "qualitative_panels",
    "plot_tables",
    "figure_inputs",
    "mlflow_metrics",
    "methods_table",
]
