"""The twin's part of the report: how often the ego's risk read from the twin flags the truly
critical frames, compared with its own map, in occluded and open sequences.

Reads ``twin.json`` (stage evaluate_twin, layout :mod:`traffictwin.twin.evaluation`:
``configurations.<cfg>.methods.<method>.<kind>.<metric>`` with ``<metric>_ci = [lo, hi]``) and
``twin_data.json`` (stage generate_twin). Its targets are judged in the report's acceptance table,
not here. Tables are built from column specs (:data:`OCCLUDED_PARTS`, :data:`OPEN_PARTS`), their notes are the macros of
``templates/report.md.j2``. A missing file or key is an ``n/a`` cell, never an error. Entry
point: :func:`provider`.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence
from pathlib import Path
from typing import Any

from traffictwin.report import model as page
from traffictwin.report.acceptance import POINTER as ACCEPTANCE_POINTER
from traffictwin.report.model import Cell, DataFile, Table, lookup
from traffictwin.report.prose import oneline, template_macro
from traffictwin.report.summary import Headline, headline, strongest
from traffictwin.risk.report_tables import RISK_FILE, Column, spec_cells, spec_columns

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

FLAGGED: Column = ("critical frames flagged", "recall", "pct", True)
FALSE_ALARMS: Column = ("false alarms (frames)", "false_alarm_share", "pct", True)
OCCLUDED: tuple[Column, ...] = (
    FLAGGED,
    ("Δ vs ego map", "recall_vs_ego", "pct", True),
    ("median lead over ego (s)", "lead_vs_ego_s_median", "f2", True),
    ("warned before onset", "warned_before_onset_share", "pct", False),
    ("vehicles left out", "left_out_share", "pct", False),
)
OPEN: tuple[Column, ...] = (
    FLAGGED,
    FALSE_ALARMS,
    ("false alarms / min", "false_alarms_per_min", "f2", False),
)
BIAS: tuple[Column, ...] = (("under pose bias (frames)", "false_alarm_share", "pct", True),)
#: a table's column groups: (twin.json key under a configuration, ``{m}`` the map, its columns,
#: the keys "—" for the ego's own map, the keys "—" for the warning at every frame)
Part = tuple[str, Sequence[Column], Collection[str], Collection[str]]
OCCLUDED_PARTS: tuple[Part, ...] = (
    (
        "methods.{m}.occluded",
        OCCLUDED,
        ("recall_vs_ego", "lead_vs_ego_s_median", "left_out_share"),
        ("recall", "recall_vs_ego", "left_out_share"),
    ),
)
OPEN_PARTS: tuple[Part, ...] = (
    ("methods.{m}.open", OPEN, (), ("recall",)),
    ("pose_bias.methods.{m}.open", BIAS, (), ("false_alarm_share",)),
)


def prose(name: str, **context: Any) -> str:
    """Macro ``name`` of ``templates/report.md.j2`` filled with ``context``, on one line."""
    return oneline(template_macro(TEMPLATES, "report.md.j2", name)(**context))


def critical_thw_text(src: page.Sources) -> str:
    """The critical THW as text (e.g. ``"1 s"``): the primary ``thresholds_s`` of ``risk.json``
    (``twin.critical_thw`` interpolates it); the key's name when that file lacks it."""
    ts = src.get(RISK_FILE, "thresholds_s")
    return f"{float(ts[0]):g} s" if isinstance(ts, list) and ts else "twin.critical_thw"


def _keys(src: page.Sources, key: str = "configurations") -> list[str]:
    """The keys of the object at twin.json ``key`` (none where it is no object)."""
    v = src.get(FILE, key)
    return list(v) if isinstance(v, dict) else []


def map_table(src: page.Sources, kind: str, parts: Sequence[Part], title: str, note: str) -> Table:
    """One row per configuration and map the ego reads (then the warning at every frame, where
    twin.json has it), the columns of ``parts``; ``kind``: occluded / open sequences."""
    heads = spec_columns(*(cols for _, cols, _, _ in parts))
    t = Table(title, ["config", "map the ego reads", *heads], anchor=f"twin-{kind}", note=note)
    for c in _keys(src):
        for m in _keys(src, f"configurations.{c}.methods"):
            bases = [
                (f"configurations.{c}.{key.format(m=m)}", cols, ego) for key, cols, ego, _ in parts
            ]
            cells = [
                x
                for base, cols, ego in bases
                for x in spec_cells(src, FILE, base, cols, ego if m == "ego" else ())
            ]
            t.rows.append([Cell(c), Cell(LABELS.get(m, m)), *cells])
        always = f"configurations.{c}.always_warns.{kind}"
        if isinstance(src.get(FILE, always), dict):
            cells = [
                x for _, cols, _, dash in parts for x in spec_cells(src, FILE, always, cols, dash)
            ]
            t.rows.append([Cell(c), Cell(ALWAYS_LABEL), *cells])
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
    crit = critical_thw_text(src)
    tables = [
        map_table(
            src,
            "occluded",
            OCCLUDED_PARTS,
            "Twin: critical frames flagged in occluded sequences",
            prose("occluded", crit=crit),
        ),
        map_table(
            src,
            "open",
            OPEN_PARTS,
            "Twin: open sequences (nothing hidden) — recall and false alarms",
            prose("open"),
        ),
    ]
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
