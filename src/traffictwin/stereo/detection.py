"""Detection and false-alarm rates of the stereo pair-check rules, with scenario-cluster bootstrap
95 % intervals (:mod:`traffictwin.stats`): the table of orb.json and the report's stereo section.

Frames of one scenario (driving sequence) are correlated, so intervals resample scenarios.
"""

from __future__ import annotations

from collections.abc import Sequence

import pandas as pd

from traffictwin.stats import mean_ci
from traffictwin.stereo.check import NO_FAULT, RULES, key_fragment, rule_flag

#: subject speed bins (m/s, ``[lo, hi)``) of the delay-fault detection: a delayed image of a
#: standing subject shows the same scene (only other road users moved)
SPEED_EDGES_MPS = (0.0, 0.5, 5.0, 10.0, 15.0, 40.0)


def _rate(
    flag: pd.Series, sel: pd.Series, groups: pd.Series, n_boot: int, seed: int
) -> dict[str, float]:
    """Share of ``flag`` among ``sel`` with its scenario-cluster bootstrap 95 % interval and count."""
    n = int(sel.sum())
    if n == 0:
        return {}
    ci = mean_ci(flag[sel].to_numpy(float), groups[sel].to_numpy(), n_boot=n_boot, seed=seed)
    return {"": ci.estimate, "_lo": ci.lo, "_hi": ci.hi, "_n": n}


def detection_table(
    df: pd.DataFrame,
    faults: Sequence[str],
    speed_edges: Sequence[float] = SPEED_EDGES_MPS,
    n_boot: int = 2000,
    seed: int = 0,
) -> dict[str, float]:
    """Detection rate per fault type and false-alarm rate on fault-free pairs for every rule of
    :data:`RULES`, each with a scenario-cluster bootstrap 95 % interval (``_lo``/``_hi``) and the
    number of pairs (``_n``); delay faults also per subject-speed bin (m/s).

    ``df``: per pair ``fault``, ``scenario`` (the cluster), ``speed`` (m/s) and the flag columns of
    :func:`~traffictwin.stereo.check.add_flags`. Keys ``rule_<rule>/<fault>_detection[_lo|_hi|_n]``,
    ``rule_<rule>/false_alarm[...]``, ``rule_<rule>/delay_detection_v<lo>-<hi>[...]``.
    """
    out: dict[str, float] = {}
    groups = df.scenario
    faulty = [f for f in faults if f != NO_FAULT]
    clean = df.fault == NO_FAULT
    for rule in RULES:
        flag = rule_flag(df, rule)
        pre = f"rule_{rule}/"
        for suffix, v in _rate(flag, clean, groups, n_boot, seed).items():
            out[f"{pre}false_alarm{suffix}"] = v
        for f in faulty:
            sel = df.fault == f
            for suffix, v in _rate(flag, sel, groups, n_boot, seed).items():
                out[f"{pre}{f}_detection{suffix}"] = v
        if "delay" in faulty:
            for lo, hi in zip(speed_edges[:-1], speed_edges[1:]):
                sel = (df.fault == "delay") & (df.speed >= lo) & (df.speed < hi)
                name = f"{pre}delay_detection_v{key_fragment(lo)}-{key_fragment(hi)}"
                for suffix, v in _rate(flag, sel, groups, n_boot, seed).items():
                    out[f"{name}{suffix}"] = v
    return out
