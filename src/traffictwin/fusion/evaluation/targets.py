"""The fusion evaluation's targets (network and registration): each target's figure with its
cluster-bootstrap interval, judged per configuration (:class:`Verdict`), from the per-pair frames
and the intervals already computed (:class:`TargetInputs`), against the acceptance thresholds the
stage passes in (``acceptance.fusion``, :mod:`traffictwin.acceptance`). Status ``pass`` /
``fail`` / ``not evaluated`` (a target whose configuration or rows were not evaluated: never
``pass``)."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from traffictwin.acceptance import FAIL, NOT_EVALUATED, Threshold
from traffictwin.acceptance import judge as judge_threshold
from traffictwin.fusion.evaluation.intervals import (
    ci_kwargs,
    paired_intervals,
    percentile_interval,
    pooled_dice,
    scenario_codes,
    scenario_draws,
)
from traffictwin.fusion.evaluation.keys import (
    HEADLINE,
    HYBRID,
    LEARNED,
    LEARNED_NETWORK,
    LEARNED_REFINED,
    NETWORK,
    PER_CONFIG_NETWORK,
    scenario_of,
)
from traffictwin.stats import (
    CIConfig,
    Interval,
    mean_ci,
    paired_mean_difference_ci,
    statistic_ci,
)

if TYPE_CHECKING:  # pandas loads where a table is built: check_params imports this package
    import pandas as pd

# targets judged on wall times: they differ between identical runs, so not in fusion.json
# (Evaluation.timings -> the stage's run record; the benchmark benchmarks/registration.py measures it)
TIMING_TARGETS = ("learned_runtime_ms",)


@dataclass(frozen=True)
class Verdict:
    """One target at one configuration: the figure judged (``value``) and its interval
    ``[lo, hi]``, the ``status``; ``ci_beyond_threshold``: the whole interval lies on the side of
    the verdict (None: nothing was judged); ``why`` a target is not evaluated; ``extra``: further
    numbers the target reports (e.g. the signed difference)."""

    value: float | None
    lo: float | None
    hi: float | None
    status: str
    ci_beyond_threshold: bool | None = None
    why: str | None = None
    extra: Mapping[str, Any] = field(default_factory=dict)

    def with_extra(self, **extra: Any) -> Verdict:
        return replace(self, extra={**self.extra, **extra})

    def as_dict(self) -> dict[str, Any]:
        """The fusion.json entry: ``value, lo, hi, status`` (+ ``ci_beyond_threshold``, ``why``,
        the extras)."""
        out: dict[str, Any] = {"value": self.value, "lo": self.lo, "hi": self.hi}
        out["status"] = self.status
        if self.ci_beyond_threshold is not None:
            out["ci_beyond_threshold"] = self.ci_beyond_threshold
        if self.why is not None:
            out["why"] = self.why
        return out | dict(self.extra)


def judge(iv: Interval, t: Threshold) -> Verdict:
    """Pass/fail of ``iv`` against threshold ``t`` (:func:`traffictwin.acceptance.judge`);
    ``ci_beyond_threshold``: the whole interval lies on the side of the verdict (the verdict is
    not noise)."""
    j = judge_threshold(t, iv.estimate, iv.lo, iv.hi)
    return Verdict(iv.estimate, iv.lo, iv.hi, j.status, j.ci_beyond)


def missing(why: str) -> Verdict:
    """A target that could not be evaluated, and why."""
    return Verdict(None, None, None, NOT_EVALUATED, why=why)


def _overall(per: Mapping[str, Verdict]) -> str:
    st = [v.status for v in per.values()]
    if not st:
        return NOT_EVALUATED
    if "fail" in st:
        return "fail"
    return NOT_EVALUATED if NOT_EVALUATED in st else "pass"


@dataclass(frozen=True)
class TargetInputs:
    """What the targets are judged on: the per-pair frames ``frames[(cfg, row)]``, the ``test``
    and ``diff`` blocks of fusion.json, the bootstrap settings ``ci``, the acceptance
    ``thresholds`` (``acceptance.fusion``) and the one network's ``training`` record
    (train_fusion_network.json: ``best_epoch`` (0-based), ``epochs`` run, ``stopped_early``)."""

    frames: Mapping[tuple[str, str], pd.DataFrame]
    test: Mapping[str, Any]
    diff: Mapping[str, Any]
    ci: CIConfig
    thresholds: Mapping[str, Threshold]
    training: Mapping[str, Any] = field(default_factory=dict)

    def frame(self, c: str, row: str) -> pd.DataFrame | None:
        return self.frames.get((c, row))

    def numbers(self, c: str, row: str) -> Mapping[str, Any] | None:
        """``test.<c>.<row>`` (None where the row was not evaluated at ``c``)."""
        return self.test.get(c, {}).get(row)

    def paired(self, c: str, row: str, base: str) -> Mapping[str, Any] | None:
        """``diff.<c>.<row>.vs_<base>`` (None or empty where not both were evaluated)."""
        return self.diff.get(c, {}).get(row, {}).get(f"vs_{base}")


def _judge_target(ti: TargetInputs, iv: Interval, name: str) -> Verdict:
    return judge(iv, ti.thresholds[name])


def _ratio(ti: TargetInputs, c: str) -> Verdict:
    """Network KLD(b) / naive KLD(b), ratio of means on the common pairs."""
    n, b = ti.frame(c, NETWORK), ti.frame(c, "naive")
    if n is None or b is None:
        return missing(f"configuration {c} or its dnn / naive rows not evaluated")
    _, ia, ib = np.intersect1d(n["pair_id"], b["pair_id"], return_indices=True)
    kn, kb = n["kld_fou"].to_numpy()[ia], b["kld_fou"].to_numpy()[ib]
    groups = scenario_of(n["pair_id"].to_numpy()[ia])

    def stat(i: np.ndarray) -> float:
        den = kb[i].mean()
        return float(kn[i].mean() / den) if den > 0 else math.nan

    iv = statistic_ci(stat, len(kn), groups, **ci_kwargs(ti.ci))
    return _judge_target(ti, iv, "kld_ratio_vs_naive")


def _value_ci(ti: TargetInputs, c: str, key: str, name: str, row: str = NETWORK) -> Verdict:
    """Row ``row``'s ``key`` at ``c`` with its interval, as fusion.json has them."""
    v = ti.numbers(c, row)
    if v is None:
        return missing(f"row {row} not evaluated at configuration {c}")
    b = v[f"{key}_ci"]
    return _judge_target(ti, Interval(v[key], b["lo"], b["hi"], ti.ci.level), name)


