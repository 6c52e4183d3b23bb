"""The twin's part of the report: how often the ego's risk read from the twin flags the truly
critical frames, compared with its own map, in occluded and open sequences, with the targets.

Reads ``twin.json`` (stage evaluate_twin, layout :mod:`traffictwin.twin.evaluation`:
``configurations.<cfg>.methods.<method>.<kind>.<metric>`` with ``<metric>_ci = [lo, hi]``, and
``targets``) and ``twin_data.json`` (stage generate_twin). A missing file or key is an ``n/a``
cell, never an error. Entry point: :func:`provider`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from traffictwin.report import model as page
from traffictwin.report.model import NA, Cell, DataFile, Table, fmt_value, lookup
from traffictwin.report.summary import Headline, headline

FILE = "twin.json"
DATA_FILE = "twin_data.json"
TITLE = "Cooperative twin — risk from N vehicles' fused maps"
FIGURES: dict[str, str] = {
    "twin_timeline": (
        "Time headway of the ego over one occluded sequence at the target configuration: from its "
        "own map, from the twin and the truth; shaded = truly critical (THW < 1.5 s), ticks = "
        "frames in which the ego's own lidar returns from the hazard"
    ),
    "twin_map": (
        "The twin at the critical onset of that sequence (ego frame) and each vehicle's map where "
        "the twin put it; true and noisy positions with the configuration's 98 % radius"
    ),
}
LABELS = {
    "ego": "ego's own map (no cooperation)",
    "naive": "naive (noisy poses + Dempster)",
    "registered": "registered (FM + ECC) + Dempster",
    "learned": "learned registration + Dempster",
    "dnn": "network on noisy poses",
    "registered+network": "registered + network",
    "learned+network": "learned registration + network",
}
NOTE = (
    "Frames are critical when the true time headway (corridor, vehicles and pedestrians, simulator "
    "boxes) is below 1.5 s; a map flags a frame when the headway read from its occupied cells "
    "(m_O >= twin.occ_threshold, the ego's footprint ignored) is below 1.5 s. Lead time: per "
    "sequence, the ego map's first flag in the critical episode minus the method's (never = one "
    "frame after the episode). Intervals: 95 % bootstrap over sequences (traffictwin.stats)."
)


def _ci(src: page.Sources, key: str, fmt: str) -> Cell:
    v = src.get(FILE, key)
    if not (isinstance(v, list) and len(v) == 2 and all(isinstance(x, (int, float)) for x in v)):
        return Cell(NA, title=f"no interval in reports/metrics/{FILE}: {key}")
    return Cell(
        f"[{fmt_value(v[0], fmt)}, {fmt_value(v[1], fmt)}]",
        value=list(v),
        derived=f"95 % sequence-bootstrap interval, metrics/{FILE}#{key}",
    )


def _methods(src: page.Sources, c: str) -> list[str]:
    m = src.get(FILE, f"configurations.{c}.methods")
    return list(m) if isinstance(m, dict) else []


def occluded_table(src: page.Sources) -> Table:
    cols = [
        "config",
        "map the ego reads",
        "critical frames flagged",
        "95 % CI",
        "Δ vs ego map",
        "95 % CI",
        "lead time (s)",
        "95 % CI",
        "vehicles left out",
    ]
    t = Table(
        "Twin: critical frames flagged in occluded sequences",
        cols,
        anchor="twin-occluded",
    )
    configs = src.get(FILE, "configurations")
    for c in configs if isinstance(configs, dict) else {}:
        for m in _methods(src, c):
            k = f"configurations.{c}.methods.{m}.occluded"
            row = [
                Cell(c),
                Cell(LABELS.get(m, m)),
                src.cell(FILE, f"{k}.recall", "pct"),
                _ci(src, f"{k}.recall_ci", "pct"),
            ]
            if m == "ego":
                row += [Cell("—")] * 5
            else:
                row += [
                    src.cell(FILE, f"{k}.recall_vs_ego", "pct"),
                    _ci(src, f"{k}.recall_vs_ego_ci", "pct"),
                    src.cell(FILE, f"{k}.lead_time_s", "f2"),
                    _ci(src, f"{k}.lead_time_s_ci", "f2"),
                    src.cell(FILE, f"{k}.left_out_share", "pct"),
                ]
            t.rows.append(row)
    t.note = NOTE
    return t


def open_table(src: page.Sources) -> Table:
    cols = [
        "config",
        "map the ego reads",
        "critical frames flagged",
        "95 % CI",
        "false alarms",
        "95 % CI",
    ]
    t = Table(
        "Twin: open sequences (nothing hidden) — recall and false alarms", cols, anchor="twin-open"
    )
    configs = src.get(FILE, "configurations")
    for c in configs if isinstance(configs, dict) else {}:
        for m in _methods(src, c):
            k = f"configurations.{c}.methods.{m}.open"
            t.rows.append(
                [
                    Cell(c),
                    Cell(LABELS.get(m, m)),
                    src.cell(FILE, f"{k}.recall", "pct"),
                    _ci(src, f"{k}.recall_ci", "pct"),
                    src.cell(FILE, f"{k}.false_alarm_rate", "pct"),
                    _ci(src, f"{k}.false_alarm_rate_ci", "pct"),
                ]
            )
    t.note = (
        "False alarms: share of the frames that are not critical which the map flags. Intervals: "
        "95 % bootstrap over sequences (traffictwin.stats)."
    )
    return t


TARGETS = (
    ("occluded_recall_ge_0.9", "occluded: twin flags >= 90 % of critical frames", "pct"),
    ("occluded_recall_above_ego", "occluded: twin flags more than the ego map (CI > 0)", "pct"),
    ("occluded_lead_time_gt_0.5s", "occluded: mean lead time > 0.5 s", "f2"),
    ("open_false_alarms_le_0.05", "open: false alarms <= 5 %", "pct"),
)


def targets_table(src: page.Sources) -> Table:
    c = src.get(FILE, "targets.configuration")
    m = src.get(FILE, "targets.method")
    t = Table(
        f"Twin targets (configuration {c if c is not None else NA}, twin: {m if m is not None else NA})",
        ["target", "value", "95 % CI", "met"],
        anchor="twin-targets",
        headline=True,
    )
    for key, label, fmt in TARGETS:
        ok = src.get(FILE, f"targets.{key}.pass")
        t.rows.append(
            [
                Cell(label),
                src.cell(FILE, f"targets.{key}.value", fmt),
                _ci(src, f"targets.{key}.ci", fmt),
                Cell(
                    NA if ok is None else ("yes" if ok else "no"),
                    value=ok,
                    derived=f"metrics/{FILE}#targets.{key}.pass",
                ),
            ]
        )
    return t


def section(src: page.Sources, figures: list[page.Figure]) -> page.Section:
    paras = [
        "Three vehicles share lidar evidential maps at 10 Hz around a junction (stage generate_twin): the "
        "ego turns right towards a hazard beside a parked van — a pedestrian at the van's side or a "
        "stopped car — hidden from the ego at the critical onset in `occluded` sequences, in plain view "
        "in `open` ones. Every vehicle's pose carries the configuration's noise; the twin registers "
        "the others' maps onto the ego's (stage evaluate_twin) and the ego's time headway is read from "
        "its own map and from the twin. See the tables for what the twin gains and costs."
    ]
    if not src.has(FILE):
        paras.append(f"reports/metrics/{FILE} is missing: run `dvc repro evaluate_twin`.")
        return page.Section(TITLE, paragraphs=paras, figures=figures)
    return page.Section(
        TITLE,
        paragraphs=paras,
        tables=[occluded_table(src), open_table(src), targets_table(src)],
        figures=figures,
    )


def headlines(metrics: Mapping[str, Any]) -> list[Headline]:
    """The targets' method and configuration, occluded sequences: share of critical frames
    flagged (``recall``) and its gain over the ego's own map (``recall_gain``), with their
    sequence-bootstrap intervals."""
    twin = metrics.get(FILE)
    method = lookup(twin, "targets.method") or lookup(twin, "headline")
    cfg = lookup(twin, "targets.configuration")
    occ = lookup(twin, f"configurations.{cfg}.methods.{method}.occluded")
    if not isinstance(occ, Mapping):
        return []
    where = f"{LABELS.get(method, method)} at configuration {cfg}, occluded sequences"
    return headline(
        "recall",
        "critical frames flagged",
        where,
        occ.get("recall"),
        occ.get("recall_ci"),
        "pct",
    ) + headline(
        "recall_gain",
        "gain in critical frames flagged over the ego's own map",
        where,
        occ.get("recall_vs_ego"),
        occ.get("recall_vs_ego_ci"),
        "pct",
    )


def provider() -> page.SectionProvider:
    """The twin section's provider for the report (after the fusion and risk sections)."""
    return page.SectionProvider(
        name="twin",
        headlines=headlines,
        section=section,
        figures=FIGURES,
        data_files=(DataFile(DATA_FILE, "Twin data (generate_twin)"),),
        shown_files=r"twin\.json",
    )
