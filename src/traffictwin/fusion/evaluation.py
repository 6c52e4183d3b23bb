"""Fusion evaluation (paper V-A, Figs. 4–7): every registered method on every configuration's test set.

The stage ``evaluate_fusion`` reads params and paths and writes the outputs; everything in
between is here, with paths and settings as explicit arguments:

- :func:`load_test_sets` / :func:`load_raw_pairs` — the same pair ids (and so the same noise
  draws) for every configuration and method, masses and grid shape checked;
- :func:`evaluate_method` — per-sample metrics of one registered method
  (:data:`traffictwin.fusion.methods.METHODS`) on a :class:`~traffictwin.fusion.methods.FusionInput`;
- :func:`evaluate` — every method without a network once per configuration, every *row* of
  networks (``networks[row][cfg]``: ``dnn`` = the one network at every configuration, plus the
  ``fusion_variants`` rows such as ``registered+network``, ``dnn[paper]`` or the ablation's
  per-configuration networks ``dnn[per-config]``) where it has a model, the per-configuration
  networks on the other configurations (cross table), pose-error bins, cluster-bootstrap
  intervals, paired differences and the targets: an :class:`Evaluation`;
- :func:`row_intervals`, :func:`paired_intervals`, :func:`fusion_targets` — the statistics
  (:mod:`traffictwin.stats`; cluster = scenario = ``pair_id // 1000``);
- :func:`plot_tables`, :func:`figures`, :func:`qualitative_panels` — DVC plot data and figures;
- :func:`mlflow_metrics`, :func:`methods_table` — the flat numbers of one network's MLflow run,
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
  status, ci_beyond_threshold}}}`` — the issue's targets (:func:`fusion_targets`), status
  ``pass`` / ``fail`` / ``not evaluated``;
- ``cross.dnn[per-config]-<net>.<cfg>.<metric>`` (with the ablation),
  ``bins.{translation,rotation}.<row>.<bin>.<metric>``,
  ``n_pairs.{per_config,registered,cross}``, ``bootstrap.{n_boot,seed,level,cluster}``.

fusion.json and the samples table hold only what the same data and params reproduce exactly.
Wall times differ between identical runs and are in :attr:`Evaluation.timings` (the stage puts
them in its run record): ``ms_per_pair.<cfg>.<row>``, ``runtime_ms_per_pair.<row>`` and the
targets judged on them (:data:`TIMING_TARGETS`).
"""

from __future__ import annotations

import logging
import math
import re
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from traffictwin.config import typed
from traffictwin.evidential.masses import check_masses, unknown_mass
from traffictwin.fusion.config import FusionEvalConfig, PoseNoise
from traffictwin.fusion.methods import (
    METHODS,
    FusionInput,
    FusionMethod,
    precompute_registrations,
)
from traffictwin.fusion.metrics import UncertaintyAUROC, aggregate, auroc_from_hist, prf
from traffictwin.fusion.pairs import evenly_spaced  # re-exported: the one pair selection
from traffictwin.grid import GridSpec
from traffictwin.io.shards import Dataset, DatasetError
from traffictwin.stats import (
    CIConfig,
    Interval,
    mean_ci,
    paired_mean_difference_ci,
    resample_counts,
    statistic_ci,
)

__all__ = [
    "EvalSettings",
    "CIConfig",
    "Evaluation",
    "SUMMARY_KEYS",
    "CROSS_KEYS",
    "BIN_KEYS",
    "CI_KEYS",
    "DIFF_KEYS",
    "DIFF_BASELINES",
    "FIGURE_METHODS",
    "HEADLINE",
    "SCENARIO_STRIDE",
    "TARGETS",
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
    "figures",
    "mlflow_metrics",
    "methods_table",
]

# precision / recall / Dice of both classes, pooled over samples
CLASS_SCORE_KEYS = tuple(
    f"{m}_{c}" for c in ("occ", "free") for m in ("precision", "recall", "dice")
)
SUMMARY_KEYS = (
    "n",
    *(f"kld_fo_{s}" for s in ("mean", "median", "q25", "q75")),
    *(f"kld_fou_{s}" for s in ("mean", "median", "q25", "q75")),
    *CLASS_SCORE_KEYS,
    "dice_occ_sample_mean",
    "dice_free_sample_mean",
    "u_mean",
    "u_mean_known",
)
CROSS_KEYS = (
    "n",
    "kld_fo_mean",
    "kld_fou_mean",
    "dice_occ",
    "dice_free",
    "precision_occ",
    "recall_occ",
)
BIN_KEYS = (
    "n",
    "kld_fou_mean",
    "kld_fou_median",
    "kld_fo_mean",
    "kld_fo_median",
    "dice_occ",
    "dice_free",
)
SCORE_KEYS = (*CLASS_SCORE_KEYS, "kld_fou_mean", "kld_fo_mean")  # fusion_scores.csv columns per row
# the method order of the score plots / fusion_scores.csv and the methods of the KLD box plot
# (network rows of fusion_variants are added where they exist)
SCORE_METHODS = ("dnn", "naive", "registered", "naive-yager", "naive-cautious", "ego")
FIGURE_METHODS = ("naive", "registered", "dnn")
NETWORK = "dnn"  # the one fusion network (every configuration)
HEADLINE = "kld_fou_mean"  # KLD(b): KL over the full mass vector (m_F, m_O, u), mean over pairs
SCENARIO_STRIDE = (
    1000  # scenario = pair_id // 1000: the bootstrap cluster (pairs of a scenario correlate)
)
CI_KEYS = ("kld_fou_mean", "kld_fo_mean", "dice_occ", "dice_free", "u_mean", "u_auroc")
DIFF_KEYS = ("kld_fou_mean", "kld_fo_mean", "dice_occ")
DIFF_BASELINES = ("naive", "registered")
PER_CONFIG_NETWORK = "dnn[per-config]"  # the ablation's networks trained on one configuration each
# further paired baselines of single rows: the one network against the per-configuration networks
ROW_BASELINES = {NETWORK: (PER_CONFIG_NETWORK,)}
HYBRID = "registered+network"
LEARNED = "learned"  # the one learned registration (+ Dempster)
LEARNED_NETWORK = "learned+network"
# rows whose networks (one per configuration) are also run on the other configurations: cross
# entries "<row>-<net>"
CROSS_ROWS = (PER_CONFIG_NETWORK,)

log = logging.getLogger("traffictwin.evaluate_fusion")


