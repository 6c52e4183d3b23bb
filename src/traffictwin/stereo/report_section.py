"""The stereo part of the report: stereo-pair fault detection per rule, and the learned stereo
network beside SGM. Entry point: :func:`provider`.

Reads ``orb.json`` (stage orb_filter; keys ``rule_<rule>/<metric>``) and ``stereo.json`` (stage
stereo_learned; keys ``<source>/<mask>/<metric>``), an interval as ``<key>_lo`` / ``<key>_hi``
beside a key; the rest of both files is in the appendix. The prose is the macros of
``templates/report.md.j2``. A missing file or key is an ``n/a`` cell.
"""

from __future__ import annotations

from pathlib import Path

from traffictwin.report import model as page
from traffictwin.report.acceptance import POINTER as ACCEPTANCE_POINTER
from traffictwin.report.model import NEVER, Cell, Table, json_number
from traffictwin.report.prose import macro_prose

TITLE = "Stereo — SGM and the learned stereo network's range accuracy, stereo-pair fault detection"
ORB_FILE = "orb.json"
STEREO_FILE = "stereo.json"
#: the figures the section shows, in order; their captions are macros of the same name
FIGURE_STEMS = ("stereo_learned_example", "train_stereo", "stereo_resolution")
TEMPLATES = Path(__file__).parent / "templates"
#: rule key in orb.json -> row label
RULE_LABELS = {
    "orb_paper": "ORB, paper's rule over all cross-checked matches",
    "orb": "ORB, robust rule over reliable matches",
    "valid_share": "SGM valid share below threshold",
    "orb_or_valid_share": "robust ORB OR valid share",
}
#: the detection rates per rule in orb.json: (key, column header)
FAULTS = (
    ("delay_detection", "delay faults detected"),
    ("vertical_detection", "vertical shifts detected"),
    ("false_alarm", "false alarms (fault-free)"),
)
#: the rows of the learned-stereo comparison: (label, metric key, format)
STEREO_ROWS: tuple[tuple[str, str, str], ...] = (
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


#: macro ``name`` of ``templates/report.md.j2`` filled with ``context``, on one line
prose = macro_prose(TEMPLATES, "report.md.j2")


def value_ci(src: page.Sources, file: str, key: str, fmt: str = "pct") -> list[Cell]:
    """The number at ``file``#``key`` and its interval ``[<key>_lo, <key>_hi]`` (a derived cell)."""
    lo, hi = (json_number(src.get(file, f"{key}_{b}")) for b in ("lo", "hi"))
    where = f"metrics/{file}#{key}_lo/_hi"
    why = f"no interval in reports/metrics/{file}: {key}_lo/_hi"
    ci = page.span_cell(lo, hi, fmt, f"95 % cluster-bootstrap interval, {where}", why)
    return [src.cell(file, key, fmt), ci]


def fault_table(src: page.Sources) -> Table | None:
    """Detection / false-alarm rates per rule with intervals, and the pairs they are over (the
    last row); None without the rules in orb.json (the data section shows an older file)."""
    rules = [r for r in RULE_LABELS if src.get(ORB_FILE, f"rule_{r}/false_alarm") is not None]
    if not rules:
        return None
    det = Table(
        "Stereo-pair fault detection per rule (reports/metrics/orb.json)",
        ["rule", "drops pairs"] + [h for _, name in FAULTS for h in (name, "95 % CI")],
        anchor="stereo-fault-detection",
        headline=True,
        note=prose("detection"),
    )
    for r in rules:
        drops = "yes" if src.get(ORB_FILE, f"rule_{r}/configured") == 1 else ""
        cells = [c for k, _ in FAULTS for c in value_ci(src, ORB_FILE, f"rule_{r}/{k}")]
        det.rows.append([Cell(RULE_LABELS[r]), Cell(drops), *cells])
    counts = [src.cell(ORB_FILE, f"rule_orb/{k}_n", "int") for k, _ in FAULTS]
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
    acceptance table where stereo.json has targets; which stage has not run, where a file is
    missing."""
    sec = page.Section(TITLE, paragraphs=[prose("intro")], figures=figures)
    if isinstance(src.get(STEREO_FILE, "targets"), dict):
        sec.paragraphs.append(ACCEPTANCE_POINTER)
    sec.tables = [t for t in (fault_table(src), learned_table(src)) if t is not None]
    for file, stage in ((STEREO_FILE, "stereo_learned"), (ORB_FILE, "orb_filter")):
        sec.paragraphs += [] if src.has(file) else [prose("missing", file=file, stage=stage)]
    return sec


def provider() -> page.SectionProvider:
    """The stereo section's provider for the report (after the risk section); its page
    reports/pages/stereo.md, no headline numbers."""
    return page.SectionProvider(
        name="stereo",
        section=section,
        figures={stem: prose(stem) for stem in FIGURE_STEMS},
        figure_pattern=NEVER,
    )
