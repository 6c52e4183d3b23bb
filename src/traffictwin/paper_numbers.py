"""Numbers and claims the two papers report, with where they print them: the only numbers typed
in by hand (the report shows them beside this run's, which come from metrics files). The papers'
data differ from ours (VTD and GTA V at real scale, vs the project's own simulator), so the
comparison is of trends and rankings. Outside ``traffictwin.report``: the risk evaluation writes
its differences to the paper into risk.json (:data:`traffictwin.risk.evaluation.scoring.PAPER`).
The papers are in ``shared/seeds/`` beside the repository; the fusion paper prints no numbers
(Fig. 5 KLD box plots, Figs. 6/7 score curves), so it enters as qualitative claims.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class PaperNumber:
    """One reported value: ``value`` in ``unit``, where it is printed (``source``), what it means."""

    value: Any
    unit: str
    source: str
    note: str = ""


@dataclass(frozen=True)
class PaperClaim:
    """A qualitative result of a paper (a sentence about a figure), keyed for the findings / report."""

    text: str
    source: str


# --------------------------------------------------------------------------- fusion (van Kempen et al.)
FUSION_CITATION = (
    "van Kempen et al., Combined Registration and Fusion of Evidential Occupancy Grid Maps "
    "for Live Digital Twins of Traffic (RWTH Aachen, ika)"
)

# Configurations A-D (Fig. 3): 98 % intervals r (m) and alpha (deg).
FUSION_CONFIGURATIONS: dict[str, tuple[float, float]] = {
    "A": (0.0, 0.0),
    "B": (1.0, 10.0),
    "C": (2.5, 15.0),
    "D": (5.0, 20.0),
}

FUSION_CLAIMS: dict[str, PaperClaim] = {
    "kld_A_baseline_better": PaperClaim(
        "Without pose noise (A) the network is, on average, worse than the naive fusion (KLD).",
        "Sec. V-A, Fig. 5",
    ),
    "kld_BCD_net_better": PaperClaim(
        "With pose noise (B, C, D) the network's KLD is much better than the naive fusion's.",
        "Sec. V-A, Fig. 5",
    ),
    "kld_baseline_degrades_faster": PaperClaim(
        "The naive fusion's KLD degrades much faster and stronger with growing noise.",
        "Sec. V-A, Fig. 5",
    ),
    "kld_net_less_spread": PaperClaim(
        "The network's KLD varies much less over the test set (more reliable).", "Sec. V-A, Fig. 5"
    ),
    "scores_A_baseline_better": PaperClaim(
        "Without uncertainty all precision / recall / Dice scores are better for the naive fusion.",
        "Sec. V-A, Figs. 6-7",
    ),
    "scores_flatter_net": PaperClaim(
        "All scores decrease with noise; the network's curves are much flatter.",
        "Sec. V-A, Figs. 6-7",
    ),
    "scores_net_dominant_except": PaperClaim(
        "With growing noise the network dominates most scores, except precision (occupied) and "
        "recall (free), a consequence of o_w = 3.",
        "Sec. V-A, Figs. 6-7; Sec. VI",
    ),
}

# --------------------------------------------------------------------------- risk (Feth et al.)
RISK_CITATION = (
    "Feth et al., Dynamic Risk Assessment for Vehicles of Higher Automation Levels by Deep Learning "
    "(Fraunhofer IESE / DFKI)"
)

# Table 1: the CNN's confusion matrix over the whole effective data set, critical <=> THW < 1.5 s
RISK_CONFUSION = {
    "tp": PaperNumber(67_052, "situations", "Table 1", "predicted critical, actually critical"),
    "fp": PaperNumber(19_069, "situations", "Table 1", "predicted critical, actually uncritical"),
    "fn": PaperNumber(9_737, "situations", "Table 1", "predicted uncritical, actually critical"),
    "tn": PaperNumber(10_312, "situations", "Table 1", "predicted uncritical, actually uncritical"),
}

RISK: dict[str, PaperNumber] = {
    "test_mse": PaperNumber(0.01470, "MSE (normalised risk)", "Sec. 4", "'testing average error'"),
    "accuracy": PaperNumber(72.87, "%", "Sec. 4, Table 1", "critical vs uncritical at THW 1.5 s"),
    "wang_kato_accuracy": PaperNumber(
        70.77, "%", "Sec. 4 (ref. [20])", "Wang & Kato, DICTA 2017: dashcam risk rating, other task"
    ),
    "n_frames": PaperNumber(110_152, "stereo frames recorded", "Sec. 3.3, 3.5"),
    "n_effective": PaperNumber(106_170, "frames after the ORB filter", "Sec. 3.5"),
    "orb_outlier_pct": PaperNumber(3.5, "% of pairs flagged by ORB (approx.)", "Sec. 3.3"),
    "n_critical": PaperNumber(76_789, "critical situations", "Sec. 4"),
    "split": PaperNumber("70:10:20", "train:val:test (random)", "Sec. 3.5"),
    "epochs": PaperNumber(30, "epochs", "Sec. 3.5", "validation error rises after ~15"),
    "batch_size": PaperNumber(10, "", "Sec. 3.5"),
    "thw_threshold_s": PaperNumber(1.5, "s", "Sec. 4"),
}


def risk_confusion_derived() -> dict[str, float]:
    """Scores derived from :data:`RISK_CONFUSION` and the frame counts, in %: the accuracy
    reproduces the paper's 72.87 % (the table is read the right way round)."""
    tp, fp, fn, tn = (RISK_CONFUSION[k].value for k in ("tp", "fp", "fn", "tn"))
    n = tp + fp + fn + tn
    return {
        "n": float(n),
        "accuracy_pct": 100.0 * (tp + tn) / n,
        "precision_critical_pct": 100.0 * tp / (tp + fp),
        "recall_critical_pct": 100.0 * tp / (tp + fn),
        "critical_share_pct": 100.0 * (tp + fn) / n,
        "orb_outlier_pct": 100.0 * (1 - RISK["n_effective"].value / RISK["n_frames"].value),
        "n_dropped": float(RISK["n_frames"].value - RISK["n_effective"].value),
        **{f"share_{k}_pct": 100.0 * RISK_CONFUSION[k].value / n for k in ("tp", "fp", "fn", "tn")},
    }
