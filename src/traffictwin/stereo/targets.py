"""The learned stereo network's targets on the stereo evaluation (``reports/metrics/stereo.json``):
each target's value with its sequence-bootstrap interval, the threshold and whether it is met."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

#: name → (metric key in stereo.json, op, threshold, format, description, met by the interval)
TARGETS: dict[str, tuple[str, str, float, str, str, bool]] = {
    "learned_crit_obj_relerr_median": (
        "learned/own/crit_obj_relerr_median",
        "<=",
        0.035,
        "pct",
        "learned stereo: median relative range error on the objects at the critical distances "
        "(12–21 m), its own estimated pixels (SGM: about 7 %)",
        False,
    ),
    "learned_crit_obj_relerr_p90": (
        "learned/own/crit_obj_relerr_p90",
        "<=",
        0.10,
        "pct",
        "learned stereo: 90th percentile of that error (SGM: about 17 %)",
        False,
    ),
    "learned_minus_sgm_epe": (
        "diff_learned_minus_sgm/common/epe",
        "<",
        0.0,
        "f3",
        "end-point error learned − SGM (px) on the pixels both estimate, paired over the same "
        "test frames: met when the whole interval lies below 0",
        True,
    ),
}


def _holds(x: float, op: str, threshold: float) -> bool:
    """``x <op> threshold`` for ``op`` in ``<=`` / ``<``."""
    return bool(x <= threshold) if op == "<=" else bool(x < threshold)


def stereo_targets(metrics: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """Every target of :data:`TARGETS` on ``metrics`` (stereo.json's flat keys, with ``_lo`` /
    ``_hi``): ``value``, ``value_lo``, ``value_hi``, ``op``, ``threshold``, ``format``,
    ``description`` and ``met`` (``None`` when the value is missing; for a target judged by its
    interval, met only when the whole interval lies on the target's side)."""
    out = {}
    for name, (key, op, thr, fmt, desc, by_interval) in TARGETS.items():
        v, lo, hi = metrics.get(key), metrics.get(f"{key}_lo"), metrics.get(f"{key}_hi")
        if v is None:
            met = None
        elif by_interval:
            met = bool(hi is not None and _holds(hi, op, thr))
        else:
            met = _holds(v, op, thr)
        out[name] = {
            "metric": key,
            "value": v,
            "value_lo": lo,
            "value_hi": hi,
            "op": op,
            "threshold": thr,
            "format": fmt,
            "description": desc,
            "met": met,
        }
    return out
