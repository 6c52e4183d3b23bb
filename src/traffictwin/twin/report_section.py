"""The twin's part of the report: how often the ego's risk read from the twin flags the truly
critical frames, compared with its own map, in occluded and open sequences.

Reads ``twin.json`` (stage evaluate_twin, layout :mod:`traffictwin.twin.evaluation`), its prose
from the macros of ``templates/report.md.j2``. Entry point: :func:`provider`.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from traffictwin.fusion.report_section.tables import FUSION_METHOD_LABELS
from traffictwin.report import model as page
from traffictwin.report.acceptance import POINTER as ACCEPTANCE_POINTER
from traffictwin.report.model import Cell, DataFile, Table, lookup
from traffictwin.report.prose import macro_prose
from traffictwin.report.summary import Headline, headline, strongest
from traffictwin.risk.report_tables import RISK_FILE, Column, spec_cells, spec_columns

FILE = "twin.json"
TEMPLATES = Path(__file__).parent / "templates"
TITLE = "Cooperative twin — risk from N vehicles' fused maps"
#: the figures the section shows, in order; their captions are macros of the same name
FIGURE_STEMS = ("twin_timeline", "twin_map")
LABELS = {  # the fusion tables' labels, where the twin's maps differ
    **FUSION_METHOD_LABELS,
    "ego": "ego's own map (no cooperation)",
    "naive": "naive (noisy poses + Dempster)",
    "dnn": "network on noisy poses",
}
ALWAYS_LABEL = "reference: a warning at every frame"
#: the table's columns under ``configurations.<cfg>.methods.<map>`` (and ``.always_warns``): what
#: the twin gains in occluded sequences, what it costs in open ones (nothing hidden)
COLUMNS: tuple[Column, ...] = (
    ("critical frames flagged (occluded)", "occluded.recall", "pct", True),
    ("Δ vs ego map", "occluded.recall_vs_ego", "pct", True),
    ("median lead over ego (s)", "occluded.lead_vs_ego_s_median", "f2", True),
    ("warned before onset", "occluded.warned_before_onset_share", "pct", False),
    ("vehicles left out", "occluded.left_out_share", "pct", False),
    ("false alarms (open, frames)", "open.false_alarm_share", "pct", True),
)
#: the keys shown "—" for the ego's own map and for the warning at every frame
EGO_DASH = ("occluded.recall_vs_ego", "occluded.lead_vs_ego_s_median", "occluded.left_out_share")
ALWAYS_DASH = ("occluded.recall", "occluded.recall_vs_ego", "occluded.left_out_share")


#: macro ``name`` of ``templates/report.md.j2`` filled with ``context``, on one line
prose = macro_prose(TEMPLATES, "report.md.j2")


def critical_thw_text(src: page.Sources) -> str:
    """The critical THW as text (e.g. ``"1 s"``): the primary ``thresholds_s`` of ``risk.json``
    (``twin.critical_thw`` interpolates it); the key's name when that file lacks it."""
    ts = src.get(RISK_FILE, "thresholds_s")
    return f"{float(ts[0]):g} s" if isinstance(ts, list) and ts else "twin.critical_thw"


def map_table(src: page.Sources) -> Table:
    """One row per configuration and map the ego reads (then the warning at every frame, where
    twin.json has it), the columns :data:`COLUMNS`."""
    t = Table(
        "Twin: critical frames flagged in occluded sequences, false alarms in open ones",
        ["config", "map the ego reads", *spec_columns(COLUMNS)],
        anchor="twin-maps",
        note=prose("note", crit=critical_thw_text(src)),
    )
    for c in src.get(FILE, "configurations") or {}:
        base = f"configurations.{c}"
        rows = [
            (LABELS.get(m, m), f"methods.{m}", EGO_DASH if m == "ego" else ())
            for m in src.get(FILE, f"{base}.methods") or {}
        ]
        if isinstance(src.get(FILE, f"{base}.always_warns"), dict):
            rows.append((ALWAYS_LABEL, "always_warns", ALWAYS_DASH))
        for label, key, dash in rows:
            cells = spec_cells(src, FILE, f"{base}.{key}", COLUMNS, dash)
            t.rows.append([Cell(c), Cell(label), *cells])
    return t


def section(src: page.Sources, figures: list[page.Figure]) -> page.Section:
    """The twin section: warnings in occluded and open sequences; a pointer to the acceptance
    table where twin.json has targets."""
    sec = page.Section(TITLE, paragraphs=[prose("intro")], figures=figures)
    if not src.has(FILE):
        sec.paragraphs.append(prose("missing", file=FILE))
        return sec
    if isinstance(src.get(FILE, "targets"), dict):
        sec.paragraphs.append(ACCEPTANCE_POINTER)
    sec.tables = [map_table(src)]
    return sec


def headlines(metrics: Mapping[str, Any]) -> list[Headline]:
    """The targets' method and configuration, occluded sequences: share of critical frames
    flagged (``recall``, beside the strongest other map) and its gain over the ego's own map
    (``recall_gain``), with their sequence-bootstrap intervals."""
    twin = metrics.get(FILE)
    method = lookup(twin, "targets.method") or lookup(twin, "headline")
    cfg = lookup(twin, "targets.configuration")
    maps = lookup(twin, f"configurations.{cfg}.methods")
    occ = lookup(maps, f"{method}.occluded")
    if not isinstance(occ, Mapping):
        return []
    path = f"metrics/{FILE}#configurations.{cfg}.methods.{{}}.occluded.recall"
    rivals = {
        LABELS.get(m, m): (
            lookup(r, "occluded.recall"),
            lookup(r, "occluded.recall_ci"),
            path.format(m),
        )
        for m, r in maps.items()
        if m != method
    }
    where = f"{LABELS.get(method, method)} at configuration {cfg}, occluded sequences"

    def head(name: str, what: str, k: str, base: Any = None) -> list[Headline]:
        return headline(name, what, where, occ.get(k), occ.get(f"{k}_ci"), "pct", base)

    gain = "gain in critical frames flagged over the ego's own map"
    base = strongest(rivals, higher_better=True)
    return head("recall", "critical frames flagged", "recall", base) + head(
        "recall_gain", gain, "recall_vs_ego"
    )


def provider() -> page.SectionProvider:
    """The twin section's provider for the report (after the fusion and risk sections); twin.json
    is in the appendix in full."""
    return page.SectionProvider(
        name="twin",
        headlines=headlines,
        section=section,
        figures={stem: prose(stem) for stem in FIGURE_STEMS},
        data_files=(DataFile("twin_data.json", "Twin data (generate_twin)"),),
    )