TOO_FEW_WRONG = "too few wrong cells"  # the verdict's reason where AUROC(u) is withheld


def _auroc(ti: TargetInputs, c: str) -> Verdict:
    """The network's AUROC(u) at ``c``; not evaluated (":data:`TOO_FEW_WRONG`", with the counts)
    where too few wrong cells stand behind it (``u_auroc_enough`` false)."""
    v = ti.numbers(c, NETWORK)
    if v is not None and not v.get("u_auroc_enough", True):
        return missing(
            f"{TOO_FEW_WRONG}: {v.get('u_auroc_n_wrong')} wrong cells in "
            f"{v.get('u_auroc_pairs_wrong')} pairs at {c}"
        )
    return _value_ci(ti, c, "u_auroc", "u_auroc")


def _dice_drop(ti: TargetInputs, c: str) -> Verdict:
    """1 − Dice occ(network at c) / Dice occ(network at A) on their common pairs, resampled
    together."""
    ref, other = ti.frame("A", NETWORK), ti.frame(c, NETWORK)
    if ref is None or other is None:
        return missing("configurations A and D both needed")
    common, ir, io = np.intersect1d(ref["pair_id"], other["pair_id"], return_indices=True)
    codes, g = scenario_codes(common)
    draws = scenario_draws(g, ti.ci)
    er, br = pooled_dice(ref.iloc[ir], "occ", codes, g, draws)
    eo, bo = pooled_dice(other.iloc[io], "occ", codes, g, draws)
    if not er > 0:  # reference Dice = 0 or undefined: no relative drop
        return missing(f"network Dice occ at A is {er}: the relative drop is undefined")
    with np.errstate(invalid="ignore", divide="ignore"):  # resamples with Dice 0 drop out
        iv = percentile_interval(1.0 - eo / er, 1.0 - bo / br, ti.ci.level, g)
    return _judge_target(ti, iv, "dice_occ_drop_A_to_D")


def _vs_ego(ti: TargetInputs, c: str) -> Verdict:
    n, e = ti.frame(c, NETWORK), ti.frame(c, "ego")
    if n is None or e is None:
        return missing(f"dnn or ego not evaluated at configuration {c}")
    diffs, _ = paired_intervals(n, e, ti.ci)
    return _judge_target(ti, diffs["dice_occ"], "dice_occ_vs_ego")


