"""The stereo part of the report: SGM depth accuracy by range, the learned stereo network beside
SGM, the SGM variants, stereo-pair fault detection per rule, and the camera-resolution study.
Entry point: :func:`provider`.

Reads the metrics files of :data:`WRITERS` (their keys: ``<group>/<metric>`` and
``<source>/<mask>/<metric>``, with an interval's ``<key>_lo`` / ``<key>_hi`` beside a key). The
learned network refines SGM on SGM's valid pixels, so both estimate the same pixels: stereo.json's
``common`` and ``own`` masks hold the same numbers, shown once (``own``, with the density; the
paired differences on ``common``). Notes and paragraphs are the macros of
``templates/report.md.j2`` (:func:`prose`). A missing file or key is an ``n/a`` cell.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from traffictwin.report import model as page
from traffictwin.report.acceptance import POINTER as ACCEPTANCE_POINTER
from traffictwin.report.model import NA, NEVER, Cell, Table, fmt_value, json_number
from traffictwin.report.prose import oneline, template_macro

TITLE = "Stereo — SGM and the learned stereo network's range accuracy, stereo-pair fault detection"
DISPARITY_FILE = "disparity.json"
ORB_FILE = "orb.json"
RESOLUTION_FILE = "stereo_resolution.json"
STEREO_FILE = "stereo.json"
VARIANTS_FILE = "sgm_variants.json"
#: what writes each metrics file the section reads
WRITERS = {
    DISPARITY_FILE: "stage disparity has not run",
    STEREO_FILE: "stage stereo_learned has not run",
    VARIANTS_FILE: "stage sgm_variants has not run",
    ORB_FILE: "stage orb_filter has not run",
    RESOLUTION_FILE: "run `python -m benchmarks.stereo_resolution`",
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
GROUP_LABELS = {"all": "all pairs", "fault_none": "fault-free pairs", "test": "test split"}

#: a table row (or column): (label, metric key, format)
Row = tuple[str, str, str]
ACCURACY_COLUMNS: tuple[Row, ...] = (
    ("bad-2 (> 2 px)", "bad2", "pct"),
    ("D1 (> 3 px and > 5 %)", "d1", "pct"),
    ("density", "density", "pct"),
    ("EPE [px]", "epe", "g4"),
)
RANGE_COLUMNS = (("gt_pixels", "int"), ("valid_share", "pct"))
RANGE_COLUMNS += (("relerr_median", "pct"), ("relerr_p90", "pct"))
#: the detection rates per rule in orb.json, their column headers
FAULTS = ("delay_detection", "vertical_detection", "false_alarm")
DETECTION = ("delay faults detected", "vertical shifts detected", "false alarms (fault-free)")
SWEEP = ("false_alarm", "delay_detection", "vertical_detection")  # the sweep's columns
#: the range error by distance, as the resolution study and the learned stereo show it
RANGE_ROWS: tuple[Row, ...] = (
    ("0–10 m: median range error", "z0-10m_relerr_median", "pct"),
    ("10–30 m: median range error", "z10-30m_relerr_median", "pct"),
    ("30–90 m: median range error", "z30-90m_relerr_median", "pct"),
    ("30–90 m: 90th percentile", "z30-90m_relerr_p90", "pct"),
)


#: the rows of the learned-stereo comparison: (label, metric key, format)
STEREO_ROWS: tuple[Row, ...] = (
    ("end-point error [px]", "epe", "f3"),
    ("bad-1 (> 1 px)", "bad1", "pct"),
    ("bad-2 (> 2 px)", "bad2", "pct"),
    ("density (share of GT pixels with an estimate)", "density", "pct"),
    *RANGE_ROWS,
    ("objects at the critical distances: median range error", "crit_obj_relerr_median", "pct"),
    ("objects at the critical distances: 90th percentile", "crit_obj_relerr_p90", "pct"),
    ("objects at the critical distances: share estimated", "crit_obj_density", "pct"),
)
#: the rows of the generalisation and chosen-variant tables, on each source's own pixels
GENERALISATION_ROWS = tuple(STEREO_ROWS[i] for i in (0, 1, 8, 9))
GENERALISATION_SOURCES = {"sgm": "SGM", "learned": "full network", "holdout": "without them"}
#: the paired differences shown, on the pixels both sources estimate
DIFF_ROWS = tuple(r for r in STEREO_ROWS if r[1] in ("epe", "crit_obj_relerr_median"))
#: the SGM variants table's columns: (header, figure key, format)
VARIANT_COLUMNS: tuple[Row, ...] = (
    ("EPE [px]", "epe", "f3"),
    ("bad-1", "bad1", "pct"),
    ("density", "density", "pct"),
    ("critical objects: median range error", "crit_obj_relerr_median", "pct"),
    ("critical objects: p90", "crit_obj_relerr_p90", "pct"),
    ("critical objects: share estimated", "crit_obj_density", "pct"),
)
#: how many variants the table lists beyond the configured and the chosen one
VARIANTS_SHOWN = 6


def prose(name: str, **context: Any) -> str:
    """Macro ``name`` of ``templates/report.md.j2`` filled with ``context``, on one line."""
    return oneline(template_macro(TEMPLATES, "report.md.j2", name)(**context))


def ci_cell(src: page.Sources, file: str, key: str, fmt: str = "pct") -> Cell:
    """``[lo, hi]`` of ``<key>_lo`` / ``<key>_hi`` in ``file``: a derived cell (n/a if absent)."""
    lo, hi = json_number(src.get(file, f"{key}_lo")), json_number(src.get(file, f"{key}_hi"))
    if lo is None or hi is None:
        return Cell(NA, title=f"no interval in reports/metrics/{file}: {key}_lo/_hi")
    return Cell(
        f"[{fmt_value(lo, fmt)}, {fmt_value(hi, fmt)}]",
        value=[lo, hi],
        derived=f"95 % cluster-bootstrap interval, metrics/{file}#{key}_lo/_hi",
    )


def value_ci(src: page.Sources, file: str, key: str, fmt: str = "pct") -> list[Cell]:
    """The number at ``file``#``key`` and its interval."""
    return [src.cell(file, key, fmt), ci_cell(src, file, key, fmt)]


