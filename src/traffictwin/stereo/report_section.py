"""The stereo part of the report: the learned stereo network beside SGM, and stereo-pair fault
detection per rule. Entry point: :func:`provider`.

Reads ``stereo.json`` (stage stereo_learned; keys ``<source>/<mask>/<metric>``) and ``orb.json``
(stage orb_filter; keys ``rule_<rule>/<metric>``), with an interval's ``<key>_lo`` / ``<key>_hi``
beside a key. The learned network refines SGM on SGM's valid pixels, so both estimate the same
pixels: stereo.json's ``common`` and ``own`` masks hold the same numbers, shown once (``own``,
with the density; the paired differences on ``common``). SGM's accuracy per distance bin and the
ORB check's speed bins and threshold sweep (``disparity.json``, ``orb.json``), the SGM variants,
the generalisation to unseen road templates and the camera-resolution study are in the appendix. Notes and paragraphs are the macros of
``templates/report.md.j2`` (:func:`prose`). A missing file or key is an ``n/a`` cell.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from traffictwin.report import model as page
from traffictwin.report.acceptance import POINTER as ACCEPTANCE_POINTER
from traffictwin.report.model import NEVER, Cell, Table, json_number
from traffictwin.report.prose import oneline, template_macro

TITLE = "Stereo — SGM and the learned stereo network's range accuracy, stereo-pair fault detection"
ORB_FILE = "orb.json"
STEREO_FILE = "stereo.json"
#: what writes each metrics file the section reads
WRITERS = {
    STEREO_FILE: "stage stereo_learned has not run",
    ORB_FILE: "stage orb_filter has not run",
}
#: the figures the section shows, in order; their captions are macros of the same name
FIGURE_STEMS = ("stereo_learned_example", "stereo_resolution")
TEMPLATES = Path(__file__).parent / "templates"

#: rule key in orb.json -> row label
RULE_LABELS = {
    "orb_paper": "ORB, paper's rule over all cross-checked matches",
    "orb": "ORB, robust rule over reliable matches",
    "valid_share": "SGM valid share below threshold",
    "orb_or_valid_share": "robust ORB OR valid share",
}
#: the detection rates per rule in orb.json, their column headers
FAULTS = ("delay_detection", "vertical_detection", "false_alarm")
DETECTION = ("delay faults detected", "vertical shifts detected", "false alarms (fault-free)")

#: a table row: (label, metric key, format)
Row = tuple[str, str, str]
#: the rows of the learned-stereo comparison
STEREO_ROWS: tuple[Row, ...] = (
    ("end-point error [px]", "epe", "f3"),
    ("bad-1 (> 1 px)", "bad1", "pct"),
    ("bad-2 (> 2 px)", "bad2", "pct"),
    ("density (share of GT pixels with an estimate)", "density", "pct"),
    ("0–10 m: median range error", "z0-10m_relerr_median", "pct"),
    ("10–30 m: median range error", "z10-30m_relerr_median", "pct"),
    ("30–90 m: median range error", "z30-90m_relerr_median", "pct"),
    ("30–90 m: 90th percentile", "z30-90m_relerr_p90", "pct"),
    ("objects at the critical distances: median range error", "crit_obj_relerr_median", "pct"),
    ("objects at the critical distances: 90th percentile", "crit_obj_relerr_p90", "pct"),
    ("objects at the critical distances: share estimated", "crit_obj_density", "pct"),
)
#: the paired differences shown (learned − SGM), on the pixels both sources estimate
DIFF_ROWS = tuple(r for r in STEREO_ROWS if r[1] in ("epe", "crit_obj_relerr_median"))


def prose(name: str, **context: Any) -> str:
    """Macro ``name`` of ``templates/report.md.j2`` filled with ``context``, on one line."""
    return oneline(template_macro(TEMPLATES, "report.md.j2", name)(**context))


def ci_cell(src: page.Sources, file: str, key: str, fmt: str = "pct") -> Cell:
    """``[lo, hi]`` of ``<key>_lo`` / ``<key>_hi`` in ``file``: a derived cell (n/a if absent)."""
    lo, hi = json_number(src.get(file, f"{key}_lo")), json_number(src.get(file, f"{key}_hi"))
    return page.span_cell(
        lo,
        hi,
        fmt,
        f"95 % cluster-bootstrap interval, metrics/{file}#{key}_lo/_hi",
        f"no interval in reports/metrics/{file}: {key}_lo/_hi",
    )


def value_ci(src: page.Sources, file: str, key: str, fmt: str = "pct") -> list[Cell]:
    """The number at ``file``#``key`` and its interval."""
    return [src.cell(file, key, fmt), ci_cell(src, file, key, fmt)]


