"""The evaluation loop: every method and network row on every configuration's pairs (:func:`evaluate`),
collecting the per-pair frames, each row's numbers with intervals, the paired differences, the
cross table, the pose-error bins and the targets into an :class:`Evaluation`."""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from traffictwin.acceptance import Threshold
from traffictwin.evidential.masses import unknown_mass
from traffictwin.fusion.config import FusionEvalConfig
from traffictwin.fusion.evaluation.intervals import (
    ci_kwargs,
    lohi,
    paired_intervals,
    row_intervals,
)
from traffictwin.fusion.evaluation.keys import (
    CROSS_ROWS,
    DIFF_BASELINES,
    HEADLINE,
    NETWORK,
    ROW_BASELINES,
    SCENARIO_STRIDE,
    EvalSettings,
    is_cross,
    row_method,
    scenario_of,
)
from traffictwin.fusion.evaluation.method_run import (
    cross_entry,
    evaluate_method,
    pose_bins,
    summary,
    tag_samples,
)
from traffictwin.fusion.evaluation.targets import TIMING_TARGETS, fusion_targets
from traffictwin.fusion.methods import METHODS, FusionInput, FusionMethod
from traffictwin.fusion.metrics import auroc_with_counts
from traffictwin.fusion.pairs import evenly_spaced
from traffictwin.fusion.registration_batches import precompute_registrations
from traffictwin.grid import GridSpec
from traffictwin.stats import CIConfig, mean_ci

if TYPE_CHECKING:  # pandas loads where a table is built: check_params imports this package
    import pandas as pd

log = logging.getLogger("traffictwin.evaluate_fusion")


@dataclass
class Evaluation:
    """Result of :func:`evaluate`: ``metrics`` (the fusion.json dict, before :func:`json_clean`),
    ``samples`` (one row per configuration × row × pair), ``bins`` (pose-error bin table),
    ``data`` / ``raw`` (the evaluated arrays per configuration / raw pairs), ``networks``
    (``{row: {cfg: model}}``) and ``timings`` (wall times, which differ between identical runs:
    ``ms_per_pair.<cfg>.<row>``, ``runtime_ms_per_pair.<row>``, ``targets`` of
    :data:`TIMING_TARGETS`; never in ``metrics`` or ``samples``)."""

    metrics: dict[str, Any]
    samples: pd.DataFrame
    bins: pd.DataFrame
    data: dict[str, dict[str, np.ndarray]]
    raw: dict[str, np.ndarray]
    networks: Mapping[str, Mapping[str, Any]]
    timings: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class PairSubsets:
    """Indices of the evaluated pairs each kind of run uses: ``every`` pair, the ``registered``
    subset of the slow methods (``registered_max_pairs``), the ``cross`` table's subset
    (``cross_max_pairs``); spread evenly over the pairs."""

    every: np.ndarray
    registered: np.ndarray
    cross: np.ndarray

    @classmethod
    def of(cls, n: int, cfg: FusionEvalConfig) -> PairSubsets:
        return cls(
            np.arange(n),
            evenly_spaced(n, cfg.registered_max_pairs),
            evenly_spaced(n, cfg.cross_max_pairs),
        )


@dataclass(frozen=True)
class RowRun:
    """One evaluation row at one configuration: its name, registry method, network (None for a
    method without one) and the ``network`` column of its samples (the configuration a
    per-configuration network was trained on, or the row)."""

    row: str
    method: FusionMethod
    model: Any
    network: str


@dataclass
class _Collected:
    """What :func:`evaluate` gathers: the samples-table parts in order, each (configuration, row)'s
    per-pair frame and the fusion.json blocks per configuration."""

    frames: list[pd.DataFrame] = field(default_factory=list)
    own: dict[tuple[str, str], pd.DataFrame] = field(default_factory=dict)
    test: dict[str, dict[str, Any]] = field(default_factory=dict)
    diff: dict[str, dict[str, Any]] = field(default_factory=dict)
    label: dict[str, dict[str, Any]] = field(default_factory=dict)
    cross: dict[str, dict[str, Any]] = field(default_factory=dict)

    def add(self, c: str, row: str, tagged: pd.DataFrame) -> None:
        self.frames.append(tagged)
        self.own[(c, row)] = tagged