def _edges(name: str, prefix: str) -> list[str]:
    """The two edges of a bin name after ``prefix`` (``p``: the decimal point):
    ``_edges("z0p5-2", "z")`` -> ``["0.5", "2"]``."""
    return name.removeprefix(prefix).replace("p", ".").split("-", 1)


def _keys(src: page.Sources, file: str, pattern: str) -> list[str]:
    """The first group of ``pattern`` over the keys of ``file`` that match it, in file order."""
    data = src.metrics.get(file)
    return [m.group(1) for k in data or {} if (m := re.fullmatch(pattern, k))]


def compare_table(
    src: page.Sources,
    file: str,
    key: str,
    sources: Mapping[str, str],
    rows: Sequence[Row],
    diffs: Mapping[str, str],
    **table: Any,
) -> Table:
    """Rows = quantities, a value and an interval column per source; ``key``: the metrics key
    with ``{source}`` and ``{key}`` placeholders. Then the paired differences of
    :data:`DIFF_ROWS`, one row each per ``diffs`` entry (``{what: key with {key}}``, e.g.
    ``"learned − SGM"``) in the last source's columns; ``table``: :class:`Table`'s other fields."""
    heads = [h for name in sources.values() for h in (name, f"{name} 95 % CI")]
    t = Table(columns=["quantity", *heads], **table)
    for label, k, fmt in rows:
        cells = [c for s in sources for c in value_ci(src, file, key.format(source=s, key=k), fmt)]
        t.rows.append([Cell(label), *cells])
    blank = [Cell("")] * (len(heads) - 2)
    for what, diff in diffs.items():
        for label, k, fmt in DIFF_ROWS:
            cells = value_ci(src, file, diff.format(key=k), fmt)
            t.rows.append([Cell(f"{label} ({what})"), *blank, *cells])
    return t