def _u_gap(ti: TargetInputs, c: str) -> Verdict:
    """|network mean u − label mean u|, paired over the pairs."""
    n = ti.frame(c, NETWORK)
    if n is None:
        return missing(f"dnn not evaluated at configuration {c}")
    d = paired_mean_difference_ci(
        n["u_mean"].to_numpy(),
        n["label_u_mean"].to_numpy(),
        scenario_of(n["pair_id"]),
        **ci_kwargs(ti.ci),
    )
    # |difference|: the interval of |d| from the interval of d
    lo, hi = (d.lo, d.hi) if d.lo >= 0 else (-d.hi, -d.lo) if d.hi <= 0 else (0.0, max(-d.lo, d.hi))
    res = _judge_target(
        ti, Interval(abs(d.estimate), lo, hi, d.level, d.n_groups), "u_mean_vs_label"
    )
    return res.with_extra(signed_difference={"estimate": d.estimate, "lo": d.lo, "hi": d.hi})


def _beats_registered(ti: TargetInputs, c: str, row: str, name: str) -> Verdict:
    """KLD(b) of ``row`` − registered: interval wholly below target ``name``'s threshold (judged
    on the interval, operator ``<``), Dice occ difference not wholly below 0 (not shown worse)."""
    t = ti.thresholds[name]
    if t.operator != "<" or t.judged_on != "interval":
        raise ValueError(
            f"target {name}: must be judged on the interval with operator '<' (its upper end), "
            f"got {t.judged_on} {t.operator!r}"
        )
    dd = ti.paired(c, row, "registered")
    if not dd:
        return missing(f"rows {row} and registered not both evaluated at configuration {c}")
    k, dc = dd[HEADLINE], dd["dice_occ"]
    if not all(math.isfinite(x) for x in (k["lo"], k["hi"], dc["lo"], dc["hi"])):
        return missing(f"no interval of the {row} − registered difference at {c}")
    below = t.holds(t.figure(k["estimate"], k["lo"], k["hi"]))  # KLD(b) lower, shown
    ok = below and not dc["hi"] < 0  # and Dice occ not shown lower
    return Verdict(
        k["estimate"], k["lo"], k["hi"], "pass" if ok else "fail", bool(below)
    ).with_extra(dice_occ_difference={"estimate": dc["estimate"], "lo": dc["lo"], "hi": dc["hi"]})


def _one_vs_per_config(ti: TargetInputs, c: str) -> Verdict:
    dd = ti.paired(c, NETWORK, PER_CONFIG_NETWORK)
    if not dd:
        return missing(
            f"no {PER_CONFIG_NETWORK} network at configuration {c} (the ablation "
            "`make ablations` (ablation per_config) trains them)"
        )
    k = dd[HEADLINE]
    # judged on the interval's upper bound: the one network is not shown worse by more
    res = _judge_target(ti, Interval(k["hi"], k["lo"], k["hi"], ti.ci.level), "one_vs_per_config")
    return res.with_extra(difference={"estimate": k["estimate"], "lo": k["lo"], "hi": k["hi"]})


def _learned_success(ti: TargetInputs, c: str, name: str, row: str = LEARNED) -> Verdict:
    """``row`` − registered registration success rate (paired), with the threshold's second
    condition (the interval's lower end) where set."""
    dd = (ti.paired(c, row, "registered") or {}).get("success_rate")
    if not dd:
        return missing(f"rows {row} and registered not both evaluated at configuration {c}")
    res = _judge_target(ti, Interval(dd["estimate"], dd["lo"], dd["hi"], ti.ci.level), name)
    return res.with_extra(n_pairs=dd["n_pairs"])


def _learned_mean(ti: TargetInputs, c: str, column: str, name: str, row: str = LEARNED) -> Verdict:
    """Mean of a registration row's per-pair ``column`` (success, wall time) at ``c``."""
    f = ti.frame(c, row)
    if f is None or (column == "reg_success" and ti.numbers(c, row) is None):
        return missing(f"{row} not evaluated at configuration {c}")
    iv = mean_ci(f[column].to_numpy(np.float64), scenario_of(f["pair_id"]), **ci_kwargs(ti.ci))
    return _judge_target(ti, iv, name)


def _training_converged(ti: TargetInputs, c: str) -> Verdict:
    """The one network's training (``ti.training``; ``c``: the noise it was trained on): the
    figure is its best epoch's place in the run, (best_epoch + 1) / epochs (1: the last epoch
    run); it fails whatever that place where early stopping did not end the run (the epoch cap
    did: the network may still have been improving). No interval: one training run."""
    best, epochs = ti.training.get("best_epoch"), ti.training.get("epochs")
    if not isinstance(best, int) or not isinstance(epochs, int) or not 0 <= best < epochs:
        return missing(f"no training record of the network trained on {c} (best_epoch, epochs)")
    place = (best + 1) / epochs
    j = judge_threshold(ti.thresholds["training_converged"], place)
    stopped = ti.training.get("stopped_early") is True
    v = Verdict(place, None, None, j.status if stopped else FAIL)
    if not stopped:
        v = replace(
            v, why=f"the run reached its epoch cap ({epochs}): early stopping did not end it"
        )
    return v.with_extra(best_epoch=best, epochs=epochs, stopped_early=stopped)


