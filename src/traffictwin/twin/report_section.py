"""The twin's part of the report: how often the ego's risk read from the twin flags the truly
critical frames, compared with its own map, in occluded and open sequences.

Reads ``twin.json`` (stage evaluate_twin, layout :mod:`traffictwin.twin.evaluation`:
``configurations.<cfg>.methods.<method>.<kind>.<metric>`` with ``<metric>_ci = [lo, hi]``) and
``twin_data.json`` (stage generate_twin). Its targets are judged in the report's acceptance table,
not here. Tables are built from :data:`Metric` specs, their notes are the macros of
``templates/report.md.j2``. A missing file or key is an ``n/a`` cell, never an error. Entry
point: :func:`provider`.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence
from pathlib import Path
from typing import Any

from traffictwin.report import model as page
from traffictwin.report.acceptance import POINTER as ACCEPTANCE_POINTER
from traffictwin.report.model import Cell, DataFile, Table, interval_cell, lookup
from traffictwin.report.prose import oneline, template_macro
from traffictwin.report.summary import Headline, headline, strongest
from traffictwin.risk.report_tables import RISK_FILE

FILE = "twin.json"
DATA_FILE = "twin_data.json"
TEMPLATES = Path(__file__).parent / "templates"
TITLE = "Cooperative twin — risk from N vehicles' fused maps"
#: the figures the section shows, in order; their captions are macros of the same name
FIGURE_STEMS = ("twin_timeline", "twin_map")
LABELS = {
    "ego": "ego's own map (no cooperation)",
    "naive": "naive (noisy poses + Dempster)",
    "registered": "registered (FM + ECC) + Dempster",
    "learned": "learned registration + Dempster",
    "dnn": "network on noisy poses",
    "registered+network": "registered + network",
    "learned+network": "learned registration + network",
}
ALWAYS_LABEL = "reference: a warning at every frame"
DASH = "—"

#: one figure of a table row: (column header, key under the row's base, format, with its
#: interval ``<key>_ci`` in a "95 % CI" column beside it)
Metric = tuple[str, str, str, bool]
FLAGGED: Metric = ("critical frames flagged", "recall", "pct", True)
WARNED: Metric = ("warned before onset", "warned_before_onset_share", "pct", False)
FALSE_ALARMS: Metric = ("false alarms (frames)", "false_alarm_share", "pct", True)
LEAD: Metric = ("median lead over ego (s)", "lead_vs_ego_s_median", "f2", True)
OCCLUDED: tuple[Metric, ...] = (
    FLAGGED,
    ("Δ vs ego map", "recall_vs_ego", "pct", True),
    LEAD,
    WARNED,
    ("vehicles left out", "left_out_share", "pct", False),
)
OPEN: tuple[Metric, ...] = (
    FLAGGED,
    FALSE_ALARMS,
    ("false alarms / min", "false_alarms_per_min", "f2", False),
)
BIAS: tuple[Metric, ...] = (("under pose bias (frames)", "false_alarm_share", "pct", True),)


def prose(name: str, **context: Any) -> str:
    """Macro ``name`` of ``templates/report.md.j2`` filled with ``context``, on one line."""
    return oneline(template_macro(TEMPLATES, "report.md.j2", name)(**context))


def critical_thw_text(src: page.Sources) -> str:
    """The critical THW as text (e.g. ``"1 s"``): the primary ``thresholds_s`` of ``risk.json``
    (``twin.critical_thw`` interpolates it); the key's name when that file lacks it."""
    ts = src.get(RISK_FILE, "thresholds_s")
    return f"{float(ts[0]):g} s" if isinstance(ts, list) and ts else "twin.critical_thw"


def _table(title: str, anchor: str, first: Sequence[str], *metrics: Sequence[Metric]) -> Table:
    """An empty table: the ``first`` (label) columns, then each metric's (and interval's)."""
    heads = [
        h for ms in metrics for head, _, _, ci in ms for h in ((head, "95 % CI") if ci else (head,))
    ]
    return Table(title, [*first, *heads], anchor=anchor)


def _cells(
    src: page.Sources, base: str, metrics: Sequence[Metric], dash: Collection[str] = ()
) -> list[Cell]:
    """The cells of ``metrics`` under twin.json key ``base``; a metric in ``dash`` shows "—"."""
    out: list[Cell] = []
    for _, key, fmt, ci in metrics:
        if key in dash:
            out += [Cell(DASH)] * (1 + ci)
            continue
        out.append(src.cell(FILE, f"{base}.{key}", fmt))
        out += [interval_cell(src, FILE, f"{base}.{key}", "sequence-bootstrap", fmt)] if ci else []
    return out