@dataclass(frozen=True)
class EvalSettings:
    """How per-sample metrics are computed (units in the names)."""

    batch_size: int = 8
    kld_eps: float = 1e-7
    auroc_bins: int = 4096
    success_trans_m: float = 0.5
    success_rot_deg: float = 1.0

    @classmethod
    def from_config(cls, c: FusionEvalConfig) -> EvalSettings:
        return cls(c.batch_size, c.kld_eps, c.auroc_bins, c.success_trans_m, c.success_rot_deg)


def fusion_ci_config(cfg: Any) -> CIConfig:
    """``evaluation.fusion_ci`` of params.yaml, checked."""
    return typed(cfg["evaluation"]["fusion_ci"], CIConfig, key="evaluation.fusion_ci")


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


def row_method(row: str) -> str:
    """The registry method of an evaluation row: ``"dnn[paper]"`` → ``"dnn"``."""
    return row.split("[")[0]


def scenario_of(pair_id: np.ndarray) -> np.ndarray:
    """Scenario of each pair, ``pair_id // 1000`` (int64): the bootstrap cluster."""
    return np.asarray(pair_id, dtype=np.int64) // SCENARIO_STRIDE


# -- data ----------------------------------------------------------------------------------------
def _check_maps(a: np.ndarray, name: str, grid: GridSpec | None, channels: int = 2) -> None:
    """Masses ``a`` (N, channels, H, W): finite, on the simplex, on ``grid``; errors name ``name``."""
    a = np.asarray(a)
    if a.ndim != 4 or a.shape[1] != channels:
        raise DatasetError(f"{name}: expected shape (N, {channels}, H, W), got {a.shape}")
    if grid is not None and a.shape[-2:] != (grid.rows, grid.cols):
        raise DatasetError(
            f"{name}: grid {a.shape[-2]}x{a.shape[-1]} cells, expected {grid.rows}x{grid.cols} "
            "(params.yaml 'grid'; stale data?)"
        )
    for k in range(0, channels, 2):
        what = name if channels == 2 else f"{name} channels {k}-{k + 1}"
        try:
            check_masses(a[:, k : k + 2], what)
        except ValueError as exc:
            raise DatasetError(str(exc)) from None


def load_test_sets(
    roots: Mapping[str, str | Path],
    split: str,
    max_pairs: int | None,
    grid: GridSpec | None = None,
) -> tuple[dict[str, dict[str, np.ndarray]], np.ndarray]:
    """Each configuration's ``split`` arrays (``roots[cfg]`` = its prealigned dataset) restricted to
    the same pair ids: ``max_pairs`` of the pair ids common to all configurations, spread evenly
    over them (so over scenarios/templates). ``inputs`` and ``label`` are checked (finite masses on
    the simplex, on ``grid`` when given): :class:`DatasetError` naming the dataset and array."""
    raw = {}
    for c, root in roots.items():
        ds = Dataset(root, kind="prealigned")
        raw[c] = ds.load_all(split)
        for key in ("inputs", "label", "noise", "rel_pose_true", "rel_pose_noisy", "pair_id"):
            if key not in raw[c]:
                raise DatasetError(f"{ds.root}: array '{key}' missing in split '{split}'")
        _check_maps(raw[c]["inputs"], f"{ds.root}: split '{split}' array 'inputs'", grid, 4)
        _check_maps(raw[c]["label"], f"{ds.root}: split '{split}' array 'label'", grid)
    common = np.array(
        sorted(set.intersection(*(set(raw[c]["pair_id"].tolist()) for c in roots))),
        dtype=np.int64,
    )
    if not len(common):
        raise DatasetError(
            f"{', '.join(str(r) for r in roots.values())}: no pair id common to all '{split}' splits"
        )
    chosen = common[evenly_spaced(len(common), max_pairs)]
    out = {}
    for c in roots:
        pid = np.asarray(raw[c]["pair_id"], dtype=np.int64)
        # the first draw of each pair id wins (a stable sort keeps the first)
        order = np.argsort(pid, kind="stable")
        first = order[np.searchsorted(pid[order], chosen)]
        out[c] = {k: v[first] for k, v in raw[c].items()}
    return out, chosen


def load_raw_pairs(
    root: str | Path, pair_ids: np.ndarray, split: str, grid: GridSpec | None = None
) -> dict[str, np.ndarray]:
    """``map1``, ``map2``, ``label``, ``pose1``, ``pose2`` of the fusion dataset ``root`` for
    ``pair_ids`` (in that order); the maps are checked like :func:`load_test_sets`'s."""
    ds = Dataset(root, kind="fusion")
    keys = ("map1", "map2", "label", "pose1", "pose2", "pair_id")
    arrays = ds.load_all(split, keys=keys)
    index = {int(p): i for i, p in enumerate(arrays["pair_id"])}
    missing = [int(p) for p in pair_ids if int(p) not in index]
    if missing:
        raise DatasetError(
            f"{ds.root}: pair ids {missing[:5]} of the prealigned data missing in split '{split}' (stale data?)"
        )
    idx = np.array([index[int(p)] for p in pair_ids], dtype=np.int64)
    out = {k: arrays[k][idx] for k in keys}
    for k in ("map1", "map2", "label"):
        _check_maps(out[k], f"{ds.root}: split '{split}' array '{k}'", grid)
    return out


# -- one method ----------------------------------------------------------------------------------
def _batches(n: int, size: int):
    for s in range(0, n, max(1, size)):
        yield slice(s, min(n, s + size))


def evaluate_method(
    method: FusionMethod | str, x: FusionInput, label: np.ndarray, settings: EvalSettings
) -> tuple[pd.DataFrame, UncertaintyAUROC]:
    """Per-sample metrics of ``method`` on the pairs ``x`` against ``label`` (N, 2, H, W).

    Returns one row per pair (:func:`~traffictwin.fusion.metrics.per_sample_metrics`, ``ms`` = wall
    time per pair: the method's own per-pair timing if it has one, else its batch's time / size,
    plus the method's diagnostic ``columns``) and the streaming u-AUROC of the whole set (with the
    per-pair histograms of u, :meth:`~traffictwin.fusion.metrics.UncertaintyAUROC.sample_histograms`).
    """
    from traffictwin.fusion.metrics import per_sample_metrics

    method = METHODS[method] if isinstance(method, str) else method
    auroc = UncertaintyAUROC(bins=settings.auroc_bins, keep_samples=True)
    parts, extra, seconds = [], [], []
    for sl in _batches(len(label), settings.batch_size):
        t0 = time.perf_counter()
        batch = x.take(sl)
        fused = method(batch)
        ms = 1000.0 * (time.perf_counter() - t0) / (sl.stop - sl.start)
        pred = fused.masses
        if pred.shape != label[sl].shape:
            raise ValueError(
                f"{method.name}: prediction shape {pred.shape} != label shape {label[sl].shape} "
                f"for samples {sl.start}:{sl.stop}"
            )
        auroc.update(label[sl], pred)
        frame = pd.DataFrame(per_sample_metrics(label[sl], pred, settings.kld_eps))
        frame["ms"] = ms
        parts.append(frame)
        if method.columns is not None:
            extra.append(method.columns(fused, batch, settings))
        if fused.seconds is not None:
            seconds.append(fused.seconds)
    frame = pd.concat(parts, ignore_index=True)
    for k in extra[0] if extra else ():
        frame[k] = np.concatenate([e[k] for e in extra])
    if seconds:
        frame["ms"] = 1000.0 * np.concatenate(seconds)
    return frame, auroc