def fault_table(src: page.Sources) -> Table | None:
    """Detection / false-alarm rates per rule with intervals, and the pairs they are over (the
    last row); None without the rules in orb.json (the data section shows an older file)."""
    rules = [r for r in RULE_LABELS if src.get(ORB_FILE, f"rule_{r}/false_alarm") is not None]
    if not rules:
        return None
    det = Table(
        "Stereo-pair fault detection per rule (reports/metrics/orb.json)",
        ["rule", "drops pairs"] + [h for name in DETECTION for h in (name, "95 % CI")],
        anchor="stereo-fault-detection",
        headline=True,
        note=prose("detection"),
    )
    for r in rules:
        drops = "yes" if src.get(ORB_FILE, f"rule_{r}/configured") == 1 else ""
        cells = [c for k in FAULTS for c in value_ci(src, ORB_FILE, f"rule_{r}/{k}")]
        det.rows.append([Cell(RULE_LABELS[r]), Cell(drops), *cells])
    counts = [src.cell(ORB_FILE, f"rule_orb/{k}_n", "int") for k in FAULTS]
    det.rows.append(
        [Cell("pairs evaluated"), Cell(""), *[x for n in counts for x in (n, Cell(""))]]
    )
    return det


def learned_table(src: page.Sources) -> Table | None:
    """SGM | interval | learned | interval on the fault-free test frames, each source's own
    pixels; then the paired differences learned − SGM (the last rows, in the learned columns)."""
    if not src.has(STEREO_FILE):
        return None
    t = Table(
        "Learned stereo network vs SGM, fault-free test frames (reports/metrics/stereo.json)",
        ["quantity", "SGM", "SGM 95 % CI", "learned", "learned 95 % CI"],
        anchor="stereo-learned",
        note=prose("learned"),
    )
    for label, k, fmt in STEREO_ROWS:
        cells = [
            c for s in ("sgm", "learned") for c in value_ci(src, STEREO_FILE, f"{s}/own/{k}", fmt)
        ]
        t.rows.append([Cell(label), *cells])
    for label, k, fmt in DIFF_ROWS:
        cells = value_ci(src, STEREO_FILE, f"diff_learned_minus_sgm/common/{k}", fmt)
        t.rows.append([Cell(f"{label} (learned − SGM)"), Cell(""), Cell(""), *cells])
    return t


def section(src: page.Sources, figures: list[page.Figure]) -> page.Section:
    """The stereo section: fault detection and the learned network beside SGM; a pointer to the
    acceptance table where stereo.json has targets."""
    sec = page.Section(TITLE, paragraphs=[prose("intro")], figures=figures)
    if (targets := src.get(STEREO_FILE, "targets")) and isinstance(targets, dict):
        sec.paragraphs.append(ACCEPTANCE_POINTER)
    sec.tables = [t for t in (fault_table(src), learned_table(src)) if t is not None]
    sec.paragraphs += [
        prose("missing", file=f, why=w) for f, w in WRITERS.items() if not src.has(f)
    ]
    return sec


def provider() -> page.SectionProvider:
    """The stereo section's provider for the report (after the risk section). Its metrics files
    are in the appendix in full (the section shows a part of stereo.json)."""
    return page.SectionProvider(
        name="stereo",  # its page, reports/pages/stereo.md (no headline numbers)
        section=section,
        figures={stem: prose(stem) for stem in FIGURE_STEMS},
        figure_pattern=NEVER,
    )
