"""Seed replicates of the fusion claims: the network and the learned registration trained with
several training seeds on the same data, every run evaluated on the same test pairs, and the
claims re-stated with intervals over seeds × scenarios.

Input: per run (seed), the per-pair evaluation samples of ``reports/fusion_eval_samples.csv``
(stage evaluate_fusion; :func:`pair_table` keeps the columns used here). Rows that a training
seed changes (:data:`SEED_ROWS`: the network, the learned registration and what builds on them)
differ between runs; the classical rows (:data:`FIXED_ROWS`) are the same in every run and are
read from the first.

Interval: each bootstrap resample draws the scenarios (``pair_id // 1000``, the same draws as
the single-seed intervals of :mod:`.intervals`) and, independently, the seeds with replacement;
the statistic is the mean over the drawn seeds of each seed's statistic on the drawn scenarios
(training randomness and scenario sampling both in the interval). With one seed it reduces to
the single-seed scenario bootstrap, resample by resample.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from traffictwin.fusion.evaluation.intervals import (
    lohi,
    percentile_interval,
    scenario_codes,
    scenario_draws,
)
from traffictwin.fusion.metrics import prf
from traffictwin.stats import CIConfig, Interval, excludes_zero, resample_counts

# rows a training seed changes, and classical rows every run shares (evaluate_fusion's methods)
SEED_ROWS = (
    "dnn",
    "learned",
    "learned-refined",
    "learned+network",
    "learned-refined+network",
    "registered+network",
)
FIXED_ROWS = ("registered", "naive")
PAIR_COLUMNS = (
    "config",
    "method",
    "pair_id",
    "kld_fou",
    "tp_occ",
    "fp_occ",
    "fn_occ",
    "reg_success",
)
POSE_ROWS = ("learned", "learned-refined", "registered")  # rows with a pose success per pair
SEED_STREAM = 7919  # the seed draws' RNG seed = ci.seed + this (independent of the scenario draws)

# the comparisons the report states (a − b, metric, configurations): the network against the
# classical registration and the naive fusion, the learned registration's success against the
# classical one's, and the learned pose + network against the classical registration
COMPARISONS: tuple[tuple[str, str, str, tuple[str, ...]], ...] = (
    ("dnn", "registered", "kld_fou_mean", ("A", "B", "C", "D")),
    ("dnn", "naive", "kld_fou_mean", ("B", "C", "D")),
    ("learned", "registered", "success_rate", ("B", "C", "D")),
    ("learned-refined", "registered", "success_rate", ("B", "C", "D")),
    ("learned+network", "registered", "kld_fou_mean", ("A", "B", "C", "D")),
    ("learned-refined+network", "registered", "kld_fou_mean", ("A", "B", "C", "D")),
)


def pair_table(samples: pd.DataFrame, source: str = "fusion_eval_samples.csv") -> pd.DataFrame:
    """The columns and rows of an evaluation's per-pair samples that the seed comparison reads,
    sorted by configuration, method and pair; ``source`` names the file in errors."""
    missing = [c for c in PAIR_COLUMNS if c not in samples.columns]
    if missing:
        raise ValueError(f"{source}: missing column(s) {missing}; expected {list(PAIR_COLUMNS)}")
    keep = samples[samples["method"].isin(SEED_ROWS + FIXED_ROWS)]
    return (
        keep[list(PAIR_COLUMNS)]
        .sort_values(["config", "method", "pair_id"], kind="stable")
        .reset_index(drop=True)
    )


@dataclass(frozen=True)
class SeedBootstrap:
    """Resample plan over seeds × scenarios for ``n_seeds`` runs scored on the pairs ``pair_id``."""

    codes: np.ndarray  # (n,) scenario code of each pair
    n_groups: int
    draws: np.ndarray  # (n_boot, G) scenario counts
    seed_weights: np.ndarray  # (n_boot, S) how often each seed is drawn
    level: float

    @classmethod
    def plan(cls, pair_id: np.ndarray, n_seeds: int, ci: CIConfig) -> SeedBootstrap:
        codes, g = scenario_codes(np.asarray(pair_id, np.int64))
        draws = scenario_draws(g, ci).astype(np.float64)
        if n_seeds == 1:  # every resample keeps the one seed: the single-seed bootstrap
            w = np.ones((ci.n_boot, 1))
        else:
            w = resample_counts(n_seeds, ci.n_boot, ci.seed + SEED_STREAM).astype(np.float64)
        return cls(codes, g, draws, w, ci.level)

    def _sums(self, values: np.ndarray) -> np.ndarray:
        """(S, G) per-seed per-scenario sums of ``values`` (S, n)."""
        onehot = np.zeros((self.n_groups, self.codes.size))
        onehot[self.codes, np.arange(self.codes.size)] = 1.0
        return np.asarray(values, np.float64) @ onehot.T

    def _over_seeds(self, per_seed: np.ndarray) -> np.ndarray:
        """(n_boot,) seed-drawn mean of (n_boot, S) per-seed resampled statistics."""
        w = self.seed_weights
        return (per_seed * w).sum(axis=1) / w.sum(axis=1)

    def mean(self, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per-seed means (S,) of ``values`` (S, n) and the seeds × scenarios resamples (n_boot,)."""
        v = np.atleast_2d(np.asarray(values, np.float64))
        counts = self.draws @ np.bincount(self.codes, minlength=self.n_groups).astype(np.float64)
        per_seed = (self.draws @ self._sums(v).T) / np.maximum(counts, 1e-12)[:, None]
        return v.mean(axis=1), self._over_seeds(per_seed)

    def dice(self, tp: np.ndarray, fp: np.ndarray, fn: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per-seed pooled Dice (S,) of per-pair counts (S, n) and the resamples (n_boot,)."""
        tp, fp, fn = (np.atleast_2d(np.asarray(x, np.float64)) for x in (tp, fp, fn))
        est = prf(tp.sum(axis=1), fp.sum(axis=1), fn.sum(axis=1))[2]
        st, sf, sn = (self.draws @ self._sums(x).T for x in (tp, fp, fn))
        return np.asarray(est, np.float64), self._over_seeds(prf(st, sf, sn)[2])

    def interval(self, per_seed: np.ndarray, boot: np.ndarray) -> Interval:
        return percentile_interval(float(np.mean(per_seed)), boot, self.level, self.n_groups)


def _verdict(iv: Interval) -> str:
    if not excludes_zero(iv):
        return "no difference shown"
    return "lower" if iv.hi < 0 else "higher"


def _blocks(
    runs: Sequence[pd.DataFrame], names: Sequence[str], cfg: str, row: str
) -> list[pd.DataFrame]:
    """The per-pair samples of ``row`` at ``cfg``: one block per seed for a seed row, the first
    run's alone for a classical row; pair order checked equal (the same test pairs everywhere)."""
    use = runs if row in SEED_ROWS else runs[:1]
    blocks = [r[(r["config"] == cfg) & (r["method"] == row)] for r in use]
    ref = blocks[0]["pair_id"].to_numpy(np.int64)
    for name, b in zip(names, blocks, strict=False):
        if not np.array_equal(b["pair_id"].to_numpy(np.int64), ref):
            raise ValueError(
                f"seed run {name!r}: row {row!r} at configuration {cfg} has other test pairs "
                f"({len(b)}) than run {names[0]!r} ({ref.size}); every seed must be evaluated "
                "on the same pairs"
            )
    return blocks


def _matrix(blocks: Sequence[pd.DataFrame], column: str, n_seeds: int) -> np.ndarray:
    """(n_seeds, n) values of ``column`` of the first ``n_seeds`` blocks; a classical row (one
    block) is the same for every seed."""
    v = np.stack([b[column].to_numpy(np.float64) for b in blocks[:n_seeds]])
    return np.repeat(v, n_seeds, axis=0) if v.shape[0] == 1 else v


def _metric(
    plan: SeedBootstrap, blocks: Sequence[pd.DataFrame], metric: str, n_seeds: int
) -> tuple[np.ndarray, np.ndarray]:
    """Per-seed values (n_seeds,) and resamples of ``metric`` (KLD(b), occupied Dice, success)."""
    if metric == "kld_fou_mean":
        return plan.mean(_matrix(blocks, "kld_fou", n_seeds))
    if metric == "success_rate":
        return plan.mean(_matrix(blocks, "reg_success", n_seeds))
    if metric == "dice_occ":
        return plan.dice(*(_matrix(blocks, f"{k}_occ", n_seeds) for k in ("tp", "fp", "fn")))
    raise ValueError(f"unknown seed metric {metric!r}")


def _entry(plan: SeedBootstrap, per_seed: np.ndarray, boot: np.ndarray) -> dict[str, Any]:
    iv = plan.interval(per_seed, boot)
    return {
        "estimate": iv.estimate,
        **lohi(iv),
        "per_seed": [float(x) for x in per_seed],
        "seed_sd": float(np.std(per_seed, ddof=1)) if per_seed.size > 1 else 0.0,
    }


def seed_replicates(
    runs: Mapping[str, pd.DataFrame], ci: CIConfig, configurations: Sequence[str]
) -> dict[str, Any]:
    """Every seed row's KLD(b), occupied Dice and (pose rows) success per configuration, and the
    :data:`COMPARISONS` as paired differences, each with its seeds × scenarios interval, beside
    the first run's single-seed interval and verdict (``holds``: the verdict is the same):
    ``rows.<cfg>.<row>.<metric>``, ``findings.<a>_vs_<b>.<metric>.<cfg>.{single_seed, seeds, holds}``.
    ``runs``: ``{name: pair_table}``, the default run first."""
    names = list(runs)
    if len(names) < 2:
        raise ValueError(f"seed replicates need at least 2 runs, got {names}")
    frames = [pair_table(runs[n], n) for n in names]
    S = len(frames)
    rows: dict[str, dict[str, Any]] = {}
    for cfg in configurations:
        for row in SEED_ROWS:
            blocks = _blocks(frames, names, cfg, row)
            if blocks[0].empty:
                continue
            plan = SeedBootstrap.plan(blocks[0]["pair_id"].to_numpy(), S, ci)
            metrics = ("kld_fou_mean", "dice_occ") + (("success_rate",) if row in POSE_ROWS else ())
            rows.setdefault(cfg, {})[row] = {
                m: _entry(plan, *_metric(plan, blocks, m, S)) for m in metrics
            }
    findings: dict[str, dict[str, dict[str, Any]]] = {}
    for a, b, metric, cfgs in COMPARISONS:
        for cfg in (c for c in cfgs if c in configurations):
            ba_, bb_ = _blocks(frames, names, cfg, a), _blocks(frames, names, cfg, b)
            if ba_[0].empty or bb_[0].empty:
                continue
            pid = ba_[0]["pair_id"].to_numpy()
            if not np.array_equal(pid, bb_[0]["pair_id"].to_numpy()):
                raise ValueError(f"rows {a!r} and {b!r} at {cfg} were evaluated on other pairs")
            out: dict[str, Any] = {}
            for key, k in (("single_seed", 1), ("seeds", S)):
                plan = SeedBootstrap.plan(pid, k, ci)
                ea, boot_a = _metric(plan, ba_, metric, k)
                eb, boot_b = _metric(plan, bb_, metric, k)
                iv = plan.interval(ea - eb, boot_a - boot_b)
                out[key] = {"estimate": iv.estimate, **lohi(iv), "verdict": _verdict(iv)}
            out["holds"] = out["single_seed"]["verdict"] == out["seeds"]["verdict"]
            findings.setdefault(f"{a}_vs_{b}", {}).setdefault(metric, {})[cfg] = out
    return {
        "seeds": names,
        "n_boot": ci.n_boot,
        "level": ci.level,
        "resampled": "seeds (with replacement) x scenarios (pair_id // 1000)",
        "rows": rows,
        "findings": findings,
    }