def _summary(frame: pd.DataFrame) -> dict[str, float]:
    agg = aggregate({k: frame[k].to_numpy() for k in frame.columns})
    return {k: agg[k] for k in SUMMARY_KEYS if k in agg}


def _tag(
    frame: pd.DataFrame,
    cfg: str,
    method: str,
    d: dict[str, np.ndarray],
    idx: np.ndarray,
    network: str = "",
) -> pd.DataFrame:
    """The samples-table rows: configuration, row (method), network, pair id, the noise drawn and
    the label's mean u of each pair (``label_u_mean``)."""
    frame = frame.copy()
    nz = d["noise"][idx]
    frame.insert(0, "pair_id", np.asarray(d["pair_id"][idx], dtype=np.int64))
    frame.insert(0, "network", network)
    frame.insert(0, "method", method)
    frame.insert(0, "config", cfg)
    frame["noise_dx"], frame["noise_dy"], frame["noise_dyaw"] = nz[:, 0], nz[:, 1], nz[:, 2]
    frame["trans_err_m"] = np.hypot(nz[:, 0], nz[:, 1])
    frame["rot_err_deg"] = np.degrees(np.abs(nz[:, 2]))
    frame["label_u_mean"] = unknown_mass(np.asarray(d["label"][idx], np.float64)).mean(axis=(1, 2))
    return frame


# -- statistics ----------------------------------------------------------------------------------
def _codes(pair_id: np.ndarray) -> tuple[np.ndarray, int]:
    """Dense scenario codes 0..G-1 of pairs (the order :func:`traffictwin.stats.mean_ci` uses)."""
    _, codes = np.unique(scenario_of(pair_id), return_inverse=True)
    codes = codes.reshape(-1)
    return codes, int(codes.max()) + 1 if codes.size else 0


def _draws(n_groups: int, ci: CIConfig) -> np.ndarray:
    """(n_boot, G) resample counts of the scenarios: the same draws as ``stats.mean_ci`` (same seed)."""
    return resample_counts(n_groups, ci.n_boot, ci.seed)


def _interval(estimate: float, boot: np.ndarray, level: float, n_groups: int) -> Interval:
    """Percentile interval of the finite bootstrap values ``boot`` (NaN bounds when none)."""
    boot = np.asarray(boot, dtype=np.float64)
    boot = boot[np.isfinite(boot)]
    if not boot.size:
        return Interval(float(estimate), math.nan, math.nan, level, n_groups)
    a = (1.0 - level) / 2.0
    lo, hi = np.quantile(boot, [a, 1.0 - a])
    return Interval(float(estimate), float(lo), float(hi), level, n_groups)


def _pooled_dice(
    frame: pd.DataFrame, cls: str, codes: np.ndarray, n_groups: int, draws: np.ndarray
) -> tuple[float, np.ndarray]:
    """Pooled Dice of class ``cls`` (2TP / (2TP + FP + FN) over all pairs) and its value in each
    resample (``draws`` @ per-scenario sums of the per-pair counts)."""
    counts = [frame[f"{k}_{cls}"].to_numpy(np.float64) for k in ("tp", "fp", "fn")]
    sums = [np.bincount(codes, weights=v, minlength=n_groups) for v in counts]
    estimate = float(prf(*(v.sum() for v in counts))[2])
    return estimate, prf(*(draws @ g for g in sums))[2]


def _auroc_boot(
    pos: np.ndarray,
    neg: np.ndarray,
    codes: np.ndarray,
    n_groups: int,
    draws: np.ndarray,
    chunk: int = 256,
) -> np.ndarray:
    """AUROC of u in each resample from per-pair histograms ``pos``/``neg`` (N, bins): summed per
    scenario, then ``draws`` @ those sums (``chunk`` resamples at a time to bound memory)."""
    onehot = np.zeros((n_groups, len(codes)))
    onehot[codes, np.arange(len(codes))] = 1.0
    pg, ng = onehot @ np.asarray(pos, np.float64), onehot @ np.asarray(neg, np.float64)
    out = np.empty(len(draws))
    for s in range(0, len(draws), chunk):  # a few blocks of resamples, each vectorised
        out[s : s + chunk] = auroc_from_hist(draws[s : s + chunk] @ pg, draws[s : s + chunk] @ ng)
    return out


def row_intervals(
    frame: pd.DataFrame, pos: np.ndarray, neg: np.ndarray, ci: CIConfig
) -> dict[str, Interval]:
    """Cluster-bootstrap intervals of one row at one configuration, keyed by :data:`CI_KEYS`.

    ``frame``: its per-pair metrics with ``pair_id``; ``pos``/``neg``: per-pair histograms of u
    on wrong / right label-known cells (same order). KLD and u means: :func:`~traffictwin.stats.mean_ci`;
    Dice and AUROC(u) recomputed from the resampled per-scenario sums (same draws).
    """
    pid = frame["pair_id"].to_numpy(np.int64)
    groups = scenario_of(pid)
    kw = {"n_boot": ci.n_boot, "level": ci.level, "seed": ci.seed}
    out = {
        "kld_fou_mean": mean_ci(frame["kld_fou"].to_numpy(), groups, **kw),
        "kld_fo_mean": mean_ci(frame["kld_fo"].to_numpy(), groups, **kw),
        "u_mean": mean_ci(frame["u_mean"].to_numpy(), groups, **kw),
    }
    codes, g = _codes(pid)
    draws = _draws(g, ci)
    for cls in ("occ", "free"):
        out[f"dice_{cls}"] = _interval(*_pooled_dice(frame, cls, codes, g, draws), ci.level, g)
    est = auroc_from_hist(np.sum(pos, axis=0), np.sum(neg, axis=0))
    out["u_auroc"] = _interval(est, _auroc_boot(pos, neg, codes, g, draws), ci.level, g)
    if "reg_success" in frame:  # methods that estimate a pose
        out["success_rate"] = mean_ci(frame["reg_success"].to_numpy(np.float64), groups, **kw)
    return out