def _keys(src: page.Sources, key: str = "configurations") -> list[str]:
    """The keys of the object at twin.json ``key`` (none where it is no object)."""
    v = src.get(FILE, key)
    return list(v) if isinstance(v, dict) else []


def _methods(src: page.Sources, c: str) -> list[str]:
    return _keys(src, f"configurations.{c}.methods")


def occluded_table(src: page.Sources) -> Table:
    """Per configuration and map: critical frames flagged, gain and lead over the ego's own map."""
    t = _table(
        "Twin: critical frames flagged in occluded sequences",
        "twin-occluded",
        ["config", "map the ego reads"],
        OCCLUDED,
    )
    ego_dash = ("recall_vs_ego", "lead_vs_ego_s_median", "left_out_share")
    for c in _keys(src):
        for m in _methods(src, c):
            k = f"configurations.{c}.methods.{m}.occluded"
            dash = ego_dash if m == "ego" else ()
            t.rows.append([Cell(c), Cell(LABELS.get(m, m)), *_cells(src, k, OCCLUDED, dash)])
        k = f"configurations.{c}.always_warns.occluded"
        if isinstance(src.get(FILE, k), dict):
            dash = ("recall", "recall_vs_ego", "left_out_share")
            t.rows.append([Cell(c), Cell(ALWAYS_LABEL), *_cells(src, k, OCCLUDED, dash)])
    t.note = prose("occluded", crit=critical_thw_text(src))
    return t


def open_table(src: page.Sources) -> Table:
    """Per configuration and map: recall and false alarms in open sequences, also under bias."""
    t = _table(
        "Twin: open sequences (nothing hidden) — recall and false alarms",
        "twin-open",
        ["config", "map the ego reads"],
        OPEN,
        BIAS,
    )
    for c in _keys(src):
        for m in _methods(src, c):
            k, kb = f"configurations.{c}.methods.{m}.open", f"configurations.{c}.pose_bias"
            row = _cells(src, k, OPEN) + _cells(src, f"{kb}.methods.{m}.open", BIAS)
            t.rows.append([Cell(c), Cell(LABELS.get(m, m)), *row])
        k = f"configurations.{c}.always_warns.open"
        if isinstance(src.get(FILE, k), dict):
            row = _cells(src, k, OPEN, ("recall",)) + _cells(src, k, BIAS, ("false_alarm_share",))
            t.rows.append([Cell(c), Cell(ALWAYS_LABEL), *row])
    t.note = prose("open")
    return t


def section(src: page.Sources, figures: list[page.Figure]) -> page.Section:
    """The twin section: warnings in occluded and open sequences; a pointer to the acceptance
    table where twin.json has targets."""
    paras = [prose("intro")]
    if not src.has(FILE):
        paras.append(prose("missing", file=FILE))
        return page.Section(TITLE, paragraphs=paras, figures=figures)
    if isinstance(src.get(FILE, "targets"), dict):
        paras.append(ACCEPTANCE_POINTER)
    tables = [occluded_table(src), open_table(src)]
    return page.Section(TITLE, paragraphs=paras, tables=tables, figures=figures)


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
    others = lookup(twin, f"configurations.{cfg}.methods")
    base = strongest(
        {
            LABELS.get(m, m): (
                lookup(row, "occluded.recall"),
                lookup(row, "occluded.recall_ci"),
                f"metrics/{FILE}#configurations.{cfg}.methods.{m}.occluded.recall",
            )
            for m, row in (others.items() if isinstance(others, Mapping) else ())
            if m != method
        },
        higher_better=True,
    )
    value, ci = occ.get("recall"), occ.get("recall_ci")
    gain, gain_ci = occ.get("recall_vs_ego"), occ.get("recall_vs_ego_ci")
    what = "gain in critical frames flagged over the ego's own map"
    recall = headline("recall", "critical frames flagged", where, value, ci, "pct", base)
    return recall + headline("recall_gain", what, where, gain, gain_ci, "pct")


def provider() -> page.SectionProvider:
    """The twin section's provider for the report (after the fusion and risk sections); twin.json
    is in the appendix in full (each hazard kind, the predictive warnings and their rule, the
    other vehicles' risk)."""
    return page.SectionProvider(
        name="twin",
        headlines=headlines,
        section=section,
        figures={stem: prose(stem) for stem in FIGURE_STEMS},
        data_files=(DataFile(DATA_FILE, "Twin data (generate_twin)"),),
    )