def disparity_tables(src: page.Sources) -> list[Table]:
    """SGM disparity accuracy per group, then the relative depth error per range bin."""
    if not src.has(DISPARITY_FILE):
        return []
    groups = [g for g in GROUP_LABELS if src.get(DISPARITY_FILE, f"{g}/bad2") is not None]
    cols = [  # the metrics this file has (an older stage version wrote fewer)
        c
        for c in ACCURACY_COLUMNS
        if any(src.get(DISPARITY_FILE, f"{g}/{c[1]}") is not None for g in groups)
    ]
    acc = Table(
        "SGM disparity accuracy against the exact disparity (reports/metrics/disparity.json)",
        ["pairs", *[label for label, _, _ in cols]],
        anchor="stereo-accuracy",
        note=prose("accuracy"),
    )
    for g in groups:
        cells = [src.cell(DISPARITY_FILE, f"{g}/{m}", f) for _, m, f in cols]
        acc.rows.append([Cell(GROUP_LABELS[g]), *cells])
    rng = Table(
        "SGM range error |Z − Z_gt| / Z_gt by GT distance (Z = fx·B / d; reports/metrics/disparity.json)",
        ["pairs", "GT distance", "GT pixels", "valid share", "median", "90th percentile"],
        anchor="stereo-range-error",
        note=prose("range_error"),
    )
    for g in [g for g in ("fault_none", "all") if g in groups]:
        pattern = rf"{re.escape(g)}/(z[0-9p]+-[0-9p]+m)_relerr_median"
        for b in _keys(src, DISPARITY_FILE, pattern):
            cells = [src.cell(DISPARITY_FILE, f"{g}/{b}_{m}", f) for m, f in RANGE_COLUMNS]
            lo, hi = _edges(b[:-1], "z")
            rng.rows.append([Cell(GROUP_LABELS[g]), Cell(f"{lo}–{hi} m"), *cells])
    return [t for t in (acc, rng) if t.rows]


def fault_tables(src: page.Sources) -> list[Table]:
    """Detection / false-alarm rates per rule with intervals and the pairs they are over (the
    last row), delay detection by speed, the valid-share threshold sweep."""
    rules = [r for r in RULE_LABELS if src.get(ORB_FILE, f"rule_{r}/false_alarm") is not None]
    if not rules:  # no orb.json, or one of an older stage version: the data section shows it
        return []
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
    bins = _keys(src, ORB_FILE, r"rule_orb/(delay_detection_v[0-9p]+-[0-9p]+)")
    bins.sort(key=lambda b: float(_edges(b, "delay_detection_v")[0]))
    speed = Table(
        "Delay faults detected by subject speed (reports/metrics/orb.json)",
        ["rule"] + ["v {}–{} m/s".format(*_edges(b, "delay_detection_v")) for b in bins],
        anchor="stereo-delay-by-speed",
        note=prose("by_speed"),
    )
    speed.rows.append(
        [Cell("delay faults (count)")]
        + [src.cell(ORB_FILE, f"rule_orb/{b}_n", "int") for b in bins]
    )
    for r in rules:
        cells = [src.cell(ORB_FILE, f"rule_{r}/{b}", "pct") for b in bins]
        speed.rows.append([Cell(RULE_LABELS[r]), *cells])
    sweep = Table(
        "Valid-share rule: threshold sweep (reports/metrics/orb.json)",
        ["flag when valid share <", "false alarms", "delay detected", "vertical detected"],
        anchor="stereo-valid-share-sweep",
    )
    pattern = r"sweep/min_valid_share_([0-9p]+)_false_alarm_rate"
    for th in sorted(_keys(src, ORB_FILE, pattern), key=lambda x: float(x.replace("p", "."))):
        pre = f"sweep/min_valid_share_{th}"
        cells = [src.cell(ORB_FILE, f"{pre}_{k}_rate", "pct") for k in SWEEP]
        sweep.rows.append([Cell(f"threshold {th.replace('p', '.')}"), *cells])
    return [det] + ([speed] if bins else []) + ([sweep] if sweep.rows else [])


