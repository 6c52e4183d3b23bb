"""The stages' run records (``reports/timings/<stage>.json``): reading them, and the run's wall
time from their start and end stamps (``make readme``'s timing tables)."""

from __future__ import annotations

import json
from collections.abc import Mapping
from datetime import datetime
from pathlib import Path

#: a pause longer than this between one stage's end and the next one's start is not part of the run
#: (a stage re-run on its own later, e.g. `dvc repro report` after a fix)
GAP_S = 300.0


def read_records(folder: str | Path) -> list[dict]:
    """Every run record ``<folder>/*.json``, in name order."""
    return [json.loads(p.read_text()) for p in sorted(Path(folder).glob("*.json"))]


def seconds(record: Mapping) -> float:
    """The stage's own time (s) of a run record (0 when it has none)."""
    return float(record.get("seconds", 0.0))


def _t(s: str) -> datetime:
    return datetime.strptime(s, "%Y-%m-%dT%H:%M:%SZ")


def sessions(records: list[dict]) -> list[list[dict]]:
    """The timed records (``started`` / ``finished``) in start order, split where a stage started
    more than :data:`GAP_S` after every earlier one had finished."""
    timed = sorted(
        (r for r in records if "started" in r and "finished" in r), key=lambda r: _t(r["started"])
    )
    out: list[list[dict]] = []
    end = None
    for r in timed:
        if end is None or (_t(r["started"]) - end).total_seconds() > GAP_S:
            out.append([])
            end = _t(r["finished"])
        out[-1].append(r)
        end = max(end, _t(r["finished"]))
    return out


def wall_seconds(records: list[dict]) -> float | None:
    """The run's wall time (s): the sum of the sessions' spans (first stage start to last stage
    end of each, :func:`sessions`); None without timed records."""
    parts = sessions(records)
    if not parts:
        return None
    return sum(
        (max(_t(r["finished"]) for r in s) - min(_t(r["started"]) for r in s)).total_seconds()
        for s in parts
    )