def paired_intervals(
    a: pd.DataFrame, b: pd.DataFrame, ci: CIConfig
) -> tuple[dict[str, Interval], int]:
    """Paired differences ``a − b`` of :data:`DIFF_KEYS` over the pairs both rows evaluated
    (matched by ``pair_id``), scenarios resampled together; and the number of common pairs."""
    common, ia, ib = np.intersect1d(
        a["pair_id"].to_numpy(np.int64), b["pair_id"].to_numpy(np.int64), return_indices=True
    )
    if not common.size:
        return {}, 0
    a, b = a.iloc[ia], b.iloc[ib]
    groups = scenario_of(common)
    kw = {"n_boot": ci.n_boot, "level": ci.level, "seed": ci.seed}
    out = {
        k: paired_mean_difference_ci(
            a[k.removesuffix("_mean")].to_numpy(),
            b[k.removesuffix("_mean")].to_numpy(),
            groups,
            **kw,
        )
        for k in ("kld_fou_mean", "kld_fo_mean")
    }
    codes, g = _codes(common)
    draws = _draws(g, ci)
    ea, ba = _pooled_dice(a, "occ", codes, g, draws)
    eb, bb = _pooled_dice(b, "occ", codes, g, draws)
    out["dice_occ"] = _interval(ea - eb, ba - bb, ci.level, g)
    if "reg_success" in a and "reg_success" in b:  # both estimate a pose: success-rate difference
        out["success_rate"] = paired_mean_difference_ci(
            a["reg_success"].to_numpy(np.float64),
            b["reg_success"].to_numpy(np.float64),
            groups,
            **kw,
        )
    return out, int(common.size)


def _lohi(iv: Interval) -> dict[str, float]:
    return {"lo": iv.lo, "hi": iv.hi}


# -- all methods ---------------------------------------------------------------------------------
def pose_bins(
    frame: pd.DataFrame, trans_bins_m: Sequence[float], rot_bins_deg: Sequence[float]
) -> tuple[dict[str, Any], pd.DataFrame]:
    """Metrics per method and bin of the drawn translation / rotation error (dict and table)."""
    from traffictwin.fusion.metrics import pose_error_bins

    noise = frame[["noise_dx", "noise_dy", "noise_dyaw"]].to_numpy()
    tb, rb, tl, rl = pose_error_bins(noise, trans_bins_m, rot_bins_deg)
    frame = frame.assign(trans_bin=[tl[i] for i in tb], rot_bin=[rl[i] for i in rb])
    out: dict[str, Any] = {"translation": {}, "rotation": {}}
    rows = []
    for axis, col, labels in (("translation", "trans_bin", tl), ("rotation", "rot_bin", rl)):
        for meth, g in frame.groupby("method", sort=False):
            out[axis][meth] = {}
            for lab in labels:
                sub = g[g[col] == lab]
                if len(sub):
                    agg = aggregate({k: sub[k].to_numpy() for k in sub.columns})
                    out[axis][meth][lab] = {k: agg[k] for k in BIN_KEYS if k in agg}
                    if "reg_success" in sub and sub["reg_success"].notna().all():
                        out[axis][meth][lab]["success_rate"] = float(
                            sub["reg_success"].astype(float).mean()
                        )
                    rows.append({"axis": axis, "bin": lab, "method": meth, **out[axis][meth][lab]})
    return out, pd.DataFrame(rows)


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