@dataclass(frozen=True)
class _Context:
    """The inputs every configuration's evaluation shares."""

    raw: dict[str, np.ndarray]
    networks: Mapping[str, Mapping[str, Any]]
    grid: GridSpec
    cfg: FusionEvalConfig
    ci: CIConfig
    settings: EvalSettings
    pairs: PairSubsets


def _check_networks(networks: Mapping[str, Mapping[str, Any]], configs: Sequence[str]) -> None:
    if NETWORK not in networks:
        raise ValueError(f"evaluate: networks has no '{NETWORK}' row (rows: {list(networks)})")
    for row, nets in networks.items():
        method = METHODS.get(row_method(row))
        if method is None or "model" not in method.needs:
            raise ValueError(
                f"evaluate: network row {row!r} names no registry method that uses a model "
                f"(expected <method>[<loss>] with method from "
                f"{[m for m, f in METHODS.items() if 'model' in f.needs]})"
            )
        unknown = sorted(set(nets) - set(configs))
        if unknown:
            raise ValueError(
                f"evaluate: networks[{row!r}] has configuration(s) {unknown} not in the data {list(configs)}"
            )


def _config_input(ctx: _Context, d: Mapping[str, np.ndarray]) -> FusionInput:
    """The pairs of one configuration as a :class:`FusionInput`, with the classical registration
    of the slow methods' pairs computed once per pair (in parallel) and shared through ``memo``."""
    base = FusionInput(
        inputs=d["inputs"],
        map1=ctx.raw["map1"],
        map2=ctx.raw["map2"],
        rel_pose_noisy=d["rel_pose_noisy"],
        rel_pose_true=d["rel_pose_true"],
        grid=ctx.grid,
        batch_size=ctx.cfg.batch_size,
        registration=ctx.cfg.registration_params,
        refinement=ctx.cfg.refinement_params,
        pair_key=np.arange(len(ctx.pairs.every)),
        memo={},  # each registration once per pair, shared by the methods that use it
    )
    # the classical registration of the pairs the slow methods (registered, registered+network)
    # run on: once per pair, in parallel
    precompute_registrations(base.take(ctx.pairs.registered), ctx.cfg.registration_workers)
    return base


def _row_runs(networks: Mapping[str, Mapping[str, Any]], c: str) -> list[RowRun]:
    """Every method without a network, then every network row that has a model at ``c``."""
    runs = [RowRun(name, m, None, "") for name, m in METHODS.items() if "model" not in m.needs]
    runs += [
        RowRun(row, METHODS[row_method(row)], nets[c], c if row in CROSS_ROWS else row)
        for row, nets in networks.items()
        if c in nets
    ]
    return runs


def _evaluate_rows(ctx: _Context, acc: _Collected, c: str, d: Mapping[str, np.ndarray]) -> None:
    """Every row at configuration ``c``: its per-pair frame, numbers and intervals (``test``) and,
    for a per-configuration network, its own cell of the cross table."""
    base = _config_input(ctx, d)
    acc.test[c] = {}
    for run in _row_runs(ctx.networks, c):
        idx = ctx.pairs.registered if run.method.slow else ctx.pairs.every
        x = base.take(idx)
        x.model = run.model
        f, au = evaluate_method(run.method, x, d["label"][idx], ctx.settings)
        tagged = tag_samples(f, c, run.row, d, idx, network=run.network)
        acc.add(c, run.row, tagged)
        extra = run.method.summary(f, ctx.settings) if run.method.summary else {}
        hists = au.sample_histograms()
        cis = row_intervals(tagged, *hists, ctx.ci)
        counted = auroc_with_counts(
            *hists, ctx.settings.auroc_min_wrong, ctx.settings.auroc_min_pairs
        )
        if not counted["u_auroc_enough"]:  # too few wrong cells: no number, no interval
            nan = float("nan")
            cis["u_auroc"] = replace(cis["u_auroc"], estimate=nan, lo=nan, hi=nan)
        acc.test[c][run.row] = {
            **summary(f),
            **counted,
            **extra,
            **{f"{k}_ci": lohi(iv) for k, iv in cis.items()},
        }
        if run.row in CROSS_ROWS:
            acc.cross[f"{run.row}-{c}"][c] = cross_entry(f, au)
    _evaluate_cross(ctx, acc, c, d, base)