def resolution_tables(src: page.Sources) -> list[Table]:
    """The camera-resolution study: one column per width; the paired differences between widths
    (the last rows, in the column of the larger width)."""
    data = src.metrics.get(RESOLUTION_FILE)
    if not isinstance(data, dict):
        return []
    widths = sorted({int(m.group(1)) for k in data if (m := re.match(r"^w(\d+)/", k))})
    if not widths:
        return []
    t = Table(
        "Camera resolution study: SGM range error at the critical distance and SGM cost "
        "(reports/metrics/stereo_resolution.json, benchmarks/stereo_resolution.py)",
        ["quantity", *[f"width {w} px" for w in widths]],
        anchor="stereo-resolution",
        note=prose("resolution"),
    )
    lo, hi = (json_number(data.get(f"study/critical_{e}_m")) for e in ("lo", "hi"))
    crit = f"{lo:g}–{hi:g} m" if lo is not None and hi is not None else "the critical distance"
    rows = [
        ("image height [px]", "height", "int"),
        ("SGM search range [px]", "num_disparities", "int"),
    ]
    rows += [
        (f"GT disparity at {z:g} m [px]", f"gt_disparity_px_at_{z:g}m", "f2")
        for z in (lo, hi)
        if z is not None
    ]
    rows += [
        (f"objects at {crit}: median range error", "crit_obj_relerr_median", "pct"),
        (f"objects at {crit}: 90th percentile", "crit_obj_relerr_p90", "pct"),
        (f"objects at {crit}: valid share", "crit_obj_valid_share", "pct"),
        (f"all surfaces at {crit}: median range error", "crit_all_relerr_median", "pct"),
        *RANGE_ROWS,
        ("SGM time per frame [ms]", "sgm_ms_median", "f1"),
        ("rendering time per frame [ms]", "render_ms_median", "f1"),
    ]
    for label, key, fmt in rows:
        keys = [f"w{w}/{key}" for w in widths]
        t.rows.append([Cell(label)] + [src.cell(RESOLUTION_FILE, k, fmt) for k in keys])
        if key in ("crit_obj_relerr_median", "crit_all_relerr_median"):  # with their intervals
            t.rows.append(
                [Cell(f"{label}, 95 % CI")] + [ci_cell(src, RESOLUTION_FILE, k) for k in keys]
            )
    pattern = r"(diff_w(\d+)_minus_w(\d+)/(crit_obj|crit_all)_relerr_median)"
    for m in [m for k in sorted(data) if (m := re.fullmatch(pattern, k))]:
        what = "objects" if m.group(4) == "crit_obj" else "all surfaces"
        label = f"{what} at {crit}: median range error, width {m.group(2)} − {m.group(3)} px"
        for name, c in (
            (label, src.cell(RESOLUTION_FILE, m.group(1), "pct")),
            (f"{label}, 95 % CI", ci_cell(src, RESOLUTION_FILE, m.group(1))),
        ):
            cells = [c if f"{w}" == m.group(2) else Cell("") for w in widths]
            t.rows.append([Cell(name), *cells])
    return [t]


def learned_tables(src: page.Sources) -> list[Table]:
    """SGM vs the learned stereo network on the test split with their paired differences, and
    the generalisation to unseen road templates."""
    if not src.has(STEREO_FILE):
        return []
    t = compare_table(
        src,
        STEREO_FILE,
        "{source}/own/{key}",
        {"sgm": "SGM", "learned": "learned"},
        STEREO_ROWS,
        {"learned − SGM": "diff_learned_minus_sgm/common/{key}"},
        title="Learned stereo network vs SGM, fault-free test frames (reports/metrics/stereo.json)",
        anchor="stereo-learned",
        note=prose("learned"),
    )
    return [t, *generalisation_tables(src)]


