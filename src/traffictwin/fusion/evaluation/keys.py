"""Names of the fusion evaluation: its rows (methods and network rows), the metric keys of each
block of ``fusion.json``, the per-sample settings and the bootstrap cluster (the scenario)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from traffictwin.config import typed
from traffictwin.fusion.config import FusionEvalConfig
from traffictwin.stats import CIConfig

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
LEARNED_REFINED = "learned-refined"  # the learned registration refined by ECC (+ Dempster)
LEARNED_REFINED_NETWORK = "learned-refined+network"
# rows whose networks (one per configuration) are also run on the other configurations: cross
# entries "<row>-<net>"
CROSS_ROWS = (PER_CONFIG_NETWORK,)


@dataclass(frozen=True)
class EvalSettings:
    """How per-sample metrics are computed (units in the names)."""

    batch_size: int = 8
    kld_eps: float = 1e-7
    auroc_bins: int = 4096
    success_trans_m: float = field(kw_only=True)  # m: registration succeeds within this ...
    success_rot_deg: float = field(kw_only=True)  # ... and this (deg)
    auroc_min_wrong: int = 100  # AUROC(u) withheld below this many wrong cells ...
    auroc_min_pairs: int = 10  # ... or with wrong cells in fewer pairs than this

    @classmethod
    def from_config(cls, c: FusionEvalConfig) -> EvalSettings:
        return cls(
            c.batch_size,
            c.kld_eps,
            c.auroc_bins,
            c.auroc_min_wrong,
            c.auroc_min_pairs,
            success_trans_m=c.success_trans_m,
            success_rot_deg=c.success_rot_deg,
        )


def fusion_ci_config(cfg: Any) -> CIConfig:
    """``evaluation.fusion_ci`` of params.yaml, checked."""
    return typed(cfg["evaluation"]["fusion_ci"], CIConfig, key="evaluation.fusion_ci")


def row_method(row: str) -> str:
    """The registry method of an evaluation row: ``"dnn[paper]"`` → ``"dnn"``."""
    return row.split("[")[0]


def scenario_of(pair_id: np.ndarray) -> np.ndarray:
    """Scenario of each pair, ``pair_id // 1000`` (int64): the bootstrap cluster."""
    return np.asarray(pair_id, dtype=np.int64) // SCENARIO_STRIDE


def is_cross(row: str) -> bool:
    """Whether an evaluation row is a per-configuration network on another configuration
    (``dnn[per-config]-B``: the cross table)."""
    return any(row.startswith(f"{r}-") for r in CROSS_ROWS)