def _evaluate_cross(
    ctx: _Context, acc: _Collected, c: str, d: Mapping[str, np.ndarray], base: FusionInput
) -> None:
    """Each other configuration's per-configuration network on this configuration's pairs (the
    cross table), on ``cross_max_pairs`` pairs."""
    idx = ctx.pairs.cross
    for row in (r for r in CROSS_ROWS if r in ctx.networks):
        for other, model in ctx.networks[row].items():
            if other == c:
                continue
            x = base.take(idx)
            x.model = model
            f, au = evaluate_method(METHODS[row_method(row)], x, d["label"][idx], ctx.settings)
            tagged = tag_samples(f, c, f"{row}-{other}", d, idx, network=other)
            acc.add(c, f"{row}-{other}", tagged)
            acc.cross[f"{row}-{other}"][c] = cross_entry(f, au)


def _label_u(d: Mapping[str, np.ndarray], ci: CIConfig) -> dict[str, Any]:
    """Mean u of the labels over the evaluated pairs, with its interval."""
    label_u = unknown_mass(np.asarray(d["label"], np.float64)).mean(axis=(1, 2))
    lu = mean_ci(label_u, scenario_of(d["pair_id"]), **ci_kwargs(ci))
    return {"u_mean": lu.estimate, "u_mean_ci": lohi(lu)}


def _paired_diffs(
    own: Mapping[tuple[str, str], pd.DataFrame], c: str, ci: CIConfig
) -> dict[str, Any]:
    """``diff.<c>``: every row (not the cross rows) against each baseline evaluated at ``c``."""
    out: dict[str, Any] = {}
    for (cc, row), frame in own.items():
        if cc != c or is_cross(row):
            continue
        for b in (*DIFF_BASELINES, *ROW_BASELINES.get(row, ())):
            if row == b or (c, b) not in own:
                continue
            diffs, n_common = paired_intervals(frame, own[(c, b)], ci)
            out.setdefault(row, {})[f"vs_{b}"] = {
                k: {"estimate": iv.estimate, "lo": iv.lo, "hi": iv.hi, "n_pairs": n_common}
                for k, iv in diffs.items()
            }
    return out


def _log_config(c: str, t: Mapping[str, Any]) -> None:
    log.info(
        "config %s: KLD(b) naive %.4f, network %.4f [%.4f, %.4f], registered %.4f (success %.0f %%)",
        c,
        t["naive"][HEADLINE],
        t[NETWORK][HEADLINE],
        t[NETWORK][f"{HEADLINE}_ci"]["lo"],
        t[NETWORK][f"{HEADLINE}_ci"]["hi"],
        t["registered"][HEADLINE],
        100 * t["registered"]["success_rate"],
    )


def _timings(acc: _Collected, main: pd.DataFrame, targets: Mapping[str, Any]) -> dict[str, Any]:
    """Wall times per pair (they differ between identical runs) and the targets judged on them."""
    return {
        "ms_per_pair": {
            c: {
                row: float(f["ms"].mean())
                for (cc, row), f in acc.own.items()
                if cc == c and not is_cross(row)
            }
            for c in acc.test
        },
        "runtime_ms_per_pair": {
            m: float(g["ms"].mean()) for m, g in main.groupby("method", sort=False)
        },
        "targets": {k: v for k, v in targets.items() if k in TIMING_TARGETS},
    }