# every target's judge at one configuration, in the order of fusion.json's ``targets``
JUDGES: dict[str, Callable[[TargetInputs, str], Verdict]] = {
    "kld_ratio_vs_naive": _ratio,
    "kld_at_A": lambda ti, c: _value_ci(ti, c, HEADLINE, "kld_at_A"),
    "dice_occ_at_A": lambda ti, c: _value_ci(ti, c, "dice_occ", "dice_occ_at_A"),
    "dice_occ_drop_A_to_D": _dice_drop,
    "dice_occ_vs_ego": _vs_ego,
    "u_auroc": _auroc,
    "u_mean_vs_label": _u_gap,
    "hybrid_vs_registered": lambda ti, c: _beats_registered(ti, c, HYBRID, "hybrid_vs_registered"),
    "network_vs_registered": lambda ti, c: _beats_registered(
        ti, c, NETWORK, "network_vs_registered"
    ),
    "one_vs_per_config": _one_vs_per_config,
    "learned_success_vs_registered": lambda ti, c: _learned_success(
        ti, c, "learned_success_vs_registered"
    ),
    "learned_success_gain_at_D": lambda ti, c: _learned_success(ti, c, "learned_success_gain_at_D"),
    "learned_success_at_D": lambda ti, c: _learned_mean(
        ti, c, "reg_success", "learned_success_at_D"
    ),
    "learned_kld_vs_registered": lambda ti, c: _beats_registered(
        ti, c, LEARNED_NETWORK, "learned_kld_vs_registered"
    ),
    "learned_network_kld_at_D": lambda ti, c: _value_ci(
        ti, c, HEADLINE, "learned_network_kld_at_D", LEARNED_NETWORK
    ),
    "learned_runtime_ms": lambda ti, c: _learned_mean(ti, c, "ms", "learned_runtime_ms"),
    "refined_success_gain_at_D": lambda ti, c: _learned_success(
        ti, c, "refined_success_gain_at_D", LEARNED_REFINED
    ),
    "refined_success_at_D": lambda ti, c: _learned_mean(
        ti, c, "reg_success", "refined_success_at_D", LEARNED_REFINED
    ),
    "training_converged": _training_converged,
}


def fusion_targets(
    own: Mapping[tuple[str, str], pd.DataFrame],
    metrics: Mapping[str, Any],
    ci: CIConfig,
    success_trans_m: float,
    success_rot_deg: float,
    thresholds: Mapping[str, Threshold],
    training: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Every target of :data:`JUDGES` against its acceptance threshold (``thresholds``:
    ``acceptance.fusion``, :func:`traffictwin.acceptance.thresholds`), from the per-pair frames
    ``own[(cfg, row)]``, the intervals already in ``metrics`` (``test``, ``diff``) and the one
    network's ``training`` record (train_fusion_network.json; None: that target not evaluated):
    ``{name: {description, threshold, op, status, per_config: {cfg: verdict}}}``. A target whose
    configuration or rows were not evaluated is ``not evaluated`` (never ``pass``). The
    descriptions name the registration success limits ``success_trans_m`` (m) and
    ``success_rot_deg`` (deg) (``evaluation.fusion``) in their ``{trans_m}`` / ``{rot_deg}``
    fields."""
    absent = [n for n in JUDGES if n not in thresholds]
    if absent:
        raise ValueError(
            f"fusion_targets: no acceptance threshold for {absent} (acceptance.fusion)"
        )
    ti = TargetInputs(own, metrics["test"], metrics["diff"], ci, thresholds, training or {})
    configs = list(metrics["test"])
    out: dict[str, Any] = {}
    for name, judge_at in JUDGES.items():
        t = thresholds[name]
        per = {c: judge_at(ti, c) for c in (t.configs or configs)}
        out[name] = {
            "description": t.description.format(trans_m=success_trans_m, rot_deg=success_rot_deg),
            "threshold": t.value,
            "op": t.operator,
            "status": _overall(per),
            "per_config": {c: v.as_dict() for c, v in per.items()},
        }
    return out