def evaluate(
    data: dict[str, dict[str, np.ndarray]],
    raw: dict[str, np.ndarray],
    networks: Mapping[str, Mapping[str, Any]],
    grid: GridSpec,
    cfg: FusionEvalConfig,
    ci: CIConfig,
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
    ``ci`` (see the module docstring).
    """
    configs = list(data)
    _check_networks(networks, configs)
    es = EvalSettings.from_config(cfg)
    n = len(next(iter(data.values()))["pair_id"])
    all_idx = np.arange(n)
    reg_idx = evenly_spaced(n, cfg.registered_max_pairs)
    cross_idx = evenly_spaced(n, cfg.cross_max_pairs)
    log.info(
        "evaluating %d pairs per configuration (%d for slow methods, %d cross) on %s; rows %s",
        n,
        len(reg_idx),
        len(cross_idx),
        configs,
        list(networks),
    )
    frames: list[pd.DataFrame] = []
    own: dict[tuple[str, str], pd.DataFrame] = {}  # (cfg, row) -> its per-pair frame
    metrics: dict[str, Any] = {
        "test": {},
        "diff": {},
        "label": {},
        "cross": {f"{r}-{c}": {} for r in CROSS_ROWS if r in networks for c in networks[r]},
    }
    kw = {"n_boot": ci.n_boot, "level": ci.level, "seed": ci.seed}
    for c in configs:
        d = data[c]
        base = FusionInput(
            inputs=d["inputs"],
            map1=raw["map1"],
            map2=raw["map2"],
            rel_pose_noisy=d["rel_pose_noisy"],
            rel_pose_true=d["rel_pose_true"],
            grid=grid,
            batch_size=cfg.batch_size,
            registration=cfg.registration_params,
            pair_key=np.arange(n),
            memo={},  # each registration once per pair, shared by the methods that use it
        )
        # the classical registration of the pairs the slow methods (registered, registered+network)
        # run on: once per pair, in parallel
        precompute_registrations(base.take(reg_idx), cfg.registration_workers)
        runs: list[tuple[str, FusionMethod, Any, str]] = [
            (name, m, None, "") for name, m in METHODS.items() if "model" not in m.needs
        ]
        runs += [
            (row, METHODS[row_method(row)], nets[c], c if row in CROSS_ROWS else row)
            for row, nets in networks.items()
            if c in nets
        ]
        metrics["test"][c] = {}
        for row, method, model, net in runs:
            idx = reg_idx if method.slow else all_idx
            x = base.take(idx)
            x.model = model
            f, au = evaluate_method(method, x, d["label"][idx], es)
            tagged = _tag(f, c, row, d, idx, network=net)
            frames.append(tagged)
            own[(c, row)] = tagged
            extra = method.summary(f, es) if method.summary else {}
            cis = row_intervals(tagged, *au.sample_histograms(), ci)
            metrics["test"][c][row] = {
                **_summary(f),
                "u_auroc": au.value(),
                **extra,
                **{f"{k}_ci": _lohi(iv) for k, iv in cis.items()},
            }
            if row in CROSS_ROWS:
                metrics["cross"][f"{row}-{c}"][c] = _cross_entry(f, au)
        # each other configuration's per-configuration network on this configuration's pairs
        # (cross table), on cfg.cross_max_pairs pairs
        for row in (r for r in CROSS_ROWS if r in networks):
            cidx = cross_idx
            for other, model in networks[row].items():
                if other == c:
                    continue
                x = base.take(cidx)
                x.model = model
                f, au = evaluate_method(METHODS[row_method(row)], x, d["label"][cidx], es)
                tagged = _tag(f, c, f"{row}-{other}", d, cidx, network=other)
                frames.append(tagged)
                own[(c, f"{row}-{other}")] = tagged
                metrics["cross"][f"{row}-{other}"][c] = _cross_entry(f, au)
        label_u = unknown_mass(np.asarray(d["label"], np.float64)).mean(axis=(1, 2))
        lu = mean_ci(label_u, scenario_of(d["pair_id"]), **kw)
        metrics["label"][c] = {"u_mean": lu.estimate, "u_mean_ci": _lohi(lu)}
        metrics["diff"][c] = {}
        for (cc, row), frame in own.items():
            if cc != c or _is_cross(row):
                continue
            for b in (*DIFF_BASELINES, *ROW_BASELINES.get(row, ())):
                if row == b or (c, b) not in own:
                    continue
                diffs, n_common = paired_intervals(frame, own[(c, b)], ci)
                metrics["diff"][c].setdefault(row, {})[f"vs_{b}"] = {
                    k: {"estimate": iv.estimate, "lo": iv.lo, "hi": iv.hi, "n_pairs": n_common}
                    for k, iv in diffs.items()
                }
        t = metrics["test"][c]
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
    samples = pd.concat(frames, ignore_index=True)
    main = samples[~samples["method"].map(_is_cross)]
    metrics["bins"], bins_table = pose_bins(main, cfg.trans_bins_m, cfg.rot_bins_deg)
    metrics["n_pairs"] = {
        "per_config": int(n),
        "registered": int(len(reg_idx)),
        "cross": int(len(cross_idx)),
    }
    metrics["bootstrap"] = {
        "n_boot": ci.n_boot,
        "seed": ci.seed,
        "level": ci.level,
        "cluster": f"scenario = pair_id // {SCENARIO_STRIDE}",
    }
    targets = fusion_targets(own, metrics, ci)
    metrics["targets"] = {k: v for k, v in targets.items() if k not in TIMING_TARGETS}
    timings = {
        "ms_per_pair": {
            c: {
                row: float(f["ms"].mean())
                for (cc, row), f in own.items()
                if cc == c and not _is_cross(row)
            }
            for c in configs
        },
        "runtime_ms_per_pair": {
            m: float(g["ms"].mean()) for m, g in main.groupby("method", sort=False)
        },
        "targets": {k: v for k, v in targets.items() if k in TIMING_TARGETS},
    }
    samples = samples.drop(columns="ms")
    return Evaluation(metrics, samples, bins_table, data, raw, networks, timings)


def _cross_entry(f: pd.DataFrame, au: UncertaintyAUROC) -> dict[str, float]:
    agg = aggregate({k: f[k].to_numpy() for k in f.columns})
    out = {k: agg[k] for k in CROSS_KEYS} | {"u_auroc": au.value()}
    if "reg_success" in f:
        out["success_rate"] = float(f["reg_success"].mean())
    return out


def _is_cross(row: str) -> bool:
    """Whether an evaluation row is a per-configuration network on another configuration
    (``dnn[per-config]-B``: the cross table)."""
    return any(row.startswith(f"{r}-") for r in CROSS_ROWS)


# -- targets (issue 14) --------------------------------------------------------------------------
@dataclass(frozen=True)
class Target:
    """One target: ``description``; ``threshold`` and the comparison ``op`` ("<=" or ">=") the
    point estimate must meet; ``configs`` it is judged at (None = every configuration);
    ``min_lo``: where set, the interval's lower end must also reach it."""

    description: str
    threshold: float
    op: str
    configs: tuple[str, ...] | None
    min_lo: float | None = None


TARGETS: dict[str, Target] = {
    "kld_ratio_vs_naive": Target(
        "network KLD(b) / naive KLD(b) (ratio of means, paired cluster-bootstrap CI)",
        0.3,
        "<=",
        ("C", "D"),
    ),
    "network_vs_registered": Target(
        "network − registered KLD(b) (paired): CI wholly below 0, and the Dice occ difference's CI "
        "not wholly below 0 (the plain network beats classical registration)",
        0.0,
        "<",
        ("C", "D"),
    ),
    "one_vs_per_config": Target(
        "the one network − the configuration's own network (dnn[per-config], the ablation) "
        "KLD(b), paired: upper CI bound",
        0.005,
        "<=",
        None,
    ),
    "dice_occ_at_A": Target("network Dice occ at A (pooled)", 0.99, ">=", ("A",)),
    "dice_occ_drop_A_to_D": Target(
        "relative drop of the network's Dice occ from A to D, 1 − Dice(D)/Dice(A)",
        0.10,
        "<=",
        ("D",),
    ),
    "dice_occ_vs_ego": Target(
        "network Dice occ − ego-only Dice occ (paired difference)", 0.0, ">=", None
    ),
    "u_auroc": Target("AUROC of the network's u for wrongly classified cells", 0.85, ">=", None),
    "u_mean_vs_label": Target(
        "|network mean u − label mean u| (paired over pairs)", 0.10, "<=", None
    ),
    "hybrid_vs_registered": Target(
        "registered+network − registered KLD(b) (paired): CI wholly below 0, and the Dice occ "
        "difference's CI not wholly below 0",
        0.0,
        "<",
        ("C", "D"),
    ),
}
# issue 15: the learned registration against the classical one (same pairs, paired intervals)
TARGETS.update(
    {
        "learned_success_vs_registered": Target(
            "learned − registered registration success rate (error < 0.5 m and < 1 deg; paired)",
            0.0,
            ">=",
            None,
        ),
        "learned_success_gain_at_D": Target(
            "learned − registered registration success rate at D (paired): estimate >= 0.10 and "
            "the CI's lower end >= 0.05",
            0.10,
            ">=",
            ("D",),
            min_lo=0.05,
        ),
        "learned_success_at_D": Target(
            "learned registration success rate at D (error < 0.5 m and < 1 deg)", 0.95, ">=", ("D",)
        ),
        "learned_kld_vs_registered": Target(
            "learned+network − registered KLD(b) (paired): CI wholly below 0, and the Dice occ "
            "difference's CI not wholly below 0",
            0.0,
            "<",
            ("C", "D"),
        ),
        "learned_runtime_ms": Target(
            "learned registration wall time per pair (estimate + fallback check + warp + Dempster, "
            "batches of evaluation.fusion.batch_size on the evaluation machine), ms",
            20.0,
            "<=",
            None,
        ),
    }
)
# targets judged on wall times: they differ between identical runs, so not in fusion.json
# (Evaluation.timings -> the stage's run record; the benchmark benchmarks/registration.py measures it)
TIMING_TARGETS = ("learned_runtime_ms",)
NOT_EVALUATED = "not evaluated"


def _judge(iv: Interval, threshold: float, op: str) -> dict[str, Any]:
    """Pass/fail of the point estimate against ``threshold``; ``ci_beyond_threshold``: the whole
    interval lies on the side of the verdict (the verdict is not noise)."""
    if op not in ("<=", ">="):
        raise ValueError(f"_judge: op must be '<=' or '>=', got {op!r}")
    e, lo, hi = iv.estimate, iv.lo, iv.hi
    if not math.isfinite(e):
        return {
            "value": e,
            "lo": lo,
            "hi": hi,
            "status": NOT_EVALUATED,
            "ci_beyond_threshold": False,
        }
    ok = e <= threshold if op == "<=" else e >= threshold
    if op == "<=":
        beyond = hi <= threshold if ok else lo > threshold
    else:
        beyond = lo >= threshold if ok else hi < threshold
    return {
        "value": e,
        "lo": lo,
        "hi": hi,
        "status": "pass" if ok else "fail",
        "ci_beyond_threshold": bool(beyond),
    }


def _missing(why: str) -> dict[str, Any]:
    return {"value": None, "lo": None, "hi": None, "status": NOT_EVALUATED, "why": why}


def _overall(per: Mapping[str, Mapping[str, Any]]) -> str:
    st = [v["status"] for v in per.values()]
    if not st:
        return NOT_EVALUATED
    if "fail" in st:
        return "fail"
    return NOT_EVALUATED if NOT_EVALUATED in st else "pass"


def fusion_targets(
    own: Mapping[tuple[str, str], pd.DataFrame], metrics: Mapping[str, Any], ci: CIConfig
) -> dict[str, Any]:
    """The targets of :data:`TARGETS` from the per-pair frames ``own[(cfg, row)]`` and the
    intervals already in ``metrics`` (``test``, ``diff``). A target whose configuration or rows
    were not evaluated is ``not evaluated`` (never ``pass``)."""
    configs = list(metrics["test"])
    kw = {"n_boot": ci.n_boot, "level": ci.level, "seed": ci.seed}
    out: dict[str, Any] = {}

    def frame(c: str, row: str) -> pd.DataFrame | None:
        return own.get((c, row))

    def entry(name: str, judge: Callable[[str], dict[str, Any]]) -> None:
        t = TARGETS[name]
        per = {c: judge(c) for c in (t.configs or configs)}
        out[name] = {
            "description": t.description,
            "threshold": t.threshold,
            "op": t.op,
            "status": _overall(per),
            "per_config": per,
        }

    def ratio(c: str) -> dict[str, Any]:
        n, b = frame(c, NETWORK), frame(c, "naive")
        if n is None or b is None:
            return _missing(f"configuration {c} or its dnn / naive rows not evaluated")
        _, ia, ib = np.intersect1d(n["pair_id"], b["pair_id"], return_indices=True)
        kn, kb = n["kld_fou"].to_numpy()[ia], b["kld_fou"].to_numpy()[ib]
        groups = scenario_of(n["pair_id"].to_numpy()[ia])

        def stat(i: np.ndarray) -> float:
            den = kb[i].mean()
            return float(kn[i].mean() / den) if den > 0 else math.nan

        t = TARGETS["kld_ratio_vs_naive"]
        return _judge(statistic_ci(stat, len(kn), groups, **kw), t.threshold, t.op)

    def value_ci(c: str, row: str, key: str, t: Target) -> dict[str, Any]:
        v = metrics["test"].get(c, {}).get(row)
        if v is None:
            return _missing(f"row {row} not evaluated at configuration {c}")
        b = v[f"{key}_ci"]
        return _judge(Interval(v[key], b["lo"], b["hi"], ci.level), t.threshold, t.op)

    def dice_drop(ref: pd.DataFrame, other: pd.DataFrame, what: str, t: Target) -> dict[str, Any]:
        """1 − Dice occ(other) / Dice occ(ref) on their common pairs, resampled together."""
        common, ir, io = np.intersect1d(ref["pair_id"], other["pair_id"], return_indices=True)
        codes, g = _codes(common)
        draws = _draws(g, ci)
        er, br = _pooled_dice(ref.iloc[ir], "occ", codes, g, draws)
        eo, bo = _pooled_dice(other.iloc[io], "occ", codes, g, draws)
        if not er > 0:  # reference Dice = 0 or undefined: no relative drop
            return _missing(f"{what} is {er}: the relative drop is undefined")
        with np.errstate(invalid="ignore", divide="ignore"):  # resamples with Dice 0 drop out
            iv = _interval(1.0 - eo / er, 1.0 - bo / br, ci.level, g)
        return _judge(iv, t.threshold, t.op)

    def drop(c: str) -> dict[str, Any]:
        a, d = frame("A", NETWORK), frame(c, NETWORK)
        if a is None or d is None:
            return _missing("configurations A and D both needed")
        return dice_drop(a, d, "network Dice occ at A", TARGETS["dice_occ_drop_A_to_D"])

    def vs_ego(c: str) -> dict[str, Any]:
        n, e = frame(c, NETWORK), frame(c, "ego")
        if n is None or e is None:
            return _missing(f"dnn or ego not evaluated at configuration {c}")
        diffs, _ = paired_intervals(n, e, ci)
        t = TARGETS["dice_occ_vs_ego"]
        return _judge(diffs["dice_occ"], t.threshold, t.op)

    def u_gap(c: str) -> dict[str, Any]:
        n = frame(c, NETWORK)
        if n is None:
            return _missing(f"dnn not evaluated at configuration {c}")
        d = paired_mean_difference_ci(
            n["u_mean"].to_numpy(), n["label_u_mean"].to_numpy(), scenario_of(n["pair_id"]), **kw
        )
        # |difference|: the interval of |d| from the interval of d
        lo, hi = (
            (d.lo, d.hi) if d.lo >= 0 else (-d.hi, -d.lo) if d.hi <= 0 else (0.0, max(-d.lo, d.hi))
        )
        t = TARGETS["u_mean_vs_label"]
        res = _judge(Interval(abs(d.estimate), lo, hi, d.level, d.n_groups), t.threshold, t.op)
        res["signed_difference"] = {"estimate": d.estimate, "lo": d.lo, "hi": d.hi}
        return res

    def beats_registered(c: str, row: str, name: str) -> dict[str, Any]:
        """KLD(b) of ``row`` − registered: interval wholly below target ``name``'s threshold (op
        ``<``), Dice occ difference not wholly below 0 (not shown worse)."""
        t = TARGETS[name]
        if t.op != "<":
            raise ValueError(
                f"target {name}: op must be '<' (the interval's upper end), got {t.op!r}"
            )
        dd = metrics["diff"].get(c, {}).get(row, {}).get("vs_registered")
        if not dd:
            return _missing(f"rows {row} and registered not both evaluated at configuration {c}")
        k, dc = dd[HEADLINE], dd["dice_occ"]
        if not all(math.isfinite(x) for x in (k["lo"], k["hi"], dc["lo"], dc["hi"])):
            return _missing(f"no interval of the {row} − registered difference at {c}")
        below = k["hi"] < t.threshold  # KLD(b) lower, shown
        ok = below and not dc["hi"] < 0  # and Dice occ not shown lower
        return {
            "value": k["estimate"],
            "lo": k["lo"],
            "hi": k["hi"],
            "status": "pass" if ok else "fail",
            "ci_beyond_threshold": bool(below),
            "dice_occ_difference": {"estimate": dc["estimate"], "lo": dc["lo"], "hi": dc["hi"]},
        }

    entry("kld_ratio_vs_naive", ratio)
    entry("dice_occ_at_A", lambda c: value_ci(c, NETWORK, "dice_occ", TARGETS["dice_occ_at_A"]))
    entry("dice_occ_drop_A_to_D", drop)
    entry("dice_occ_vs_ego", vs_ego)
    entry("u_auroc", lambda c: value_ci(c, NETWORK, "u_auroc", TARGETS["u_auroc"]))
    entry("u_mean_vs_label", u_gap)
    entry("hybrid_vs_registered", lambda c: beats_registered(c, HYBRID, "hybrid_vs_registered"))
    entry("network_vs_registered", lambda c: beats_registered(c, NETWORK, "network_vs_registered"))

    def one_vs_per_config(c: str) -> dict[str, Any]:
        dd = metrics["diff"].get(c, {}).get(NETWORK, {}).get(f"vs_{PER_CONFIG_NETWORK}")
        if not dd:
            return _missing(
                f"no {PER_CONFIG_NETWORK} network at configuration {c} (the ablation "
                "`make ablations` (ablation per_config) trains them)"
            )
        k = dd[HEADLINE]
        t = TARGETS["one_vs_per_config"]
        # judged on the interval's upper bound: the one network is not shown worse by more
        res = _judge(Interval(k["hi"], k["lo"], k["hi"], ci.level), t.threshold, t.op)
        res["difference"] = {"estimate": k["estimate"], "lo": k["lo"], "hi": k["hi"]}
        return res

    entry("one_vs_per_config", one_vs_per_config)

    def learned_success(c: str, name: str) -> dict[str, Any]:
        dd = (
            metrics["diff"].get(c, {}).get(LEARNED, {}).get("vs_registered", {}).get("success_rate")
        )
        if not dd:
            return _missing(
                f"rows {LEARNED} and registered not both evaluated at configuration {c}"
            )
        t = TARGETS[name]
        res = _judge(Interval(dd["estimate"], dd["lo"], dd["hi"], ci.level), t.threshold, t.op)
        if t.min_lo is not None and res["status"] == "pass" and not dd["lo"] >= t.min_lo:
            res["status"] = "fail"  # the gain is not shown: its interval reaches below min_lo
        res["n_pairs"] = dd["n_pairs"]
        return res

    def learned_rate(c: str) -> dict[str, Any]:
        v = metrics["test"].get(c, {}).get(LEARNED)
        f = frame(c, LEARNED)
        if v is None or f is None:
            return _missing(f"{LEARNED} not evaluated at configuration {c}")
        iv = mean_ci(f["reg_success"].to_numpy(np.float64), scenario_of(f["pair_id"]), **kw)
        t = TARGETS["learned_success_at_D"]
        return _judge(iv, t.threshold, t.op)

    def learned_ms(c: str) -> dict[str, Any]:
        f = frame(c, LEARNED)
        if f is None:
            return _missing(f"{LEARNED} not evaluated at configuration {c}")
        iv = mean_ci(f["ms"].to_numpy(np.float64), scenario_of(f["pair_id"]), **kw)
        t = TARGETS["learned_runtime_ms"]
        return _judge(iv, t.threshold, t.op)

    entry(
        "learned_success_vs_registered",
        lambda c: learned_success(c, "learned_success_vs_registered"),
    )
    entry("learned_success_gain_at_D", lambda c: learned_success(c, "learned_success_gain_at_D"))
    entry("learned_success_at_D", learned_rate)
    entry(
        "learned_kld_vs_registered",
        lambda c: beats_registered(c, LEARNED_NETWORK, "learned_kld_vs_registered"),
    )
    entry("learned_runtime_ms", learned_ms)
    return out


# -- outputs (JSON-safe values: traffictwin.io.jsonio.json_clean) -------------------------------
def qualitative_panels(
    ev: Evaluation,
    noise: Mapping[str, PoseNoise],
    grid: GridSpec,
    pair: int,
    fraction: float,
) -> dict[str, list[np.ndarray]]:
    """Fig. 4 panels (label / naive / network, one per configuration) of evaluated pair ``pair``:
    map 2 prealigned with a pose error of ``fraction``·(r, r, α) of each configuration."""
    from traffictwin.config import ConfigError
    from traffictwin.evidential.dempster import dempster
    from traffictwin.fusion.model_io import predict_masses
    from traffictwin.fusion.pairs import prealign

    if pair >= len(ev.raw["map1"]):
        raise ConfigError(
            f"params.yaml: 'evaluation.fusion.qualitative_pair' = {pair} but only "
            f"{len(ev.raw['map1'])} pairs are evaluated"
        )
    m1, m2 = ev.raw["map1"][pair], ev.raw["map2"][pair]
    pose1, pose2 = ev.raw["pose1"][pair], ev.raw["pose2"][pair]
    k = fraction
    rows: dict[str, list[np.ndarray]] = {"label": [], "naive": [], "network": []}
    for c in ev.data:
        r, alpha = noise[c].r, noise[c].alpha
        err = np.array([k * r, k * r, np.radians(k * alpha)])
        warped, _ = prealign(m2, pose1, pose2, grid, noise=err)
        inputs = np.concatenate([m1, warped])[None].astype(np.float32)
        rows["label"].append(ev.raw["label"][pair])
        rows["naive"].append(np.asarray(dempster(m1, warped)))
        rows["network"].append(predict_masses(ev.networks[NETWORK][c], inputs, 1)[0][0])
    return rows


def _rows(ev: Evaluation, base: Sequence[str]) -> list[str]:
    """``base`` methods plus every network row of ``ev`` not among them (variants, in order)."""
    return [*base, *(r for r in ev.networks if r not in base)]


def plot_tables(ev: Evaluation, noise: Mapping[str, PoseNoise]) -> dict[str, pd.DataFrame]:
    """DVC plot data: ``fusion_kld`` (per pair), ``fusion_scores`` (per configuration and row),
    ``fusion_pose_bins`` (per bin)."""
    samples = ev.samples
    main = samples[~samples["method"].str.startswith(f"{NETWORK}-")]
    score_rows = []
    for c in ev.data:
        row: dict[str, Any] = {
            "config": c,
            "noise_r_m": noise[c].r,
            "noise_alpha_deg": noise[c].alpha,
        }
        for m in _rows(ev, SCORE_METHODS):
            for key in SCORE_KEYS:
                row[f"{m}_{key}"] = ev.metrics["test"][c].get(m, {}).get(key)
        score_rows.append(row)
    return {
        "fusion_kld": main[
            ["config", "method", "pair_id", "kld_fou", "kld_fo", "trans_err_m", "rot_err_deg"]
        ],
        "fusion_scores": pd.DataFrame(score_rows),
        "fusion_pose_bins": ev.bins,
    }


def figures(
    ev: Evaluation,
    noise: Mapping[str, PoseNoise],
    grid: GridSpec,
    pair: int,
    fraction: float,
) -> dict[str, Any]:
    """The evaluation's matplotlib figures by file stem: ``fusion_kld_boxplot`` (KLD(b); cf. Fig. 5),
    ``fusion_scores_occupied`` / ``fusion_scores_free`` (Figs. 6, 7), ``fusion_qualitative`` (Fig. 4).
    Network rows of ``fusion_variants`` appear beside the methods where they exist."""
    from traffictwin.fusion.figures import kld_boxplot, scores_plot
    from traffictwin.fusion.map_figures import qualitative_grid

    configs = list(ev.data)
    samples = ev.samples
    main = samples[~samples["method"].str.startswith(f"{NETWORK}-")]
    n = ev.metrics["n_pairs"]
    box_rows = _rows(ev, FIGURE_METHODS)
    kvals = {
        m: {c: main[(main.method == m) & (main.config == c)]["kld_fou"].to_numpy() for c in configs}
        for m in box_rows
    }
    score_rows = _rows(ev, SCORE_METHODS)
    scores = {m: {c: ev.metrics["test"][c].get(m, {}) for c in configs} for m in score_rows}
    slow = "" if n["registered"] == n["per_config"] else f"; registered on {n['registered']}"
    r_alpha = {c: (noise[c].r, noise[c].alpha) for c in configs}
    return {
        "fusion_kld_boxplot": kld_boxplot(
            kvals,
            configs,
            box_rows,
            ylabel="KLD(b): KL(label ‖ prediction) over (m_F, m_O, u)",
            title=f"KLD(b) per configuration (test set, {n['per_config']} pairs{slow})",
            noise=r_alpha,
        ),
        "fusion_scores_occupied": scores_plot(scores, configs, score_rows, "occ", r_alpha),
        "fusion_scores_free": scores_plot(scores, configs, score_rows, "free", r_alpha),
        "fusion_qualitative": qualitative_grid(
            qualitative_panels(ev, noise, grid, pair, fraction),
            configs,
            grid.cell,
            title=f"pair {int(ev.data[configs[0]]['pair_id'][pair])}: pose error = "
            f"{fraction:.0%} of (r, r, α)",
            noise=r_alpha,
        ),
    }


def _mlflow_key(key: str) -> str:
    """MLflow metric names allow letters, digits, ``_ - . / `` and space: others become ``_``."""
    return re.sub(r"[^\w\-./ ]", "_", key)


def _flat_row(vals: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """One row's numbers with intervals ``<k>_ci: {lo, hi}`` as ``<k>_ci_lo`` / ``<k>_ci_hi``."""
    flat: dict[str, Any] = {}
    for k, v in vals.items():
        if isinstance(v, Mapping):
            flat.update({f"{prefix}{k}_{kk}": vv for kk, vv in v.items()})
        else:
            flat[f"{prefix}{k}"] = v
    return flat


def mlflow_metrics(
    metrics: Mapping[str, Any], cfg: str, row: str = NETWORK, prefix: str = "test/"
) -> dict[str, float]:
    """The flat numbers of the MLflow run of row ``row``'s network at configuration ``cfg``:
    ``<prefix><k>`` (that network only; the other methods go to :func:`methods_table`),
    ``cross_<other>/<k>`` (the network on other configurations; rows of :data:`CROSS_ROWS`
    only); intervals ``<k>_ci`` as ``<k>_ci_lo`` / ``<k>_ci_hi``; finite values only, names
    MLflow-safe."""
    flat = _flat_row(metrics["test"][cfg].get(row, {}), prefix)
    if row in CROSS_ROWS:
        for other, vals in metrics["cross"].get(f"{row}-{cfg}", {}).items():
            flat.update({f"cross_{other}/{k}": v for k, v in vals.items()})
    out: dict[str, float] = {}
    for k, v in flat.items():
        if (
            isinstance(v, (bool, int, float, np.number))
            and v is not None
            and math.isfinite(float(v))
        ):
            out[_mlflow_key(k)] = float(v)
    return out


def methods_table(metrics: Mapping[str, Any], cfg: str) -> pd.DataFrame:
    """Every method's and network row's test numbers at configuration ``cfg``, one row each
    (column ``method`` first, then the metrics sorted; intervals as ``<k>_ci_lo`` / ``<k>_ci_hi``;
    missing or non-finite values empty): the baselines' table artifact of a network's run."""
    rows = [{"method": m, **_flat_row(vals)} for m, vals in metrics["test"][cfg].items()]
    frame = pd.DataFrame(rows)
    cols = ["method", *sorted(c for c in frame.columns if c != "method")]
    return frame[cols]