def evaluate(
    data: dict[str, dict[str, np.ndarray]],
    raw: dict[str, np.ndarray],
    networks: Mapping[str, Mapping[str, Any]],
    grid: GridSpec,
    cfg: FusionEvalConfig,
    ci: CIConfig,
    thresholds: Mapping[str, Threshold],
    training: Mapping[str, Any] | None = None,
) -> Evaluation:
    """Every method on every configuration of ``data`` (from :func:`load_test_sets`, in
    configuration order), ``raw`` its raw pairs (:func:`load_raw_pairs`).

    ``networks[row][cfg]``: the loaded network of evaluation row ``row`` at configuration
    ``cfg`` — ``"dnn"`` (the one network, the same model at every configuration) and the
    variant rows (``"registered+network"``, ``"dnn[paper]"``, ``"dnn[per-config]"``, …; registry
    method :func:`row_method`). Methods without a network run once per configuration; a row runs
    where it has a model; a registration (classical or learned) is computed once per pair and
    shared by the rows that use it. Slow methods run on ``cfg.registered_max_pairs`` pairs (null
    = all: every method on the same pairs), the per-configuration networks on other
    configurations on ``cfg.cross_max_pairs`` (the cross table). Intervals and differences:
    ``ci`` (see the package docstring). Targets: judged against ``thresholds``
    (``acceptance.fusion``, :func:`traffictwin.acceptance.thresholds`); the training target on
    the one network's ``training`` record (train_fusion_network.json).
    """
    import pandas as pd

    configs = list(data)
    _check_networks(networks, configs)
    n = len(next(iter(data.values()))["pair_id"])
    pairs = PairSubsets.of(n, cfg)
    ctx = _Context(raw, networks, grid, cfg, ci, EvalSettings.from_config(cfg), pairs)
    log.info(
        "evaluating %d pairs per configuration (%d for slow methods, %d cross) on %s; rows %s",
        n,
        len(pairs.registered),
        len(pairs.cross),
        configs,
        list(networks),
    )
    acc = _Collected(
        cross={f"{r}-{c}": {} for r in CROSS_ROWS if r in networks for c in networks[r]}
    )
    for c in configs:
        _evaluate_rows(ctx, acc, c, data[c])
        acc.label[c] = _label_u(data[c], ci)
        acc.diff[c] = _paired_diffs(acc.own, c, ci)
        _log_config(c, acc.test[c])
    samples = pd.concat(acc.frames, ignore_index=True)
    main = samples[~samples["method"].map(is_cross)]
    metrics: dict[str, Any] = {
        "test": acc.test,
        "diff": acc.diff,
        "label": acc.label,
        "cross": acc.cross,
    }
    metrics["bins"], bins_table = pose_bins(main, cfg.trans_bins_m, cfg.rot_bins_deg)
    metrics["n_pairs"] = {
        "per_config": int(n),
        "registered": int(len(pairs.registered)),
        "cross": int(len(pairs.cross)),
    }
    metrics["bootstrap"] = {
        "n_boot": ci.n_boot,
        "seed": ci.seed,
        "level": ci.level,
        "cluster": f"scenario = pair_id // {SCENARIO_STRIDE}",
    }
    targets = fusion_targets(
        acc.own, metrics, ci, cfg.success_trans_m, cfg.success_rot_deg, thresholds, training
    )
    metrics["targets"] = {k: v for k, v in targets.items() if k not in TIMING_TARGETS}
    timings = _timings(acc, main, targets)
    samples = samples.drop(columns="ms")
    return Evaluation(metrics, samples, bins_table, data, raw, networks, timings)