def variant_tables(src: page.Sources) -> list[Table]:
    """SGM variants on validation (the configured matcher, the chosen one and the best others by
    the rule's criterion) and the chosen one against the configured matcher on test
    (``sgm_variants.json``)."""
    figs = src.get(VARIANTS_FILE, "validation.variants")
    if not isinstance(figs, dict) or not figs:
        return []
    chosen = str(src.get(VARIANTS_FILE, "choice.chosen"))
    configured = str(src.get(VARIANTS_FILE, "choice.configured"))
    guard = json_number(figs.get(configured, {}).get("crit_obj_density"))

    def crit(name: str) -> float:
        v = json_number(figs[name].get("crit_obj_relerr_median"))
        return float("inf") if v is None else v

    def role(n: str) -> str:
        if n in (chosen, configured):
            return " and ".join(
                r for r, x in (("configured", configured), ("chosen", chosen)) if x == n
            )
        density = json_number(figs[n].get("crit_obj_density"))
        below = guard is not None and density is not None and density < guard
        return "below the density guard" if below else ""

    others = sorted((n for n in figs if n not in (chosen, configured)), key=crit)
    names = [configured] + ([chosen] if chosen != configured else []) + others[:VARIANTS_SHOWN]
    why = src.get(VARIANTS_FILE, "test.why")
    t = Table(
        f"SGM variants on {src.get(VARIANTS_FILE, 'validation.frames')} fault-free validation "
        f"frames, each variant's own estimated pixels ({len(figs)} scored; "
        "reports/metrics/sgm_variants.json)",
        ["variant", "role"] + [h for h, _, _ in VARIANT_COLUMNS],
        anchor="stereo-sgm-variants",
        note=prose("variants", rule=src.get(VARIANTS_FILE, "choice.rule"), why=why),
    )
    for n in names:
        key = f"validation.variants.{n}"
        cells = [src.cell(VARIANTS_FILE, f"{key}.{k}", fmt) for _, k, fmt in VARIANT_COLUMNS]
        t.rows.append([Cell(n), Cell(role(n)), *cells])
    if why:
        return [t]
    frames, seqs = (src.get(VARIANTS_FILE, f"test.test/{k}") for k in ("frames", "sequences"))
    c = compare_table(
        src,
        VARIANTS_FILE,
        "test.{source}/own/{key}",
        {"configured": "configured", "chosen": "chosen"},
        GENERALISATION_ROWS,
        {"chosen − configured": "test.diff_chosen_minus_configured/common/{key}"},
        title=f"SGM: the chosen variant ({chosen}) vs the configured matcher ({configured}) on the "
        "fault-free test frames, each one's own estimated pixels (reports/metrics/sgm_variants.json)",
        anchor="stereo-sgm-chosen",
        note=prose("chosen", frames=frames, sequences=seqs),
    )
    return [t, c]


def generalisation_tables(src: page.Sources) -> list[Table]:
    """The network trained without some road templates beside the full one and SGM on those
    templates' test frames (``stereo.json`` ``generalisation``), with the paired differences."""
    g = src.get(STEREO_FILE, "generalisation")
    if not isinstance(g, dict):
        return []
    names = ", ".join(str(t) for t in g.get("templates") or [])
    title = (
        f"Learned stereo on unseen road templates ({names}): fault-free test frames of those "
        "templates, each source's own estimated pixels (reports/metrics/stereo.json)"
    )
    if g.get("why"):
        t = Table(title, ["quantity", "value"], anchor="stereo-generalisation")
        t.rows.append([Cell("not measured"), Cell(str(g["why"]))])
        return [t]
    diff = "generalisation.diff_holdout_minus_{other}/common/{{key}}"
    t = compare_table(
        src,
        STEREO_FILE,
        "generalisation.{source}/own/{key}",
        GENERALISATION_SOURCES,
        GENERALISATION_ROWS,
        {
            "without − full network": diff.format(other="learned"),
            "without − SGM": diff.format(other="sgm"),
        },
        title=title,
        anchor="stereo-generalisation",
        note=prose(
            "generalisation", frames=g.get("test/frames"), sequences=g.get("test/sequences")
        ),
    )
    return [t]


def section(src: page.Sources, figures: list[page.Figure]) -> page.Section:
    """The stereo section: disparity and range accuracy, the learned network, the SGM variants,
    fault detection, the resolution study; a pointer to the acceptance table where stereo.json
    has targets."""
    sec = page.Section(TITLE, paragraphs=[prose("intro")], figures=figures)
    if (targets := src.get(STEREO_FILE, "targets")) and isinstance(targets, dict):
        sec.paragraphs.append(ACCEPTANCE_POINTER)
    builds = (disparity_tables, learned_tables, variant_tables, fault_tables, resolution_tables)
    sec.tables = [t for build in builds for t in build(src)]
    sec.paragraphs += [
        prose("missing", file=f, why=w) for f, w in WRITERS.items() if not src.has(f)
    ]
    return sec


def provider() -> page.SectionProvider:
    """The stereo section's provider for the report (after the risk section)."""
    return page.SectionProvider(
        name="stereo",  # its page, reports/pages/stereo.md (no headline numbers)
        section=section,
        figures={stem: prose(stem) for stem in FIGURE_STEMS},
        figure_pattern=NEVER,
        shown_files=r"stereo_resolution\.json|stereo\.json|sgm_variants\.json",
    )
