"""The learned stereo network's targets on the stereo evaluation (``reports/metrics/stereo.json``):
each target's value with its sequence-bootstrap interval, the threshold and whether it is met,
judged against its acceptance threshold (``acceptance.stereo``, :mod:`traffictwin.acceptance`;
a threshold's ``metric`` is the stereo.json key it judges)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from traffictwin.acceptance import Threshold, judge


def stereo_targets(
    metrics: Mapping[str, Any], thresholds: Mapping[str, Threshold]
) -> dict[str, dict[str, Any]]:
    """Every target of ``thresholds`` on ``metrics`` (stereo.json's flat keys, with ``_lo`` /
    ``_hi``): ``metric``, ``value``, ``value_lo``, ``value_hi``, ``op``, ``threshold``,
    ``format``, ``description`` and ``met`` (``None`` when the value is missing; for a target
    judged on its interval, met only when the whole interval lies on the target's side)."""
    out = {}
    for name, t in thresholds.items():
        key = t.metric
        v, lo, hi = metrics.get(key), metrics.get(f"{key}_lo"), metrics.get(f"{key}_hi")
        out[name] = {
            "metric": key,
            "value": v,
            "value_lo": lo,
            "value_hi": hi,
            "op": t.operator,
            "threshold": t.value,
            "format": t.format,
            "description": t.description,
            "met": judge(t, v, lo, hi).met,
        }
    return out
